"""``schemas.json_body.parse_body`` against ``json_format.ParseDict``, the reference it
stands in for: on every body it takes, the same payload bytes; on every body ParseDict
refuses, None (so the caller's ParseDict gives the same refusal).

Hypothesis draws the messages and the hostile values (seeded from the run's seed by
conftest.py, which prints it).
"""

from __future__ import annotations

import math

import pytest
from google.protobuf import json_format
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas.events import EVENT_TYPES
from schemas.json_body import parse_body

#: the types the fast path takes (every field a double, a list of doubles, a string, a
#: timestamp or a message of those)
FAST = ("scan", "frame_transform", "joint_reading", "clock", "joint_estimate")
SETTINGS = settings(max_examples=300, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])


def reference(body, cls) -> bytes | None:
    """ParseDict's payload for ``body``, or None when it refuses it."""
    try:
        return json_format.ParseDict(body, cls()).SerializeToString(deterministic=True)
    except Exception:  # noqa: BLE001 - ParseError, ValueError, TypeError: all refusals
        return None


def assert_agrees(body, cls) -> bool:
    """Check ``parse_body`` against ParseDict on ``body``; whether the fast path took it."""
    ours = parse_body(body, cls)
    expected = reference(body, cls)
    if expected is None:
        assert ours is None, f"ParseDict refuses {body!r}, the fast path took it"
    elif ours is not None:
        assert ours.SerializeToString(deterministic=True) == expected
    return ours is not None


doubles = st.floats(allow_nan=True, allow_infinity=True)
ascii_text = st.text(st.characters(max_codepoint=127), max_size=12)
seconds = st.integers(-62_135_596_800, 253_402_300_799)      # Timestamp's range
nanos = st.integers(0, 999_999_999)


def _fill(message, draw) -> None:
    for field in message.DESCRIPTOR.fields:
        if not draw(st.booleans()):
            continue
        if field.message_type is not None:
            sub = getattr(message, field.name)
            if field.message_type.full_name == "google.protobuf.Timestamp":
                sub.seconds, sub.nanos = draw(seconds), draw(nanos)
            else:
                sub.SetInParent()
                _fill(sub, draw)
        elif field.is_repeated:
            getattr(message, field.name).extend(draw(st.lists(doubles, max_size=20)))
        elif field.type == field.TYPE_STRING:
            setattr(message, field.name, draw(ascii_text))
        else:
            setattr(message, field.name, draw(doubles))


@st.composite
def canonical(draw):
    """(type, body) of a random message of a fast type, as MessageToDict writes it."""
    type_name = draw(st.sampled_from(FAST))
    message = EVENT_TYPES[type_name]()
    _fill(message, draw)
    return type_name, json_format.MessageToDict(message, preserving_proto_field_name=True)


HOSTILE = st.one_of(
    st.none(), st.booleans(), st.integers(-2**70, 2**70), doubles, st.text(max_size=6),
    st.sampled_from(["nan", "NaN", "Infinity", "-Infinity", "inf", "-inf", "NAN", "1e400",
                     "0x10", " 1.5", "1_0", "", "\ud800", "é",
                     "2026-11-01T00:00:00Z", "2026-11-01T00:00:00.5Z",
                     "2026-11-01T00:00:00.123456789Z", "2026-11-01T00:00:00.1234567891Z",
                     "2026-11-01t00:00:00Z", "2026-11-01T00:00:60Z", "2026-1-01T00:00:00Z",
                     "0000-01-01T00:00:00Z", "9999-12-31T23:59:59.999999999Z",
                     "2026-02-30T00:00:00Z", "2026-11-01T00:00:00+01:00",
                     "2026-11-01T00:00:00ZZ", "2026-11-01 00:00:00Z"]),
    st.lists(st.one_of(doubles, st.sampled_from(["NaN", "nan", "Infinity", "1.5", "x"]),
                       st.integers(), st.none(), st.booleans()), max_size=6),
    st.dictionaries(st.sampled_from(["x", "w", "seconds", "position", "bogus"]),
                    st.one_of(doubles, st.integers(), st.none()), max_size=3),
)


@st.composite
def spoiled(draw):
    """A canonical body with one value, at any depth, replaced by a hostile one, or a key
    added (an unknown name, or a field's JSON name beside its proto name)."""
    type_name, body = draw(canonical())
    path = [body]
    node = body
    while isinstance(node, dict) and node and draw(st.booleans()):
        key = draw(st.sampled_from(sorted(node)))
        if not isinstance(node[key], dict):
            break
        node = node[key]
        path.append(node)
    if node and draw(st.booleans()):
        node[draw(st.sampled_from(sorted(node)))] = draw(HOSTILE)
    else:
        fields = EVENT_TYPES[type_name].DESCRIPTOR.fields
        name = draw(st.sampled_from(["bogus", *(f.json_name for f in fields)]))
        node[name] = draw(HOSTILE)
    return type_name, body


@SETTINGS
@given(canonical())
def test_a_canonical_body_takes_the_fast_path_with_parsedicts_bytes(drawn):
    type_name, body = drawn
    assert assert_agrees(body, EVENT_TYPES[type_name]), f"not taken: {body!r}"


@SETTINGS
@given(spoiled())
def test_a_hostile_value_is_taken_only_where_parsedict_gives_the_same(drawn):
    type_name, body = drawn
    assert_agrees(body, EVENT_TYPES[type_name])


@pytest.mark.parametrize(("body", "taken"), [
    ({"ranges": ["NaN", 2.5, "Infinity", "-Infinity", "1.5"]}, True),
    ({"ranges": [math.nan]}, False),            # a bare NaN: ParseDict refuses it
    ({"ranges": ["nan"]}, False),               # ParseDict's one refused spelling
    ({"ranges": [1]}, False),                   # integers: left to ParseDict
    ({"start_angle": math.inf}, False),
    ({"start_angle": "-Infinity"}, True),
    ({"startAngle": 0.5}, False),               # the JSON name: left to ParseDict
    ({"startAngle": 0.5, "start_angle": 0.5}, False),   # ParseDict refuses both names
    ({"timestamp": "2026-11-01T00:00:00.000000001Z", "frame_id": "s"}, True),
    ({"timestamp": "2026-11-01T01:00:00+01:00"}, False),
    ({"pose": {"orientation": {}}}, True),      # an empty message is still set
    ({"pose": []}, False),
    ({"frame_id": None}, False),
])
def test_named_cases(body, taken):
    assert assert_agrees(body, EVENT_TYPES["scan"]) is taken


def test_types_with_other_shapes_are_left_to_parsedict():
    """Enums, integers, maps and oneofs are not taken at all."""
    for type_name in ("location_fix", "assay", "reclaim_cut", "lot_declared"):
        assert parse_body({}, EVENT_TYPES[type_name]) is None

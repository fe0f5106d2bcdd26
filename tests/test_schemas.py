"""Schemas: generated code matches the protos, the registry, envelopes and JSON lines."""

from __future__ import annotations

import filecmp
import math

import pytest
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix

from schemas import generate, pb
from schemas.events import (
    EVENT_TYPES,
    Event,
    Malformed,
    decode_attachment,
    encode_attachment,
    event_from_sample,
    key_expr,
    make_event,
    parse_key_expr,
    payload_valid_time_ns,
    set_timestamp_ns,
    timestamp_ns,
    type_of_message,
)
from schemas.jsonl import decode_line, encode_line
from schemas.validate import check_event


def test_committed_pb2_matches_a_fresh_generation(tmp_path):
    generated = generate.generate(output_root=tmp_path)
    assert generated, "no proto files found"
    for relative in generated:
        committed = generate.OUTPUT_ROOT / relative
        assert committed.exists(), f"{relative} is not committed; run `make schemas`"
        assert filecmp.cmp(committed, tmp_path / relative, shallow=False), (
            f"schemas/{relative} differs from what protoc generates; run `make schemas`")


def test_every_domain_message_is_an_event_type_with_a_valid_time():
    helpers = {"Vector3", "Quaternion", "Mount"}
    ours = {m.full_name for m in pb.DESCRIPTOR.message_types_by_name.values()
            if m.name not in helpers}
    registered = {cls.DESCRIPTOR.full_name for cls in EVENT_TYPES.values()}
    assert ours <= registered
    assert {"foxglove.LaserScan", "foxglove.LocationFix", "foxglove.FrameTransform"} <= registered
    for name, cls in EVENT_TYPES.items():
        message = cls()
        assert type_of_message(message) == name
        assert payload_valid_time_ns(name, message) == 0


def test_type_names_are_snake_case_of_the_message():
    import re

    exceptions = {"scan": "laser_scan"}  # the contract names foxglove.LaserScan events "scan"
    for name, cls in EVENT_TYPES.items():
        snake = re.sub(r"(?<!^)(?=[A-Z])", "_", cls.DESCRIPTOR.name).lower()
        assert snake == exceptions.get(name, name)


@pytest.mark.parametrize("t_ns", [0, 1, 999_999_999, 1_793_491_200_123_456_789, -1])
def test_timestamp_ns_round_trip(t_ns):
    m = pb.Clock()
    set_timestamp_ns(m.time, t_ns)
    assert 0 <= m.time.nanos < 1_000_000_000
    assert timestamp_ns(m.time) == t_ns


def test_key_expressions():
    key = key_expr("demo", "scan", "bwr1.scanner")
    assert key == "stockpile/demo/@v1/scan/bwr1.scanner"
    assert parse_key_expr(key) == ("demo", "scan", "bwr1.scanner")
    with pytest.raises(ValueError):
        key_expr("demo", "scan", "bad/source")
    with pytest.raises(ValueError):
        key_expr("demo", "nope", "a")
    with pytest.raises(ValueError):
        parse_key_expr("stockpile/demo/@v2/scan/x")


def test_attachment_round_trip_and_garbage():
    data = encode_attachment(2**40, 12345, -5)
    assert decode_attachment(data) == (2**40, 12345, -5)
    with pytest.raises(ValueError):
        decode_attachment(data[:-1])
    m = pb.Clock()
    set_timestamp_ns(m.time, 10)
    payload = m.SerializeToString()
    event = event_from_sample("stockpile/demo/@v1/clock/sim.clock", payload, encode_attachment(1, 2, 10))
    assert event == Event("clock", "sim.clock", 1, 2, 10, payload)
    broken = event_from_sample("stockpile/demo/@v1/clock/sim.clock", payload, b"\x01\x02")
    assert isinstance(broken, Malformed) and broken.reason.startswith("bad_attachment")
    assert isinstance(event_from_sample("other/key", payload, None), Malformed)


def _examples():
    scan = LaserScan(frame_id="bwr1/scanner", start_angle=math.radians(-90), end_angle=math.radians(90))
    scan.ranges.extend([1.5 + i * 0.01 for i in range(180)] + [math.nan])
    set_timestamp_ns(scan.timestamp, 1_000_000_001)
    fix = LocationFix(latitude=-20.3, longitude=118.6, altitude=6.0)
    fix.position_covariance.extend([0.1, 0, 0, 0, 0.1, 0, 0, 0, 0.3])
    set_timestamp_ns(fix.timestamp, 5)
    tf = FrameTransform(parent_frame_id="site", child_frame_id="bwr1/wheel")
    tf.rotation.w = 1.0
    tf.translation.x = 3.25
    set_timestamp_ns(tf.timestamp, 7)
    assay = pb.Assay(assay_id="A1", lot_id="L1", status=pb.FINAL, lab_id="lab1",
                     moisture_pct=5.5, bulk_density_t_m3=2.4)
    assay.analytes.update({"SiO2": 4.1, "Fe": 62.2, "LOI": 5.0})
    set_timestamp_ns(assay.window_start, 100)
    set_timestamp_ns(assay.window_end, 200)
    set_timestamp_ns(assay.reported_time, 10**13)
    cut = pb.ReclaimCut(pile_id="P1", cut_id="C1", bench_id="B1", machine_id="bwr1", travel_m=20,
                        luff_rad=-0.1, slew_start_rad=0.5, slew_end_rad=1.2, tonnes=1500.5)
    set_timestamp_ns(cut.start_time, 1_000)
    set_timestamp_ns(cut.end_time, 2_000)
    machine = pb.MachineDeclared(machine_id="bwr1", kind=pb.BUCKET_WHEEL_RECLAIMER, l5_m=50)
    machine.scanner.rotation.w = 1.0
    set_timestamp_ns(machine.time, 3)
    return [scan, fix, tf, assay, cut, machine]


@pytest.mark.parametrize("message", _examples(), ids=lambda m: m.DESCRIPTOR.name)
def test_json_line_round_trip(message):
    event = make_event(message, source="test.src", epoch=3, seq=9)
    check_event(event)
    line = encode_line(event.type, event.source, event.epoch, event.seq, event.valid_time_ns,
                       event.payload, 42)
    back = decode_line(line)
    assert isinstance(back, Event), back
    assert back == Event(event.type, event.source, 3, 9, event.valid_time_ns, event.payload, 42)
    assert encode_line(back.type, back.source, back.epoch, back.seq, back.valid_time_ns,
                       back.payload, 42) == line


def test_json_lines_accept_camel_case_and_emit_proto_names():
    line = ('{"type":"reclaim_cut","source":"bwr1.control","epoch":1,"seq":0,'
            '"valid_time_ns":2000000000,"body":{"pileId":"P1","cutId":"C1",'
            '"endTime":"1970-01-01T00:00:02Z","slewStartRad":0.5}}')
    event = decode_line(line)
    assert isinstance(event, Event)
    message = check_event(event)
    assert message.pile_id == "P1" and message.slew_start_rad == 0.5
    out = encode_line(event.type, event.source, event.epoch, event.seq, event.valid_time_ns,
                      event.payload)
    assert '"slew_start_rad":0.5' in out and '"end_time":"1970-01-01T00:00:02Z"' in out


def test_map_fields_serialise_deterministically():
    a = pb.Assay(assay_id="A", lot_id="L")
    b = pb.Assay(assay_id="A", lot_id="L")
    for k in ("Fe", "SiO2", "P"):
        a.analytes[k] = 1.0
    for k in ("P", "SiO2", "Fe"):
        b.analytes[k] = 1.0
    assert make_event(a, source="x", epoch=0, seq=0).payload == make_event(b, source="x", epoch=0, seq=0).payload

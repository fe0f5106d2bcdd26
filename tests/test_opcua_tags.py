"""The PLC tag map and the machine state machine (:mod:`devices.opcua_tags`), pure parts.

Ground truth is computed here, independently of the module: tonnes as the sum of what the
test put on the belt, joints from the raw counts the test wrote.  Random data is seeded
from the run's seed (printed; ``--seed N`` reproduces a run).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from devices.opcua_tags import (
    MachineTracker, MapError, NodeRef, Note, Publish, Scaled, load_map, parse_map,
    parse_node_id)
from schemas.events import timestamp_ns
from seeding import session_seed

SEED = session_seed()
pytestmark = pytest.mark.seeded
EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "plc.example.toml"
NS = "nsu=urn:test;s="
S = 1_000_000_000  # ns per second

RECLAIMER = f"""
[machines.bwr1]
kind = "reclaimer"
travel = {{ node = "{NS}travel", scale = 0.0005, unit = "m" }}
slew = {{ node = "{NS}slew", scale = 0.001, unit = "deg" }}
luff = {{ node = "{NS}luff", scale = 0.01, offset = -10.0, unit = "deg" }}
[machines.bwr1.state]
node = "{NS}state"
values = {{ 0 = "idle", 2 = "reclaiming", 3 = "travelling", 4 = "fault" }}
[machines.bwr1.ids]
cut_id = "{NS}cut"
bench_id = "{NS}bench"
pile_id = "{NS}pile"
[machines.bwr1.totaliser]
node = "{NS}total"
unit = "kg"
scale = 10.0
rollover = 100000
"""

STACKER = f"""
[machines.stk1]
kind = "stacker"
[machines.stk1.state]
node = "{NS}stk.state"
values = {{ 0 = "idle", 1 = "stacking", 4 = "fault" }}
[machines.stk1.ids]
pass_id = "{NS}stk.pass"
lot_id = "{NS}stk.lot"
pile_id = "{NS}stk.pile"
[machines.stk1.pass]
pattern = "WINDROW"
start_y = {{ node = "{NS}stk.y0", scale = 1.0, unit = "mm" }}
end_y = {{ node = "{NS}stk.y1", scale = 1.0, unit = "mm" }}
[machines.stk1.totaliser]
node = "{NS}stk.total"
unit = "t"
scale = 0.1
rollover = 50000
"""


def _rng(name: str) -> np.random.Generator:
    print(f"{name}: seed {SEED} (--seed {SEED} reproduces it)")
    return np.random.default_rng(SEED)


def _tracker(text: str, machine: str) -> MachineTracker:
    return MachineTracker(parse_map(text, "t.toml").machines[machine])


def _run(tracker: MachineTracker, samples) -> list:
    """Feed ``(t_ns, tag, value[, good])`` samples, then flush; everything returned."""
    out = []
    for sample in samples:
        t_ns, tag, value, *good = sample
        out += tracker.feed(t_ns, tag, value, good[0] if good else True)
    return out + tracker.flush()


def _published(out, type_name=None) -> list:
    msgs = [o.message for o in out if isinstance(o, Publish)]
    return [m for m in msgs if type_name is None or type(m).__name__ == type_name]


# -- the map -------------------------------------------------------------------------------


def test_the_example_map_maps_both_simulated_machines():
    plc = load_map(EXAMPLE)
    assert set(plc.machines) == {"bwr1", "stk1"}
    bwr1, stk1 = plc.machines["bwr1"], plc.machines["stk1"]
    assert (bwr1.kind, bwr1.working_state, stk1.kind) == ("reclaimer", "reclaiming", "stacker")
    assert bwr1.encoders["travel"] == Scaled(NodeRef("s", "bwr1.travel", 0, "urn:stockpile:sim"),
                                             0.0005, 0.0, "m")
    assert set(bwr1.plan) == {"travel", "luff", "slew_start", "slew_end"}
    assert bwr1.totaliser.tonnes_per_count == 0.001 and bwr1.totaliser.rollover == 10 ** 9
    assert stk1.pattern == "CHEVRON" and set(stk1.ids) == {"pass_id", "lot_id", "pile_id"}
    assert stk1.state_raw("stacking") == "1" and bwr1.state_raw("reclaiming") == "2"
    nodes = plc.nodes()
    assert len(nodes) == len(bwr1.tags()) + len(stk1.tags()) == 19
    assert nodes[parse_node_id("nsu=urn:stockpile:sim;s=stk1.totaliser")] == ("stk1", "totaliser")


@pytest.mark.parametrize("text, expected", [
    ("ns=2;s=bwr1.travel", NodeRef("s", "bwr1.travel", 2, None)),
    ("nsu=urn:a:b;i=1001", NodeRef("i", "1001", 0, "urn:a:b")),
    ("i=85", NodeRef("i", "85", 0, None)),
    ("s=with;semicolon", NodeRef("s", "with;semicolon", 0, None)),
])
def test_node_ids_parse_and_print_back(text, expected):
    assert parse_node_id(text) == expected
    assert str(expected) == text


@pytest.mark.parametrize("text", ["bwr1.travel", "ns=x;s=a", "i=abc", "nsu=;s=a", ""])
def test_a_bad_node_id_is_refused(text):
    with pytest.raises(ValueError, match="node id|digits"):
        parse_node_id(text)


def _with(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new, 1)


@pytest.mark.parametrize("text, where", [
    (_with(RECLAIMER, 'kind = "reclaimer"', 'kind = "crane"'), "machines.bwr1.kind"),
    (_with(RECLAIMER, "scale = 0.0005", "scale = 0"), "machines.bwr1.travel.scale"),
    (_with(RECLAIMER, 'unit = "deg" }\nluff', 'unit = "m" }\nluff'), "machines.bwr1.slew.unit"),
    (_with(RECLAIMER, '"reclaiming"', '"digging"'), "machines.bwr1.state.values.2"),
    (_with(RECLAIMER, '2 = "reclaiming", ', ""), "machines.bwr1.state.values"),
    (_with(RECLAIMER, f'luff = {{ node = "{NS}luff", scale = 0.01, offset = -10.0, unit = "deg" }}',
           ""), "machines.bwr1.luff"),
    (_with(RECLAIMER, f'"{NS}bench"', f'"{NS}cut"'), "machines.bwr1.cut_id"),
    (_with(RECLAIMER, f'"{NS}pile"', '"pile"'), "machines.bwr1.ids.pile_id"),
    (_with(RECLAIMER, "rollover = 100000", "rollover = -1"), "machines.bwr1.totaliser.rollover"),
    (_with(RECLAIMER, 'unit = "kg"', 'unit = "lb"'), "machines.bwr1.totaliser.unit"),
    (_with(RECLAIMER, "[machines.bwr1.state]", "speed = 3\n[machines.bwr1.state]"),
     "machines.bwr1.speed"),
    (_with(STACKER, 'pattern = "WINDROW"', 'pattern = "HEAP"'), "machines.stk1.pass.pattern"),
    (_with(STACKER, f'start_y = {{ node = "{NS}stk.y0", scale = 1.0, unit = "mm" }}', ""),
     "machines.stk1.pass.start_y"),
    ("[machines]\n", "machines"),
    ("title = 'x'\n", "title"),
])
def test_a_bad_map_is_one_line_naming_the_key(text, where):
    with pytest.raises(MapError) as caught:
        parse_map(text, "plc.toml")
    message = str(caught.value)
    assert message.startswith("plc.toml: ") and where in message, message
    assert "\n" not in message


def test_a_toml_syntax_error_names_the_line(tmp_path):
    path = tmp_path / "plc.toml"
    path.write_text(RECLAIMER + "\n[machines.bwr1.ids\n")
    with pytest.raises(MapError, match=rf"^{path}:{RECLAIMER.count(chr(10)) + 2}: "):
        load_map(path)
    with pytest.raises(MapError, match="cannot read"):
        load_map(tmp_path / "missing.toml")


def test_scaled_values_convert_to_metres_and_radians_and_back():
    slew = Scaled(NodeRef("s", "x"), 0.001, 0.0, "deg")
    for counts in (-180_000, -1, 0, 1, 123_456):
        assert slew.si(counts) == math.radians(counts * 0.001)
        assert slew.raw(slew.si(counts)) == counts
    luff = Scaled(NodeRef("s", "y"), 0.01, -10.0, "deg")
    assert luff.si(1000) == pytest.approx(math.radians(0.0), abs=1e-15)
    travel = Scaled(NodeRef("s", "z"), 2.0, 5.0, "mm")
    assert travel.si(10) == pytest.approx(0.025) and travel.raw(0.025) == 10
    assert travel.raw(0.0251, whole=False) == pytest.approx(10.05)


# -- the state machine ---------------------------------------------------------------------


def test_a_pass_starts_and_ends_with_the_totaliser_delta():
    tracker = _tracker(STACKER, "stk1")
    t0 = 1_800_000_000 * S
    out = _run(tracker, [
        (t0 - S, "totaliser", 1000),        # 100.0 t before the pass
        (t0, "pass_id", "L1-P1"), (t0, "lot_id", "L1"), (t0, "pile_id", "P1"),
        (t0, "plan.start_y", 12_500), (t0, "plan.end_y", 187_250), (t0, "state", 1),
        (t0 + 10 * S, "totaliser", 1500),
        (t0 + 20 * S, "totaliser", 2712), (t0 + 20 * S, "state", 0),
    ])
    started, ended = _published(out)
    assert type(started).__name__ == "StackStarted" and type(ended).__name__ == "StackEnded"
    assert (started.pass_id, started.lot_id, started.pile_id, started.machine_id) == (
        "L1-P1", "L1", "P1", "stk1")
    assert started.pattern == 2  # WINDROW
    assert (started.start_y_m, started.end_y_m) == pytest.approx((12.5, 187.25), abs=1e-12)
    assert timestamp_ns(started.time) == t0 and timestamp_ns(ended.time) == t0 + 20 * S
    assert (ended.pass_id, ended.pile_id, ended.bad_samples) == ("L1-P1", "P1", 0)
    assert ended.tonnes == pytest.approx((2712 - 1000) * 0.1, abs=1e-9)
    assert tracker.counters["started"] == tracker.counters["ended"] == 1
    assert tracker.open_activity is None


def test_the_totaliser_wraps_and_tonnes_stay_right():
    """Random belt loads through a 5,000 t counter (0.1 t counts wrapping at 50,000):
    every pass's tonnes equal what went on the belt during it, through the wraps."""
    rng = _rng("totaliser")
    tracker = _tracker(STACKER, "stk1")
    t = 1_800_000_000 * S
    counter, truth, wraps = 49_000, [], 0
    samples = [(t, "totaliser", counter)]
    for k in range(6):
        t += S
        samples += [(t, "pass_id", f"P{k}"), (t, "state", 1)]
        on_belt = 0
        for _ in range(int(rng.integers(3, 8))):
            t += S
            counts = int(rng.integers(0, 20_000))   # less than half the counter per sample
            on_belt += counts
            wraps += counter + counts >= 50_000
            counter = (counter + counts) % 50_000
            samples.append((t, "totaliser", counter))
        truth.append(round(on_belt * 0.1, 6))
        t += S
        samples.append((t, "state", 0))
    out = _run(tracker, samples)
    ended = _published(out, "StackEnded")
    assert [e.pass_id for e in ended] == [f"P{k}" for k in range(6)]
    assert [e.tonnes for e in ended] == pytest.approx(truth, abs=1e-6)
    notes = [o for o in out if isinstance(o, Note) and o.msg == "totaliser wrapped"]
    assert len(notes) == tracker.counters["totaliser_wrapped"] == wraps >= 1


def test_a_totaliser_reset_to_zero_is_logged_and_counts_on_from_zero():
    tracker = _tracker(STACKER, "stk1")
    t = 1_800_000_000 * S
    out = _run(tracker, [(t, "totaliser", 10_000), (t, "pass_id", "P1"), (t, "state", 1),
                         (t + S, "totaliser", 12_000),
                         (t + 2 * S, "totaliser", 0),       # the PLC reset its counter
                         (t + 3 * S, "totaliser", 300), (t + 3 * S, "state", 0)])
    (ended,) = _published(out, "StackEnded")
    assert ended.tonnes == pytest.approx((2_000 + 300) * 0.1)
    (note,) = [o for o in out if isinstance(o, Note) and o.msg.startswith("totaliser")]
    assert note.msg == "totaliser reset" and note.fields["from_raw"] == 12_000
    assert tracker.counters["totaliser_reset"] == 1 and "totaliser_wrapped" not in tracker.counters


def test_bad_samples_are_counted_withheld_and_flag_the_cut():
    tracker = _tracker(RECLAIMER, "bwr1")
    t0 = 1_800_000_000 * S
    joints = {"travel": 100_000, "slew": -20_000, "luff": 1_500}
    samples = [(t0, "totaliser", 0)]
    for k in range(5):  # five readings before the cut
        samples += [(t0 + k * S, tag, raw + k) for tag, raw in joints.items()]
    tc = t0 + 5 * S
    samples += [(tc, "cut_id", "B1-C01"), (tc, "bench_id", "B1"), (tc, "pile_id", "P1"),
                (tc, "state", 2)]
    for k in range(6):  # six readings in the cut: travel is bad at 2 and uncertain at 3
        t = tc + (k + 1) * S
        samples += [(t, "travel", None if k in (2, 3) else 100_100 + k, k not in (2, 3)),
                    (t, "slew", -19_000 + 100 * k), (t, "luff", 1_600)]
    te = tc + 8 * S
    samples += [(te, "totaliser", 3_001, False), (te + S, "totaliser", 3_002),
                (te + S, "state", 3)]
    out = _run(tracker, samples)
    readings = _published(out, "JointReading")
    # 5 + 6 encoder instants; the two with a bad travel are withheld
    assert len(readings) == 9 == tracker.counters["readings"]
    assert tracker.counters["withheld_readings"] == 2
    assert tracker.counters["bad_samples"] == 3
    assert [timestamp_ns(r.time) for r in readings] == (
        [t0 + k * S for k in range(5)] + [tc + (k + 1) * S for k in (0, 1, 4, 5)])
    last = readings[-1]
    assert last.travel_m == 100_105 * 0.0005
    assert last.slew_rad == math.radians(-18_500 * 0.001)
    assert last.luff_rad == pytest.approx(math.radians(1_600 * 0.01 - 10.0), abs=1e-15)
    (cut,) = _published(out, "ReclaimCut")
    assert (cut.cut_id, cut.bench_id, cut.pile_id, cut.bad_samples) == ("B1-C01", "B1", "P1", 3)
    assert timestamp_ns(cut.start_time) == tc and timestamp_ns(cut.end_time) == te + S
    assert cut.tonnes == pytest.approx(3_002 * 0.01)  # the bad totaliser sample is skipped
    # no plan in the map: the encoders at the cut's start and end
    assert cut.travel_m == (100_000 + 4) * 0.0005
    assert cut.slew_start_rad == math.radians((-20_000 + 4) * 0.001)
    assert cut.slew_end_rad == math.radians(-18_500 * 0.001)


def test_repeats_after_a_reconnect_are_stale_and_publish_nothing():
    tracker = _tracker(STACKER, "stk1")
    t0 = 1_800_000_000 * S
    history = [(t0, "totaliser", 10), (t0 + S, "pass_id", "P1"), (t0 + S, "state", 1),
               (t0 + 5 * S, "totaliser", 500)]
    first = _run(tracker, history)
    assert [type(m).__name__ for m in _published(first)] == ["StackStarted"]
    # a new subscription brings every tag's current value again, with its old time
    again = _run(tracker, [(t0 + S, "state", 1), (t0 + S, "pass_id", "P1"),
                           (t0 + 5 * S, "totaliser", 500)])
    assert _published(again) == [] and tracker.counters["stale_samples"] == 3
    assert tracker.open_activity == "P1"
    # what changed while away is newer and is handled
    rest = _run(tracker, [(t0 + 9 * S, "totaliser", 800), (t0 + 9 * S, "state", 0)])
    (ended,) = _published(rest)
    assert ended.tonnes == pytest.approx((800 - 10) * 0.1) and tracker.counters["ended"] == 1


def test_one_instant_is_handled_whole_in_any_arrival_order():
    """The end of a pass and the start of the next at one time: the totaliser's last
    count belongs to the pass that ends, whatever order the samples of that time came in."""
    for order in ([0, 1, 2], [2, 1, 0], [1, 2, 0]):
        tracker = _tracker(STACKER, "stk1")
        t1 = 1_800_000_010 * S
        same_time = [(t1, "totaliser", 70), (t1, "pass_id", "P2"), (t1, "state", 1)]
        out = _run(tracker, [(t1 - 10 * S, "totaliser", 0), (t1 - 10 * S, "pass_id", "P1"),
                             (t1 - 10 * S, "state", 1)] + [same_time[i] for i in order]
                   + [(t1 + S, "totaliser", 75), (t1 + S, "state", 0)])
        kinds = [(type(m).__name__, getattr(m, "pass_id")) for m in _published(out)]
        assert kinds == [("StackStarted", "P1"), ("StackEnded", "P1"), ("StackStarted", "P2"),
                         ("StackEnded", "P2")], order
        assert [m.tonnes for m in _published(out, "StackEnded")] == pytest.approx([7.0, 0.5])


def test_a_fault_pauses_the_pass_and_ends_it_where_work_stopped():
    tracker = _tracker(STACKER, "stk1")
    t = 1_800_000_000 * S
    out = _run(tracker, [
        (t, "totaliser", 0), (t, "pass_id", "P1"), (t, "state", 1),
        (t + 10 * S, "state", 4), (t + 20 * S, "state", 1),          # fault, resumed
        (t + 30 * S, "totaliser", 40), (t + 30 * S, "state", 4),    # fault again...
        (t + 50 * S, "totaliser", 41), (t + 50 * S, "state", 0),    # ... then idle
    ])
    started, ended = _published(out)
    assert started.pass_id == ended.pass_id == "P1" and tracker.counters["started"] == 1
    assert timestamp_ns(ended.time) == t + 30 * S  # when it stopped stacking
    assert ended.tonnes == pytest.approx(4.1)


def test_unmapped_states_and_missing_ids_are_counted_not_guessed():
    tracker = _tracker(STACKER, "stk1")
    t = 1_800_000_000 * S
    out = _run(tracker, [(t, "state", 9), (t + S, "state", 1), (t + 2 * S, "pass_id", " P7 ")])
    assert tracker.counters["unmapped_states"] == 1 and tracker.counters["missing_ids"] == 1
    (started,) = _published(out)
    assert started.pass_id == "P7" and timestamp_ns(started.time) == t + 2 * S
    assert any(isinstance(o, Note) and o.msg == "unmapped state value" for o in out)
    late = tracker.feed(t + S, "state", 0, True)   # older than what was handled
    assert late == [] and tracker.counters["stale_samples"] == 1


def test_the_integration_page_shows_the_example_map_whole():
    page = (EXAMPLE.parent / "integration.md").read_text()
    section = page[page.index("## Machine PLCs over OPC UA"):]
    block = section[section.index("```toml\n") + len("```toml\n"):]
    block = block[:block.index("```")]
    assert block == EXAMPLE.read_text()
    assert parse_map(block).machines == load_map(EXAMPLE).machines


def test_the_simulators_packaged_map_is_the_documented_example():
    """The simulator serves the tags of the map it ships (``sim/plc_map.toml``, package
    data), which must be the example the docs show."""
    packaged = EXAMPLE.parents[1] / "sim" / "plc_map.toml"
    assert packaged.read_text() == EXAMPLE.read_text()

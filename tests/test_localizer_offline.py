"""The product's localizer over a recorded run (``services/localizer_offline.py``).

On the short simulated demo yard the projector tests share (``small_yard_sim``:
``stockpile sim --scenario demo --seed 2 --duration 0.19 --speed 0 --scan-events truth
--assay-window 1200``), the offline localizer's scanner poses, estimated from the run's
encoders and GNSS, are compared with the simulator's true scanner poses in the same ``events.jsonl`` (the
``<machine>.poses`` frame transforms the simulator cast each scan with: its own
kinematics, not the localizer's); the fixes' dates with the simulator's true antenna
times (``truth.npz``); the ledger input with a real import.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from ledger.clock import EventClock
from ledger.importing import import_lines
from ledger.memory import MemoryStore
from schemas.events import Event, decode_payload
from schemas.jsonl import decode_line
from schemas.times import NS_PER_S
from services.localizer import Config
from services.localizer_offline import (INPUT_TYPES, gnss_fixes, localize_run,
                                        write_ledger_input)
from services.service import DEFAULT_SMOOTH_LAG_S
from sim.scenario import demo

MACHINE = "bwr1"
#: scanner position RMSE the localizer must stay within (m): the process demo prints
#: about 0.18 m for the wheel centre; the bound leaves a margin
RMSE_BOUND_M = 0.30
#: the demo's encoder period while a machine works (the short run stacks throughout), ns
ENCODER_PERIOD_NS = round(NS_PER_S / demo().encoder_hz)
#: the NMEA time of day's resolution (hhmmss.ss), ns
CENTISECOND_NS = NS_PER_S // 100


def _events(path) -> list[Event]:
    out = [decode_line(line) for line in path.read_text().splitlines()]
    assert all(isinstance(e, Event) for e in out)
    return out


def _scanner_poses(events, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Times (ns) and positions (m) of ``source``'s ``<machine>/scanner`` transforms."""
    t, p = [], []
    for e in events:
        if e.type == "frame_transform" and e.source == source:
            msg = decode_payload(e.type, e.payload)
            if msg.child_frame_id == f"{MACHINE}/scanner":
                t.append(e.valid_time_ns)
                p.append((msg.translation.x, msg.translation.y, msg.translation.z))
    return np.asarray(t, np.int64), np.asarray(p, float).reshape(-1, 3)


@pytest.fixture(scope="module")
def localized(small_yard_sim, tmp_path_factory):
    """The run's ledger input on the localizer's path, written twice."""
    out = tmp_path_factory.mktemp("localized")
    counts: dict[str, int] = {}
    paths, seconds = [], []
    for name in ("first.jsonl", "second.jsonl"):
        t0 = time.perf_counter()
        write_ledger_input(small_yard_sim / "events.jsonl", small_yard_sim / "gnss.nmea",
                           out / name, machine_id=MACHINE, counts=counts if not paths else None)
        seconds.append(time.perf_counter() - t0)
        paths.append(out / name)
    print(f"offline localizer: {seconds[0]:.1f} s, {seconds[1]:.1f} s; counters {counts}")
    return {"sim": small_yard_sim, "paths": paths, "counts": counts,
            "recorded": _events(small_yard_sim / "events.jsonl"),
            "ledger_input": _events(paths[0])}


def test_scanner_poses_within_the_demo_localizer_figure(localized):
    t_true, p_true = _scanner_poses(localized["recorded"], f"{MACHINE}.poses")
    t_est, p_est = _scanner_poses(localized["ledger_input"], f"{MACHINE}.localizer")
    assert len(t_true) > 100 and len(t_est) > 100
    inside = (t_true >= t_est[0]) & (t_true <= t_est[-1])
    assert inside.mean() > 0.99
    at = np.column_stack([np.interp(t_true[inside], t_est, p_est[:, k]) for k in range(3)])
    err = np.linalg.norm(at - p_true[inside], axis=1)
    rmse = float(np.sqrt(np.mean(err ** 2)))
    per_axis = np.sqrt(np.mean((at - p_true[inside]) ** 2, axis=0))
    print(f"scanner position RMSE {rmse:.3f} m over {inside.sum():,} scans "
          f"(east {per_axis[0]:.3f}, north {per_axis[1]:.3f}, up {per_axis[2]:.3f} m); "
          f"bound {RMSE_BOUND_M} m")
    assert rmse <= RMSE_BOUND_M


def _scanner_rmse_m(recorded, estimated) -> tuple[float, np.ndarray]:
    """RMSE (m) of the estimated scanner positions at the true poses' times, and per axis."""
    t_true, p_true = _scanner_poses(recorded, f"{MACHINE}.poses")
    t_est, p_est = _scanner_poses(estimated, f"{MACHINE}.localizer")
    inside = (t_true >= t_est[0]) & (t_true <= t_est[-1])
    at = np.column_stack([np.interp(t_true[inside], t_est, p_est[:, k]) for k in range(3)])
    d = at - p_true[inside]
    return float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))), np.sqrt(np.mean(d ** 2, axis=0))


def test_smoothed_poses_are_closer_than_the_filters_and_as_many(localized):
    """The ledger input's poses are smoothed as the service smooths them (its default
    lag); the filter's own (``smooth_lag_s=0``) are further from the truth."""
    recorded = localized["recorded"]
    nmea_bytes = (localized["sim"] / "gnss.nmea").read_bytes()
    inputs = [e for e in recorded if e.type in INPUT_TYPES]
    filtered = localize_run(inputs, nmea_bytes, machine_id=MACHINE,
                            config=Config(machine_id=MACHINE, smooth_lag_s=0.0))
    smoothed = localize_run(inputs, nmea_bytes, machine_id=MACHINE)
    assert [(e.type, e.valid_time_ns) for e in smoothed] == \
        [(e.type, e.valid_time_ns) for e in filtered]
    rmse_f, axes_f = _scanner_rmse_m(recorded, filtered)
    rmse_s, axes_s = _scanner_rmse_m(recorded, smoothed)
    print(f"scanner RMSE filtered {rmse_f:.3f} m (e/n/u {np.round(axes_f, 3)}), smoothed "
          f"({DEFAULT_SMOOTH_LAG_S:g} s lag) {rmse_s:.3f} m (e/n/u {np.round(axes_s, 3)})")
    assert rmse_s < rmse_f
    assert axes_s[1] < axes_f[1]              # along the rail: where a cut's tonnes move


def test_every_scan_has_a_localizer_pose_within_the_encoder_period(localized):
    scans = np.asarray([e.valid_time_ns for e in localized["ledger_input"] if e.type == "scan"],
                       np.int64)
    t_est, _ = _scanner_poses(localized["ledger_input"], f"{MACHINE}.localizer")
    assert len(scans) > 100
    after = np.searchsorted(t_est, scans, side="left")        # first pose at or after
    before = np.searchsorted(t_est, scans, side="right") - 1  # last pose at or before
    assert (before >= 0).all() and (after < len(t_est)).all(), "a scan outside the poses"
    gap_after = t_est[after] - scans
    gap_before = scans - t_est[before]
    print(f"{len(scans):,} scans: the pose at or before them at most "
          f"{gap_before.max() / 1e6:.1f} ms earlier, the pose at or after at most "
          f"{gap_after.max() / 1e6:.1f} ms later (encoder period "
          f"{ENCODER_PERIOD_NS / 1e6:.0f} ms)")
    assert gap_before.max() <= ENCODER_PERIOD_NS
    assert gap_after.max() <= ENCODER_PERIOD_NS


def test_ledger_input_swaps_the_true_poses_for_the_localizers(localized):
    recorded, ledger_input = localized["recorded"], localized["ledger_input"]
    poses = [e for e in recorded if e.source == f"{MACHINE}.poses"]
    ours = [e for e in ledger_input if e.source == f"{MACHINE}.localizer"]
    assert poses and ours
    assert not any(e.source == f"{MACHINE}.poses" for e in ledger_input)
    # every other recorded line is there, in its order
    assert [e for e in ledger_input if e.source != f"{MACHINE}.localizer"] == \
        [e for e in recorded if e.source != f"{MACHINE}.poses"]
    # dense sequence in one epoch, unsigned; three events (estimate, wheel, scanner) a time
    assert [e.seq for e in ours] == list(range(len(ours)))
    assert len({e.epoch for e in ours}) == 1 and all(e.signer is None for e in ours)
    assert [e.type for e in ours[:3]] == ["joint_estimate", "frame_transform", "frame_transform"]
    readings = sum(e.type == "joint_reading" for e in recorded)
    assert localized["counts"]["published"] == len(ours) == 3 * readings
    # each estimate follows the reading it was made at: no event before its valid time's reading
    latest_reading = None
    for e in ledger_input:
        if e.type == "joint_reading":
            latest_reading = e.valid_time_ns
        elif e.source == f"{MACHINE}.localizer":
            assert latest_reading is not None and e.valid_time_ns <= latest_reading


def test_ledger_input_imports_whole(localized):
    store = MemoryStore(EventClock())
    with localized["paths"][0].open(encoding="utf-8") as f:
        counts = import_lines(store, f)
    print(f"import: {dict(counts)}")
    assert counts["lines"] == len(localized["ledger_input"])
    assert counts["appended"] == counts["lines"]


def test_the_result_is_the_same_byte_for_byte(localized):
    first, second = (p.read_bytes() for p in localized["paths"])
    assert len(first) > 0
    assert first == second


def test_fixes_are_dated_at_the_receivers_true_times(localized):
    truth = np.load(localized["sim"] / "truth.npz")["antenna_enu"]
    true_ns = truth[:, 0].astype(np.int64) // CENTISECOND_NS * CENTISECOND_NS
    ticks = [e.valid_time_ns for e in localized["recorded"] if e.type == "clock"]
    counts: dict[str, int] = {}
    fixes = gnss_fixes((localized["sim"] / "gnss.nmea").read_bytes(), ticks,
                       machine_id=MACHINE, epoch=1, counts=counts)
    print(f"{len(fixes):,} fixes of {len(truth):,} receiver epochs; counters {counts}")
    dated = np.asarray([f.valid_time_ns for f in fixes], np.int64)
    assert len(fixes) > 100
    assert np.isin(dated, true_ns).all()
    assert (np.diff(dated) > 0).all()
    assert counts["published"] + counts.get("no_fix", 0) == len(truth)
    assert {f.source for f in fixes} == {f"{MACHINE}.gnss"}
    assert {decode_payload(f.type, f.payload).frame_id for f in fixes} == {f"{MACHINE}/gnss"}


# -- bad input -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def recorded_inputs(localized):
    """The run's declarations, readings and clock, and its NMEA bytes."""
    events = [e for e in localized["recorded"]
              if e.type in ("site_declared", "machine_declared", "joint_reading", "clock")]
    return events, (localized["sim"] / "gnss.nmea").read_bytes()


@pytest.mark.parametrize("drop, message", [
    ("site_declared", "no site_declared event"),
    ("machine_declared", "no machine_declared event for bwr1"),
    ("joint_reading", "no joint_reading of bwr1"),
    ("clock", "GNSS fixes but no clock event"),
])
def test_a_missing_input_is_a_clear_value_error(recorded_inputs, drop, message):
    events, nmea_bytes = recorded_inputs
    kept = [e for e in events if e.type != drop]
    assert len(kept) < len(events)
    with pytest.raises(ValueError, match=message):
        localize_run(kept, nmea_bytes, machine_id=MACHINE)


def test_another_machine_is_a_clear_value_error(recorded_inputs):
    events, nmea_bytes = recorded_inputs
    with pytest.raises(ValueError, match="no machine_declared event for rc9"):
        localize_run(events, nmea_bytes, machine_id="rc9")


def test_a_bad_machine_id_is_a_value_error(recorded_inputs):
    events, nmea_bytes = recorded_inputs
    with pytest.raises(ValueError, match="bad machine id"):
        localize_run(events, nmea_bytes, machine_id="bw/r1")


def test_garbage_nmea_gives_no_fixes_and_the_encoders_alone(recorded_inputs):
    events, _nmea = recorded_inputs
    counts: dict[str, int] = {}
    out = localize_run(events[:400], b"$GPGGA,garbage*00\r\n\x00\xff" * 3, machine_id=MACHINE,
                       counts=counts)
    print(f"counters {counts}")
    assert counts["gnss_checksum_errors"] == 3 and counts.get("fixes", 0) == 0
    assert counts["readings"] == sum(e.type == "joint_reading" for e in events[:400]) > 0
    assert len(out) == 3 * counts["readings"]

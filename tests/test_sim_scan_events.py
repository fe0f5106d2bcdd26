"""``stockpile sim --scan-events``: scans and scanner poses straight from the simulator.

One short demo run per mode (off, truth through the CLI; encoders in process with an
extra sink), checked against paths that do not go through the new code: the truth
arrays, the LMS200 byte stream decoded here, the localizer's forward kinematics, and a
real DuckDB ledger filled by ``stockpile ledger import``.
"""

from __future__ import annotations

import bisect
import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan

from ledger import open_ledger
from schemas.events import decode_payload
from schemas.jsonl import decode_line, encode_line
from projector.kinematics import MachineGeometry, quaternion_to_matrix, scanner_pose
from devices import lms200
from services.scanner import scan_field, scan_message
from sim.publish import MemorySink
from sim.runner import Simulation
from sim.scanner import beam_angles_rad
from sim.scenario import demo

STOCKPILE = str(Path(sys.executable).with_name("stockpile"))
DURATION_H = 0.05      # 3 site minutes: ~900 scans at 5 Hz, the stacker not yet started
SEED = 1
NEW_SOURCES = {"bwr1.scanner", "bwr1.poses"}


def _cli_sim(out: Path, mode: str) -> Path:
    run = subprocess.run([STOCKPILE, "sim", "--scenario", "demo", "--seed", str(SEED),
                          "--duration", str(DURATION_H), "--speed", "0", "--out", str(out),
                          "--scan-events", mode], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp("scan-events")
    out = {mode: _cli_sim(base / mode, mode) for mode in ("off", "truth")}
    sink = MemorySink()
    sim = Simulation(demo(), SEED, base / "encoders", sinks=[sink], scan_events="encoders")
    sim.run(duration_h=DURATION_H)
    out["encoders"] = base / "encoders"
    out["encoders_sink"] = sink.events
    return out


def _lines(path: Path) -> list[str]:
    return path.read_text(encoding="utf-8").splitlines()


def _source(line: str) -> str:
    return json.loads(line)["source"]


def _telegram_ranges(path: Path) -> tuple[list[np.ndarray], list[int]]:
    """Ranges of every 0xB0 telegram in an LMS200 byte stream, decoded here by hand."""
    reader = lms200.TelegramReader()
    data = path.read_bytes()
    telegrams = []
    for k in range(0, len(data), 4096):  # fed in arbitrary chunks, as a serial port would
        telegrams += reader.feed(data[k:k + 4096])
    telegrams += reader.flush()
    assert reader.crc_errors == 0 and reader.garbage_bytes == 0
    ranges, counts = [], []
    for telegram in telegrams:
        m = lms200.decode_measurement(telegram)
        v = m.values.astype(np.int64)
        r = v.astype(np.float64) / (1000.0 if m.unit_mm else 100.0)
        r[v >= lms200.ERROR_CODE_MIN] = np.nan     # 8183..8191: over range, dazzle, no return
        ranges.append(r)
        counts.append(m.count)
    return ranges, counts


def test_truth_mode_imports_cleanly_and_matches_the_truth_and_the_telegrams(runs, tmp_path):
    out = runs["truth"]
    ledger_path = tmp_path / "ledger.duckdb"
    imported = subprocess.run([STOCKPILE, "ledger", "import", str(out / "events.jsonl"),
                               "--ledger", str(ledger_path), "--clock", "events", "--json"],
                              capture_output=True, text=True, timeout=300)
    assert imported.returncode == 0, imported.stderr
    counts = json.loads(imported.stdout)
    n_lines = len(_lines(out / "events.jsonl"))
    assert counts["appended"] == counts["lines"] == n_lines
    assert counts["rejected"] == counts["conflict"] == counts["duplicate"] == 0

    poses = np.load(out / "truth.npz")["scanner_poses"]   # t, position (3), rotation (9)
    n = poses.shape[0]
    assert n > 500
    with open_ledger(ledger_path, read_only=True) as store:
        assert store.quarantine() == []
        scans = list(store.read(types=["scan"]))
        transforms = list(store.read(types=["frame_transform"]))
    assert len(scans) == len(transforms) == n
    assert {e.source for e in scans} == {"bwr1.scanner"}
    assert {e.source for e in transforms} == {"bwr1.poses"}
    assert [e.seq for e in scans] == [e.seq for e in transforms] == list(range(n))

    times = np.array([e.valid_time_ns for e in scans], dtype=np.int64)
    assert np.all(np.diff(times) > 0)
    assert [e.valid_time_ns for e in transforms] == times.tolist()
    # the truth keeps time as float64 (ns): compare through the same conversion
    np.testing.assert_array_equal(times.astype(np.float64), poses[:, 0])
    # each transform comes just before its scan in the ledger
    assert all(f.global_seq < s.global_seq for f, s in zip(transforms, scans))

    for event, row in zip(transforms, poses):
        ft = decode_payload("frame_transform", event.payload)
        assert isinstance(ft, FrameTransform)
        assert (ft.parent_frame_id, ft.child_frame_id) == ("site", "bwr1/scanner")
        assert ft.timestamp.ToNanoseconds() == event.valid_time_ns
        t = ft.translation
        assert (t.x, t.y, t.z) == tuple(row[1:4])   # the very pose the scan was cast from
        q = np.array([ft.rotation.x, ft.rotation.y, ft.rotation.z, ft.rotation.w])
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1.0) < 1e-12
        np.testing.assert_allclose(quaternion_to_matrix(q), row[4:13].reshape(3, 3),
                                   rtol=0, atol=1e-12)

    expected, counts_per_scan = _telegram_ranges(out / "lms200.bin")
    assert len(expected) == n
    sc = demo()
    angles = beam_angles_rad(sc.scan_fov_deg, sc.scan_step_deg)
    n_nan = n_finite = 0
    for event, ranges, count in zip(scans, expected, counts_per_scan):
        scan = decode_payload("scan", event.payload)
        assert isinstance(scan, LaserScan)
        assert scan.frame_id == "bwr1/scanner"
        assert scan.timestamp.ToNanoseconds() == event.valid_time_ns
        assert (scan.start_angle, scan.end_angle) == (angles[0], angles[-1])
        assert scan.pose.orientation.w == 1.0 and len(scan.intensities) == 0
        got = np.array(scan.ranges)
        np.testing.assert_array_equal(got, ranges)     # NaN where the telegram has a code
        n_nan += int(np.isnan(got).sum())
        n_finite += int(np.isfinite(got).sum())
        # byte for byte what the scanner service publishes for this telegram at this time
        service = scan_message(ranges, event.valid_time_ns, "bwr1/scanner", scan_field(count))
        assert event.payload == service.SerializeToString(deterministic=True)
    assert n_nan > 0 and n_finite > 0


def test_off_is_the_truth_run_without_the_new_sources(runs):
    off, truth = runs["off"], runs["truth"]
    off_lines = _lines(off / "events.jsonl")
    truth_lines = _lines(truth / "events.jsonl")
    assert not any(_source(line) in NEW_SOURCES for line in off_lines)
    assert not any(json.loads(line)["type"] in ("scan", "frame_transform") for line in off_lines)
    kept = [line for line in truth_lines if _source(line) not in NEW_SOURCES]
    n_scans = np.load(truth / "truth.npz")["scanner_poses"].shape[0]
    assert len(truth_lines) - len(kept) == 2 * n_scans
    # the new events only add lines: nothing else moves, changes or draws other numbers
    filtered = ("\n".join(kept) + "\n").encode()
    assert hashlib.sha256(filtered).hexdigest() == \
        hashlib.sha256((off / "events.jsonl").read_bytes()).hexdigest()
    for mode in ("truth", "encoders"):
        other = runs[mode]
        for name in ("lms200.bin", "gnss.nmea"):
            assert (other / name).read_bytes() == (off / name).read_bytes(), (mode, name)
        a, b = np.load(off / "truth.npz"), np.load(other / "truth.npz")
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"{mode} {key}")
        ta, tb = (json.loads((d / "truth.json").read_text()) for d in (off, other))
        for doc in (ta, tb):
            doc["stats"].pop("wall_s")
            doc["stats"].pop("events")
        assert ta == tb


#: SHA-256 of the off run's files, made by the simulator before ``--scan-events`` existed
#: (commit 719bafe).  The test above shows the option only adds lines; this one that
#: ``off`` is what the simulator always wrote.  A deliberate change of the simulator's
#: output must update these digests.  events.jsonl changed once since: the demo's clock
#: ticks every site second while a machine works (it ticked every 10 s; every other
#: event is as it was, checked line by line against 912cf84's run).  And once more: the
#: site declares its mine grid (``"crs_epsg":7850``); without those 16 bytes the file's
#: digest is the one before (39f5bd68...).
PRE_OPTION_SHA256 = {
    "events.jsonl": "4666afd2919f012afe2740d65a7fac438f60c764570c0449f64199d161f203d5",
    "lms200.bin": "8c64557c99d2c8b866d268f89eb64c139b61bfb59db3ddcf19d91bd191f0cdaa",
    "gnss.nmea": "fb3e659acb4274b76b026b889f440c19506b69286e578c3610badc121c5c64ee",
}


def test_off_is_byte_identical_to_the_simulator_before_the_option(runs):
    for name, digest in PRE_OPTION_SHA256.items():
        assert hashlib.sha256((runs["off"] / name).read_bytes()).hexdigest() == digest, name


def test_encoders_mode_poses_are_the_kinematics_of_the_latest_reading(runs):
    out = runs["encoders"]
    lines = _lines(out / "events.jsonl")
    events = [decode_line(line) for line in lines]
    # every sink gets the same events (Zenoh is a sink like this one)
    sunk = runs["encoders_sink"]
    assert [encode_line(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.payload)
            for e in sunk] == lines

    declared = [decode_payload(e.type, e.payload) for e in events if e.type == "machine_declared"]
    geometry = MachineGeometry.from_machine_declared(
        next(m for m in declared if m.machine_id == "bwr1"))
    readings = [(e.valid_time_ns, decode_payload(e.type, e.payload)) for e in events
                if e.type == "joint_reading"]
    reading_times = [t for t, _ in readings]
    transforms = [e for e in events if e.type == "frame_transform"]
    truth = np.load(out / "truth.npz")["scanner_poses"]
    assert len(transforms) == truth.shape[0] > 500
    assert {e.source for e in transforms} == {"bwr1.poses"}
    offsets = []
    for event, row in zip(transforms, truth):
        t = event.valid_time_ns
        k = bisect.bisect_right(reading_times, t) - 1
        assert k >= 0
        # encoders at 10 Hz, scans at 5 Hz: the reading taken at the scan time is used
        assert reading_times[k] == t
        r = readings[k][1]
        position, quat = scanner_pose(geometry, (r.travel_m, r.slew_rad, r.luff_rad))
        ft = decode_payload("frame_transform", event.payload)
        got_p = np.array([ft.translation.x, ft.translation.y, ft.translation.z])
        got_q = np.array([ft.rotation.x, ft.rotation.y, ft.rotation.z, ft.rotation.w])
        np.testing.assert_allclose(got_p, position, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got_q, quat, rtol=0, atol=1e-9)
        offsets.append(np.linalg.norm(got_p - row[1:4]))
    # the encoder pose is not the truth, but close to it
    assert 1e-4 < max(offsets) < 1.0

    # the scans themselves do not depend on the pose source
    truth_scans = [line for line in _lines(runs["truth"] / "events.jsonl")
                   if json.loads(line)["type"] == "scan"]
    assert [line for line in lines if json.loads(line)["type"] == "scan"] == truth_scans


def test_an_unknown_mode_is_refused(tmp_path):
    with pytest.raises(ValueError, match="scan_events"):
        Simulation(demo(), SEED, tmp_path, scan_events="localizer")
    assert not (tmp_path / "events.jsonl").exists()   # refused before anything is written

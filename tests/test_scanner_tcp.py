"""``stockpile service scanner --tcp``: an LMS511 on Ethernet, end to end.

Real processes: the simulator's LMS511 (``python -m sim.lms511``, a CoLa TCP server on
loopback), the scanner service connected to it, the ledger service, all on a real Zenoh
router over mutual TLS with the access control generated from a site PKI.  The LMS511
plays a scripted session: scans at 0.1667 deg over 190 deg, a few telegrams corrupted
(a flipped bit, garbage before one), and a cut half-way through a telegram while it
scans on unheard; its report says what it sent, and the ledger and the service's
counters are checked against it.  Waits are on conditions (files, the ledger's stats,
liveliness), never on sleeps.  Also pure parts: the scan-counter gaps, the command line,
and a 0.1667 deg scan appended to a DuckDB ledger and projected.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ledger import open_ledger
from projector.grid import cell_centres
from projector.query import project
from schemas import pb
from schemas.events import make_event, set_timestamp_ns
from schemas.validate import check_event
from services.ledger_client import LedgerClient
from schemas.events import timestamp_ns
from schemas.times import parse_time_ns
from services.scanner_tcp import ScanGaps, parse_endpoint
from sim.lms511 import Lms511Server, profile_ranges_m
from sim.scanner import ScannerModel
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from seeding import rng as seeded_rng, session_seed
from zenoh_helpers import (
    PYTHON,
    EventSink,
    SiteClock,
    client_args,
    free_port,
    log_lines,
    open_router,
    site_pki,
    stockpile,
    stop_all,
    wait_liveliness,
    wait_until,
)

pytestmark = pytest.mark.seeded
SITE = "tcpscan"
SOURCE = "bwr1.scanner"
TIMEOUT_S = 120.0      # generous: a loaded 2-core machine; each wait normally takes seconds


def _one(lines: list[dict], msg: str) -> dict:
    found = [line for line in lines if line.get("msg") == msg]
    assert len(found) == 1, f"expected one {msg!r} line, got {found}"
    return found[0]


# -- the whole path, as processes ----------------------------------------------------------


@pytest.mark.parametrize("protocol", ["cola-b", "cola-a"])
def test_lms511_scans_are_ledgered_across_a_cut_and_bad_telegrams_are_counted(tmp_path,
                                                                              protocol):
    seed = session_seed()
    print(f"seed {seed} (--seed {seed} reproduces it)")
    pki = site_pki(tmp_path / "pki", SITE, {"ledger": "ledger", SOURCE: "scanner"})
    router, endpoint = open_router(pki, SITE)
    port, report = free_port(), tmp_path / "lms511.json"
    sim_log, scanner_log = tmp_path / "lms511.log", tmp_path / "scanner.log"
    ledger = stockpile("service", "ledger", "--ledger", str(tmp_path / "ledger.duckdb"),
                       "--site", SITE, "--status-period", "1",
                       *client_args(endpoint, pki, "ledger"), stderr_path=tmp_path / "l.log")
    sim = scanner = None
    started_ns = time.time_ns()
    try:
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", TIMEOUT_S)
        sim = subprocess.Popen(
            [PYTHON, "-m", "sim.lms511", "--port", str(port), "--protocol", protocol,
             "--step-deg", "0.1667", "--fov-deg", "190", "--frequency-hz", "25",
             "--scans", "40", "--cut-after", "15", "--scans-during-cut", "6",
             "--flip", "4,27", "--garbage", "2,9,30", "--corrupt-rate", "0.05",
             "--seed", str(seed), "--report", str(report)],
            stderr=open(sim_log, "w"), stdout=subprocess.DEVNULL)
        scanner = stockpile("service", "scanner", "--tcp", f"127.0.0.1:{port}",
                            "--protocol", protocol, "--site", SITE, "--status-period", "0.5",
                            *client_args(endpoint, pki, SOURCE), stderr_path=scanner_log)
        wait_until(lambda: report.exists() or sim.poll() is not None, TIMEOUT_S,
                   "the simulated LMS511 to play its session")
        assert report.exists(), sim_log.read_text()[-2000:]
        sent = json.loads(report.read_text())
        intact = [s for s in sent["scans"] if s["sent"] and s["fault"] != "flipped"]
        client = LedgerClient(router, SITE, timeout_s=10)
        wait_until(lambda: client.stats()["per_source"].get(SOURCE, 0) >= len(intact),
                   TIMEOUT_S, f"{len(intact)} scans in the ledger")
        scanner_rc = stop_all(scanner)[0]
        records = client.read(0, types=["scan"])
        stats = client.stats()
    finally:
        codes = stop_all(scanner, sim, ledger)
        router.close()
    assert scanner_rc == 0 and codes == [0, 0, 0]
    finished_ns = time.time_ns()

    # what reached the ledger: every intact scan once, in order, nothing quarantined
    assert stats["quarantined"] == 0 and stats["per_source"].get(SOURCE) == len(intact)
    assert [r.seq for r in records] == list(range(len(intact)))
    count, step_rad = sent["count"], math.radians(0.1667)
    assert count == 1140
    valid = []
    for record, want in zip(records, intact, strict=True):
        msg = LaserScan.FromString(record.payload)
        assert msg.frame_id == "bwr1/scanner"
        assert len(msg.ranges) == count
        assert msg.start_angle == math.radians(-95.0)
        assert msg.end_angle == msg.start_angle + step_rad * (count - 1)
        dist = np.asarray(want["dist"], dtype=np.float64)
        expected = dist * sent["scale_factor"] / 1000.0
        expected[dist < 16] = np.nan
        np.testing.assert_array_equal(np.asarray(msg.ranges), expected)
        valid.append(record.valid_time_ns)
    # dated by arrival less the device's latency (one scan period): in order (two
    # telegrams one read brought share their arrival), within the run
    assert valid == sorted(valid)
    assert started_ns - sent["latency_ns"] <= valid[0] and valid[-1] <= finished_ns

    # what the service counted
    lines = log_lines(scanner_log)
    stopped = _one(lines, "stopped")
    counters = {k: int(v) for k, v in stopped.items() if v.isdigit()}
    gaps = [(b["scan_counter"] - a["scan_counter"] - 1) % 65536
            for a, b in zip(intact, intact[1:])]
    flipped = [s for s in sent["scans"] if s["fault"] == "flipped"]
    garbage = sum(s["wire_bytes"] - s["telegram_bytes"] for s in sent["scans"]
                  if s["fault"] == "garbage")
    garbage += sum(s["wire_bytes"] for s in flipped) + sent["partial_bytes"]
    assert len(flipped) >= 2 and sent["partial_bytes"] > 0
    assert counters["published"] == len(intact)
    assert counters["telegrams"] == len(intact) + 2          # + the two sEA answers
    assert counters["lost_scans"] == sum(gaps) >= 2 + 1 + 6     # flips 4, 27; the cut
    assert counters["garbage_bytes"] == garbage
    error = "checksum_errors" if protocol == "cola-b" else "broken_frames"
    assert counters[error] == len(flipped)
    assert counters["reconnects"] == 1
    for absent in ("bad_telegrams", "other_telegrams", "latency_ignored", "waiting_for_clock",
                   "broken_frames" if protocol == "cola-b" else "checksum_errors"):
        assert absent not in counters, (absent, counters)
    lost = _one(lines, "connection lost")
    assert int(lost["bytes_dropped"]) == sent["partial_bytes"]
    assert int(_one(lines, "published")["count"]) == len(intact)
    assert not scanner_log.read_text().count("Traceback")


def test_site_clock_dates_a_scan_at_its_arrival_on_the_site_clock_less_the_latency(tmp_path):
    """``--clock site``: a scan before the first clock tick is dropped and counted; after
    it, valid time = the site time of the arrival - the device's latency (here 40 ms of a
    25 Hz scan), far from the wall clock.  The LMS511 runs in the test's process."""
    site0_ns = parse_time_ns("2030-03-31T12:00:00Z")
    router, endpoint = open_router()
    log = tmp_path / "scanner.log"
    rng = seeded_rng(31)
    ranges = profile_ranges_m(rng, 601)
    start_rad, step_rad = math.radians(-50.0), math.radians(100.0 / 600)
    sink = EventSink(router, "sitetcp", "scan", SOURCE, TIMEOUT_S)
    process = None
    try:
        with Lms511Server("127.0.0.1", 0, "cola-a") as lms:
            process = stockpile("service", "scanner", "--tcp", f"127.0.0.1:{lms.port}",
                                "--protocol", "cola-a", "--clock", "site", "--site", "sitetcp",
                                "--status-period", "0.2", *client_args(endpoint),
                                stderr_path=log)
            assert lms.wait_streaming(TIMEOUT_S), log.read_text()[-2000:]
            assert lms.send_scan(site0_ns, ranges, start_rad, step_rad).sent
            wait_until(lambda: any(line.get("waiting_for_clock") == "1"
                                   for line in log_lines(log)),
                       TIMEOUT_S, "the scan counted as waiting_for_clock")
            with SiteClock(router, "sitetcp", site0_ns) as clock:
                wait_until(lambda: any(line.get("msg") == "site clock ready"
                                       for line in log_lines(log)),
                           TIMEOUT_S, "the service to follow the site clock")
                sent_site_ns = clock.site_ns(time.monotonic_ns())
                assert lms.send_scan(sent_site_ns, ranges, start_rad, step_rad).sent
                got = sink.wait_for(1, process)
            rc = stop_all(process)[0]
    finally:
        if process is not None:
            stop_all(process)
        sink.close()
        router.close()
    assert rc == 0 and len(got) == 1
    msg = check_event(got[0])
    assert len(msg.ranges) == 601
    assert math.isclose(msg.end_angle - msg.start_angle, 600 * math.radians(0.1667),
                        abs_tol=1e-12)                 # the step as sent: 1667 / 10000 deg
    # the telegram says 40 ms passed from the scan's start to its transmission
    assert abs(timestamp_ns(msg.timestamp) - (sent_site_ns - lms.latency_ns)) < 200_000_000
    stopped = _one(log_lines(log), "stopped")
    assert int(stopped["waiting_for_clock"]) == 1 and int(stopped["published"]) == 1


def test_a_bad_tcp_address_or_a_serial_option_is_one_error_line():
    for args, words in ((["--tcp", "scanner-without-port"], "HOST:PORT"),
                        (["--tcp", "127.0.0.1:2112", "--fov-deg", "190"], "--fov-deg"),
                        (["--device", "/dev/null", "--protocol", "cola-a"], "--tcp only")):
        run = subprocess.run([sys.executable, "-m", "stockpile.cli", "service", "scanner",
                              *args, "--mode", "client", "--connect", "tcp/127.0.0.1:9"],
                             capture_output=True, text=True, timeout=60)
        assert run.returncode == 2, run.stderr
        assert len(run.stderr.strip().splitlines()) == 1, run.stderr
        assert words in run.stderr


# -- pure parts ----------------------------------------------------------------------------


def test_scan_gaps_count_the_missing_counters_across_the_wrap():
    gaps = ScanGaps()
    period_us = 40_000
    assert gaps.seen(65_530, 1_000_000, 25.0) == 0                   # the first: nothing
    assert gaps.seen(65_531, 1_000_000 + period_us, 25.0) == 0
    assert gaps.seen(2, 1_000_000 + 8 * period_us, 25.0) == 6        # 65532..1 lost
    assert gaps.seen(2, 1_000_000 + 8 * period_us, 25.0) == 0        # a repeat (sRA)
    # the device restarted: its clock went back; nothing it can tell is lost
    assert gaps.seen(0, 5_000, 25.0) == 0 and gaps.restarts == 1
    assert gaps.seen(3, 5_000 + 3 * period_us, 25.0) == 2
    # a long cut at 100 Hz (12 min): 70 000 scans, the 16-bit counter alone says 4464
    fast = ScanGaps()
    assert fast.seen(10, 2**32 - 1_000_000, 100.0) == 0
    later_us = (2**32 - 1_000_000 + 70_001 * 10_000) % 2**32      # the us counter wrapped
    assert fast.seen((10 + 70_001) % 65_536, later_us, 100.0) == 70_000


@pytest.mark.parametrize("text, expected", [
    ("192.168.0.1:2112", ("192.168.0.1", 2112)),
    ("lms511.yard:2111", ("lms511.yard", 2111)),
    ("[::1]:2112", ("::1", 2112)),
])
def test_tcp_endpoints_parse(text, expected):
    assert parse_endpoint(text) == expected


@pytest.mark.parametrize("text", ["2112", "host:", ":2112", "host:0", "host:70000",
                                  "[zz]:2112"])
def test_bad_tcp_endpoints_are_refused(text):
    with pytest.raises(ValueError):
        parse_endpoint(text)


# -- a 0.1667 deg scan: appended to a real DuckDB ledger and projected ----------------------

#: scanner x -> site -z, y -> site +x, z -> site -y: looking down, sweeping across x
LOOK_DOWN = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])
T0_NS = 1_790_000_000 * 10**9
S_NS = 10**9


def _mound_z(x_m):
    """The true surface: a ridge 4 m high along y, centred on x = 10 m, 1:1 flanks."""
    return np.maximum(0.0, 4.0 - np.abs(np.asarray(x_m) - 10.0))


def _stamp(msg, field: str, t_ns: int):
    set_timestamp_ns(getattr(msg, field), t_ns)
    return msg


def test_a_0_1667_deg_scan_is_appended_to_duckdb_and_projected(tmp_path):
    rng = seeded_rng(21)
    model = ScannerModel(fov_deg=100.0, step_deg=0.1667, any_step=True, range_noise_m=0.005,
                         range_noise_frac=0.0, mixed_pixel_prob=0.0, dropout_prob=0.0,
                         error_code_prob=0.0, rng=rng)
    assert model.n_beams == 600            # floor(100 / 0.1667) + 1: not an LMS200 field
    cell = 0.05
    xs = (np.arange(int(20 / cell)) + 0.5) * cell
    truth = np.tile(_mound_z(xs), (int(20 / cell), 1))               # (ny, nx)
    quat = Rotation.from_matrix(LOOK_DOWN).as_quat()                  # x, y, z, w
    pile = pb.PileDeclared(pile_id="P1", origin_x_m=0.0, origin_y_m=0.0, length_m=20.0,
                           width_m=20.0, ground_z_m=0.0, cell_m=0.5, voxel_m=1.0,
                           default_bulk_density_t_m3=2.4)
    events = [make_event(_stamp(pile, "time", T0_NS - S_NS), source="yard.config", epoch=1,
                         seq=0)]
    poses, scans = [], []
    for k, y in enumerate(np.arange(4.0, 16.01, 0.25)):
        t = T0_NS + k * S_NS
        pose = FrameTransform(parent_frame_id="site", child_frame_id="bwr1/scanner")
        pose.translation.x, pose.translation.y, pose.translation.z = 10.0, y, 6.0
        pose.rotation.x, pose.rotation.y, pose.rotation.z, pose.rotation.w = quat
        poses.append(make_event(_stamp(pose, "timestamp", t), source="bwr1.localizer",
                                epoch=1, seq=k))
        ranges = model.scan(truth, 0.0, 0.0, cell, (10.0, y, 6.0), LOOK_DOWN)
        scan = LaserScan(frame_id="bwr1/scanner", start_angle=float(model.angles_rad[0]),
                         end_angle=float(model.angles_rad[-1]))
        scan.pose.orientation.w = 1.0
        scan.ranges.extend(ranges.tolist())
        scans.append(make_event(_stamp(scan, "timestamp", t), source=SOURCE, epoch=1, seq=k))
    for event in scans:
        check_event(event)                 # the ledger's rule takes the 0.1667 deg step
    with open_ledger(tmp_path / "ledger.duckdb") as store:
        result = store.append(events + poses + scans)
        assert result.appended == 1 + len(poses) + len(scans), result
        assert store.quarantine() == []
    with open_ledger(tmp_path / "ledger.duckdb", read_only=True) as store:
        state = project(store, "P1")
    assert state.counters["scans_fused"] == len(scans)
    x, y = cell_centres(state.geometry)
    seen = ~np.isnan(state.elevation_m)
    band = (np.abs(x - 10.0) < 4.0) & (y > 4.5) & (y < 15.5)     # under the scanner's sweep
    assert seen[band].mean() > 0.9, seen[band].mean()
    err = state.elevation_m[band & seen] - _mound_z(x[band & seen])
    print(f"0.1667 deg: {int((band & seen).sum())} cells, median |err| "
          f"{np.median(np.abs(err)):.3f} m, max {np.abs(err).max():.3f} m")
    # a cell's fused height is its points' mean: within a few cm of the ridge's (cells
    # at the crest average both flanks, so allow their quarter-cell fall)
    assert np.median(np.abs(err)) < 0.05
    assert np.abs(err).max() < 0.3

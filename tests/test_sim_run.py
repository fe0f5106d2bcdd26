"""The simulator end to end: reproducible streams, real pseudo-terminals, truth files."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import serial

from schemas.jsonl import decode_line
from schemas.validate import check_event
from devices import lms200
from devices.nmea import NmeaReader, parse_gga
from sim.pty import PtyDevice
from sim.records import LAB_WINDOW_FE
from sim.runner import Simulation
from sim.scenario import demo

STOCKPILE = str(Path(sys.executable).with_name("stockpile"))
SHORT_H = 0.12  # site hours: declarations, lots and the start of the first pass


def _sim(out: Path, seed: int, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([STOCKPILE, "sim", "--scenario", "demo", "--seed", str(seed),
                           "--duration", str(SHORT_H), "--out", str(out), *extra],
                          capture_output=True, text=True, timeout=600)


def test_same_seed_gives_byte_identical_streams(tmp_path):
    runs = [_sim(tmp_path / f"run{i}", 1) for i in range(2)]
    assert all(r.returncode == 0 for r in runs), runs[0].stderr
    for name in ("events.jsonl", "lms200.bin", "gnss.nmea"):
        a, b = ((tmp_path / f"run{i}" / name).read_bytes() for i in range(2))
        assert a and a == b, name
    other = _sim(tmp_path / "other", 2)
    assert (tmp_path / "other" / "gnss.nmea").read_bytes() != (tmp_path / "run0" / "gnss.nmea").read_bytes()


def test_a_noise_seed_measures_the_same_world_again(tmp_path):
    """``--noise-seed``: the sensors' noise from another seed, the world from ``--seed``."""
    runs = {name: _sim(tmp_path / name, 1, *extra) for name, extra in (
        ("default", ()), ("other", ("--noise-seed", "7")), ("own", ("--noise-seed", "1")))}
    assert all(r.returncode == 0 for r in runs.values()), runs["other"].stderr
    assert "sensor noise seed 7" in runs["other"].stdout
    default, other, own = (tmp_path / name for name in ("default", "other", "own"))
    # its own seed as the noise seed is the default run, byte for byte
    for name in ("events.jsonl", "lms200.bin", "gnss.nmea"):
        assert (own / name).read_bytes() == (default / name).read_bytes(), name
    # another: every sensor's stream differs ...
    for name in ("lms200.bin", "gnss.nmea"):
        assert (other / name).read_bytes() != (default / name).read_bytes(), name
    events = [[decode_line(line) for line in (d / "events.jsonl").read_text().splitlines()]
              for d in (default, other)]
    readings = [[e.payload for e in run if e.type == "joint_reading"] for run in events]
    assert len(readings[0]) == len(readings[1]) > 0 and readings[0] != readings[1]
    # ... and the world is the same: what was stacked, where, and the truth about it
    truth = [json.loads((d / "truth.json").read_text()) for d in (default, other)]
    assert (truth[0]["seed"], truth[0]["noise_seed"], truth[1]["noise_seed"]) == (1, 1, 7)
    assert truth[0]["world"]["tonnes"] > 0
    for key in ("world", "passes", "cuts", "assays"):
        assert truth[0][key] == truth[1][key], key
    surfaces = [np.load(d / "truth.npz")["surface_z"] for d in (default, other)]
    assert np.array_equal(surfaces[0], surfaces[1])
    plan = [[(e.type, e.valid_time_ns, e.payload) for e in run
             if e.type in ("lot_declared", "stack_started", "stack_ended", "assay")]
            for run in events]
    assert plan[0] and plan[0] == plan[1]


def test_events_are_valid_and_in_arrival_order(tmp_path):
    assert _sim(tmp_path, 3).returncode == 0
    lines = (tmp_path / "events.jsonl").read_text().splitlines()
    events = [decode_line(line) for line in lines]
    for event in events:
        check_event(event)  # every event passes the ledger's own validation
    types = {e.type for e in events}
    assert {"site_declared", "pile_declared", "machine_declared", "lot_declared", "clock",
            "joint_reading", "stack_started"} <= types
    streams: dict = {}
    for e in events:
        assert e.seq == streams.get((e.source, e.epoch), -1) + 1  # dense per source
        streams[(e.source, e.epoch)] = e.seq
    clock = [e.valid_time_ns for e in events if e.type == "clock"]
    assert clock == sorted(clock)


def test_scanner_telegrams_through_a_pty_give_back_the_cast_ranges(tmp_path):
    scanner_pty, gnss_pty = PtyDevice(), PtyDevice()
    received = {"lms": bytearray(), "gnss": bytearray()}
    ports = {"lms": serial.Serial(scanner_pty.path, 500000, timeout=0.2),
             "gnss": serial.Serial(gnss_pty.path, 9600, timeout=0.2)}
    done = threading.Event()

    def reader(name: str) -> None:
        while True:
            chunk = ports[name].read(65536)
            if chunk:
                received[name] += chunk
            elif done.is_set():
                return

    threads = [threading.Thread(target=reader, args=(n,)) for n in ports]
    for thread in threads:
        thread.start()
    sim = Simulation(demo(), 4, tmp_path, scanner_pty=scanner_pty, gnss_pty=gnss_pty,
                     record_scans=True)
    stats = sim.run(duration_h=0.1)  # 1 min of stacking at full sensor rates
    done.set()
    for thread in threads:
        thread.join(timeout=60)
    for port in ports.values():
        port.close()
    scanner_pty.close()
    gnss_pty.close()
    assert stats.dropped_pty_bytes == 0
    assert bytes(received["lms"]) == (tmp_path / "lms200.bin").read_bytes()

    telegram_reader = lms200.TelegramReader()
    telegrams = telegram_reader.feed(bytes(received["lms"]))
    assert telegram_reader.crc_errors == 0 and len(telegrams) == stats.scans == len(sim.cast_scans)
    # while a machine works (all of this run) the clock ticks as each telegram leaves:
    # at its scan's time plus its transfer time, which the scanner service subtracts
    ticks = {decode_line(line).valid_time_ns
             for line in (tmp_path / "events.jsonl").read_text().splitlines()
             if '"type":"clock"' in line}
    scan_ns = np.load(tmp_path / "truth.npz")["scanner_poses"][:, 0].astype(np.int64)
    transfer_ns = [len(t) * 10 * 10**9 // demo().scanner_baud for t in telegrams]
    assert all(int(t) + d in ticks for t, d in zip(scan_ns, transfer_ns))
    unit_m = 0.001 if sim.unit_mm else 0.01
    for telegram, (cast, status) in zip(telegrams, sim.cast_scans):
        decoded = lms200.decode_measurement(telegram).ranges_m
        good = np.isfinite(cast) & (status == 0)
        assert np.all(np.isnan(decoded[~np.isfinite(cast)]))
        assert np.all(np.abs(decoded[good] - cast[good]) <= unit_m / 2 + 1e-9)
        assert good.mean() > 0.5  # the scanner sees the ground and the pile, not the sky

    nmea = NmeaReader()
    sentences = nmea.feed(bytes(received["gnss"]))
    assert nmea.checksum_errors == 0 and len(sentences) == stats.gga
    fixes = [parse_gga(s) for s in sentences]
    assert sum(f.quality > 0 for f in fixes) / len(fixes) > 0.9
    lat = np.array([f.lat_deg for f in fixes if f.quality > 0])
    assert np.all(np.abs(lat - demo().datum_lat_deg) < 0.01)  # within ~1 km of the datum


def test_truth_files_describe_the_run(tmp_path):
    sim = Simulation(demo(), 5, tmp_path)
    stats = sim.run(duration_h=0.2)
    truth = json.loads((tmp_path / "truth.json").read_text())
    world = truth["world"]
    balance = world["mass_balance"]
    assert stats.passes >= 1 and truth["passes"]
    # mass conservation: what the stacker released is in the pile (no reclaim yet), and
    # every completed pass released its planned tonnes (a pass may still be running)
    assert abs(balance["stacked_tonnes"] - world["tonnes"]) <= 1e-9 * world["tonnes"], balance
    ended = sum(p["true_tonnes"] for p in truth["passes"])
    assert ended <= balance["stacked_tonnes"] + 1e-6
    assert balance["lost_tonnes"] == 0.0
    # belt scale within a few sd of its 0.7 % error
    for p in truth["passes"]:
        assert abs(p["belt_tonnes"] / p["true_tonnes"] - 1) < 0.04
    arrays = np.load(tmp_path / "truth.npz")
    assert arrays["joints"].shape[1] == 4 and len(arrays["joints"]) > 100
    assert arrays["scanner_poses"].shape == (stats.scans, 13)
    rotations = arrays["scanner_poses"][:, 4:].reshape(-1, 3, 3)
    assert np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert arrays["surface_z"].max() > 0.5  # a pass has been stacked


def test_cut_surfaces_are_what_each_cut_acted_on(tmp_path):
    """``cut_surfaces``: the true surface at each cut's start.  Checked by a different
    method than the parcels the cut's truth comes from: the surface lost between one
    cut's start and the next (or the end; the slides in between move material, they do
    not lose it) is that cut's true volume."""
    base = demo()
    scenario = replace(base, lots=base.lots[:1], passes_per_lot=2, pass_duration_s=200.0,
                       scan_hz=1.0, encoder_hz=1.0, gnss_hz=0.2, idle_hz=0.01,
                       cuts_per_bench=(2,))
    sim = Simulation(scenario, 3, tmp_path, cut_surfaces=True)
    sim.run()
    truth = json.loads((tmp_path / "truth.json").read_text())
    arrays = np.load(tmp_path / "truth.npz")
    surfaces = arrays["cut_surface_z"]
    assert len(truth["cuts"]) == 2
    assert surfaces.shape == (2, *arrays["surface_z"].shape)
    assert truth["world"]["mass_balance"]["lost_tonnes"] == 0.0
    cell_area_m2 = sim.world.grid.cell_area_m2
    ground_m = truth["scenario"].get("ground_z_m", 0.0)
    after = [*surfaces[1:], arrays["surface_z"]]
    for cut, before_m, after_m in zip(truth["cuts"], surfaces, after):
        lost_m3 = float(np.sum(before_m.astype(np.float64) - after_m)) * cell_area_m2
        assert cut["true_volume_m3"] > 1.0
        assert abs(lost_m3 - cut["true_volume_m3"]) <= 1e-4 * cut["true_volume_m3"], cut["cut_id"]
        # the walls a cut leaves standing slide once it has passed: the volume that moved
        # is kept, and it is part of the pile the cut left
        pile_m3 = float(np.sum(after_m - ground_m)) * cell_area_m2
        assert 0.0 < cut["slump_m3"] < pile_m3, cut["cut_id"]
    # the parcels as stacked, at the first cut's start: they sum to that surface, and
    # their times lie in the passes that laid them
    thickness = arrays["first_cut_thickness"].astype(np.float64)
    assert thickness.shape[0] == len(truth["passes"]) >= 2
    np.testing.assert_allclose(ground_m + thickness.sum(axis=0), surfaces[0], atol=1e-5)
    times = arrays["first_cut_time_ns"]
    for slot, p in enumerate(truth["passes"]):
        laid = thickness[slot] > 1e-6
        assert laid.any()
        assert np.all((times[slot][laid] >= p["t0_ns"] - 1e3) & (times[slot][laid] <= p["t1_ns"] + 1e3))
    # without the option there is no such array
    plain = Simulation(scenario, 3, tmp_path / "plain")
    plain.run(duration_h=0.05)
    assert not {"cut_surface_z", "first_cut_thickness"} & set(np.load(tmp_path / "plain" / "truth.npz"))


def test_cuts_carry_the_fe_the_lab_gave_their_material(tmp_path):
    """``lab_window_fe_pct``: a cut's Fe as the laboratory's final results, one per window,
    give it.  Checked by a different path than the grade channel the world carries: the
    pile's stacked mean of the channel against every release's tonnes times the final Fe of
    the window (from truth.json's assays) its time falls in."""
    base = demo()
    scenario = replace(base, lots=base.lots[:2], passes_per_lot=1, pass_duration_s=200.0,
                       assay_window_s=40.0, scan_hz=1.0, encoder_hz=1.0, gnss_hz=0.2,
                       idle_hz=0.01, cuts_per_bench=(2,))
    sim = Simulation(scenario, 5, tmp_path)
    sim.run()
    truth = json.loads((tmp_path / "truth.json").read_text())
    final = [a for a in truth["assays"] if a["status"] == "FINAL"]
    assert len(final) == 10   # 2 passes of 200 s in 40-s windows

    def lab_fe(lot: str, time_ns: int) -> float:
        mine = [a for a in final if a["lot_id"] == lot]
        hits = [a for a in mine if a["window_start_ns"] <= time_ns < a["window_end_ns"]]
        hits = hits or [a for a in mine if a["window_end_ns"] == time_ns]   # the last window
        assert len(hits) == 1, (lot, time_ns)
        return hits[0]["analytes_pct"]["Fe"]

    releases = sim.world.releases()
    stacked_t = sum(r["tonnes"] for r in releases)
    expected = sum(r["tonnes"] * lab_fe(r["lot"], r["time_ns"]) for r in releases) / stacked_t
    assert abs(truth["world"]["stacked_grade"][LAB_WINDOW_FE] - expected) < 1e-9
    assert len(truth["cuts"]) == 2
    for cut in truth["cuts"]:
        values = [a["analytes_pct"]["Fe"] for a in final if a["lot_id"] in cut["tonnes_by_lot"]]
        assert min(values) <= cut["lab_window_fe_pct"] <= max(values), cut["cut_id"]
        # the lab measures with error and one grade per window: never the true Fe
        assert cut["lab_window_fe_pct"] != cut["grade"]["Fe"], cut["cut_id"]
        assert set(cut["grade"]) == {"Fe", "SiO2", "Al2O3", "P", "LOI"}, cut["cut_id"]


def test_clock_ticks_every_second_while_a_machine_works_and_where_it_stops(tmp_path):
    """The demo's clock ticks every site second while a machine works (10 s while the
    yard waits) and once more where the yard stops working, so that the scanner, which
    dates telegrams between the ticks around them, has the corner where a paced run
    changes pace.  The yard's working spells are read off the encoder's cadence (10 Hz
    while a machine works, 0.1 Hz while the yard waits), not the simulator's flag."""
    scenario = replace(demo(), lots=demo().lots[:1], passes_per_lot=1, cuts_per_bench=(2,))
    Simulation(scenario, 3, tmp_path).run(duration_h=0.5)
    events = [decode_line(line) for line in (tmp_path / "events.jsonl").read_text().splitlines()]
    ticks = np.array([e.valid_time_ns for e in events if e.type == "clock"])
    readings = np.array([e.valid_time_ns for e in events if e.type == "joint_reading"])
    assert np.all(np.diff(ticks) > 0)
    step_s = np.diff(readings) / 1e9
    working = np.flatnonzero(np.isclose(step_s, 0.1))
    assert working.size > 1000
    for i in working:   # every working step has a tick within a second after its start
        k = np.searchsorted(ticks, readings[i])
        assert k < len(ticks) and ticks[k] - readings[i] <= 1_000_000_000
    stops = [readings[i + 1] for i in range(len(step_s) - 1)
             if np.isclose(step_s[i], 0.1) and step_s[i + 1] > 5.0]
    assert len(stops) == 2   # the last pass (and the survey after it), the last cut
    for stop_ns in stops:    # the yard stopped during the last 10 Hz step before it
        assert np.any((ticks > stop_ns - 100_000_000) & (ticks <= stop_ns)), stop_ns


def test_a_paced_run_that_falls_behind_moves_its_schedule_on(tmp_path):
    """One handler stalls for 1 s of wall time half way through a paced run: the run
    gives that second up (site time ran slower for a moment) instead of catching up in a
    burst, in which telegrams and clock ticks would arrive together."""
    sim = Simulation(demo(), 4, tmp_path)
    site_s, speed, stall_s = 120.0, 40.0, 1.0
    real_gnss, stalled = sim._on_gnss, []

    def slow_gnss(t, period, at):
        if not stalled and t - demo().start_ns > site_s / 2 * 1e9:
            stalled.append(t)
            time.sleep(stall_s)   # the stall under test, not a synchronisation
        real_gnss(t, period, at)

    sim._on_gnss = slow_gnss
    stats = sim.run(duration_h=site_s / 3600, speed=speed)
    assert stalled and stats.rebases >= 1
    assert stats.given_up_s >= 0.9 * stall_s
    # nominal 3 s of wall time; caught up it would take about that, given up 4 s
    assert stats.wall_s >= site_s / speed + 0.8 * stall_s, stats.wall_s

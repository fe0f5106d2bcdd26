"""``stockpile sim --live-at``: a live run has the plain run's world and emits only from its
live moment; the two-bed scenarios' sources, clock and footprint; ``--milestones``.

Real runs of the real simulator into real files (and real pseudo-terminals), checked
against a plain run of the same scenario and seed, the truth arrays, and the events as
written to ``events.jsonl``.  The demo's sensors are slowed down in the runs that compare
(history at 0.5 Hz scans, 0.5 Hz GNSS, 1 Hz encoders; live at 1, 1 and 2 Hz, as the
two-bed scenarios go from their history rates to their live ones) to keep the runs short.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from common.logs import parse_log_line
from schemas.events import decode_payload
from schemas.jsonl import decode_line
from schemas.times import NS_PER_S, format_time_ns
from sim.live import Pacer, milestones
from sim.pty import PtyDevice
from sim.runner import RunStats, Simulation
from sim.scenario import BED_B_ORIGIN_Y_M, demo, two_bed_reclaim, two_bed_stack
from tests.cli_in_process import run as stockpile

STOCKPILE = str(Path(sys.executable).with_name("stockpile"))
SEED = 1
SCENARIO = replace(demo(), scan_hz=0.5, gnss_hz=0.5, encoder_hz=1.0, live_rates=(1.0, 1.0, 2.0))
DURATION_H = 1.3                     # the stacking, the survey and two cuts
LIVE_AT_NS = SCENARIO.start_ns + 2300 * NS_PER_S   # mid-stacking, before the third lot
#: the yard's facts (not the sensors'): what a live run must emit as the plain run does
YARD_TYPES = ("lot_declared", "stack_started", "stack_ended", "reclaim_cut", "assay")
DECLARATIONS = ("site_declared", "pile_declared", "machine_declared")


def _events(out: Path) -> list:
    return [decode_line(line) for line in (out / "events.jsonl").read_text().splitlines()]


def _truth(out: Path) -> dict:
    return json.loads((out / "truth.json").read_text())


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A plain run and a live run (with real ptys) of SCENARIO, seed 1: their out dirs,
    the live run's stats and its ptys."""
    base = tmp_path_factory.mktemp("live")
    plain = Simulation(SCENARIO, SEED, base / "plain")
    plain.run(duration_h=DURATION_H)
    ptys = {"scanner": PtyDevice(write_timeout_s=0.0), "gnss": PtyDevice(write_timeout_s=0.0)}
    try:
        live = Simulation(SCENARIO, SEED, base / "live", scanner_pty=ptys["scanner"],
                          gnss_pty=ptys["gnss"])
        stats = live.run(duration_h=DURATION_H, live_at_ns=LIVE_AT_NS)
    finally:
        for pty in ptys.values():
            pty.close()
    return {"plain": base / "plain", "live": base / "live", "stats": stats, "ptys": ptys}


def test_a_live_run_has_the_plain_runs_world(runs):
    plain, live = _truth(runs["plain"]), _truth(runs["live"])
    assert plain["world"]["tonnes"] > 0 and len(plain["cuts"]) >= 2
    assert live["world"]["tonnes"] == plain["world"]["tonnes"]
    assert live["world"]["volume_m3"] == plain["world"]["volume_m3"]
    assert [c["true_tonnes"] for c in live["cuts"]] == [c["true_tonnes"] for c in plain["cuts"]]
    for key in ("world", "cuts", "passes", "assays"):
        assert live[key] == plain[key], key
    surfaces = [np.load(runs[name] / "truth.npz")["surface_z"] for name in ("plain", "live")]
    assert np.array_equal(surfaces[0], surfaces[1])
    assert live["stats"]["live_at_ns"] == LIVE_AT_NS and plain["stats"]["live_at_ns"] is None


def test_a_live_run_emits_nothing_before_its_live_moment(runs):
    events = _events(runs["live"])
    assert events and min(e.valid_time_ns for e in events) >= LIVE_AT_NS
    assert {e.epoch for e in events} == {LIVE_AT_NS // NS_PER_S}
    assert not [e for e in events if e.type in DECLARATIONS]
    seqs = defaultdict(list)
    for e in events:
        seqs[e.source].append(e.seq)
    assert all(s == list(range(len(s))) for s in seqs.values()), "each source from seq 0, dense"
    # the plain run declared the yard at its start, in the start's epoch
    plain = _events(runs["plain"])
    assert {e.type for e in plain} >= set(DECLARATIONS)
    assert {e.epoch for e in plain} == {SCENARIO.start_ns // NS_PER_S}
    # the sensors sampled nothing before the live moment, and the device files and ptys
    # carry only what they sampled from then on
    truth = np.load(runs["live"] / "truth.npz")
    for name in ("joints", "scanner_poses", "antenna_enu"):
        assert truth[name].shape[0] > 0 and truth[name][:, 0].min() >= LIVE_AT_NS, name
    stats, ptys = runs["stats"], runs["ptys"]
    lms = (runs["live"] / "lms200.bin").stat().st_size
    gnss = (runs["live"] / "gnss.nmea").read_bytes()
    assert lms == stats.lms200_bytes == ptys["scanner"].written_bytes + ptys["scanner"].dropped_bytes
    assert gnss.count(b"$G") == stats.gga == truth["antenna_enu"].shape[0]
    assert len(gnss) == ptys["gnss"].written_bytes + ptys["gnss"].dropped_bytes


def test_a_live_run_emits_the_yard_events_of_the_plain_run_from_its_live_moment(runs):
    def yard(events, since_ns):
        return [(e.type, e.source, e.valid_time_ns, e.payload) for e in events
                if e.type in YARD_TYPES and e.valid_time_ns >= since_ns]
    live, plain = yard(_events(runs["live"]), 0), yard(_events(runs["plain"]), LIVE_AT_NS)
    assert live == plain
    assert {kind for kind, *_ in live} >= {"lot_declared", "stack_started", "stack_ended",
                                           "reclaim_cut"}


def test_a_live_run_samples_at_the_live_rates(runs):
    """History rates before the live moment (the plain run), live rates from it on."""
    def first_step_s(out: Path, name: str) -> float:
        times = np.load(out / "truth.npz")[name][:3, 0].astype(np.int64)
        assert len(times) == 3
        steps = np.diff(times) / NS_PER_S
        assert steps[0] == steps[1]
        return float(steps[0])
    for name, plain_s, live_s in (("scanner_poses", 2.0, 1.0), ("antenna_enu", 2.0, 1.0),
                                  ("joints", 1.0, 0.5)):
        assert first_step_s(runs["plain"], name) == plain_s, name
        assert first_step_s(runs["live"], name) == live_s, name


def test_the_live_wall_time_sets_when_the_live_moment_happens(tmp_path):
    live_at = SCENARIO.start_ns + 3000 * NS_PER_S
    duration_h = (3000 + 20) / 3600     # 20 site s live, at 100x: 0.2 s wall
    sim = Simulation(SCENARIO, SEED, tmp_path)
    wall_s = time.time() + 3.0        # the fast-forward takes under a second
    stats = sim.run(duration_h=duration_h, speed=100.0, live_at_ns=live_at, live_wall_s=wall_s)
    assert time.time() >= wall_s + 0.2 - 0.05
    assert stats.live_late_s == 0.0 and stats.rebases == 0


def test_a_run_that_reaches_its_live_moment_late_says_so_in_one_line(tmp_path):
    wall_s = time.time() - 30.0
    done = subprocess.run([STOCKPILE, "sim", "--scenario", "demo", "--live-at",
                           "2026-11-01T00:50:00Z", "--live-wall", f"{wall_s:.3f}", "--speed",
                           "1000", "--duration", "3002s", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1
    record = parse_log_line(lines[0])
    assert record["level"] == "warning" and "late" in record["msg"]
    late_s = _truth(tmp_path)["stats"]["live_late_s"]
    assert late_s >= 30.0 and float(record["late_s"]) == pytest.approx(late_s, abs=0.001)


@pytest.mark.parametrize("rebase", [True, False])
def test_a_run_kept_to_its_live_wall_time_catches_up_rather_than_rebasing(rebase):
    stats = RunStats()
    pacer = Pacer(speed=1.0, idle_speed=0.0, stats=stats)
    pacer.start(time.monotonic() - 1.0, rebase=rebase)   # a second behind already
    pacer.wait(0, busy=True)
    assert stats.late_events == 1 and stats.max_lag_s >= 1.0
    assert stats.rebases == int(rebase)
    assert (pacer.schedule0_s > time.monotonic() - 0.5) is rebase


def test_a_source_prefix_names_the_yard_sources_and_assay_ids(tmp_path):
    plain = Simulation(demo(), SEED, tmp_path / "default")
    assert {n: plain.producers[n].source for n in ("config", "clock", "lims", "lab")} == {
        "config": "yard.config", "clock": "sim.clock", "lims": "lims", "lab": "lab1"}
    sc = replace(demo(), source_prefix="bedX")
    sim = Simulation(sc, SEED, tmp_path / "prefixed")
    assert {n: sim.producers[n].source for n in ("config", "clock", "lims", "lab")} == {
        "config": "bedX.config", "clock": "bedX.clock", "lims": "bedX.lims", "lab": "bedX.lab"}
    # a live window after the reclaim, while the lab reports
    t0 = sc.start_ns
    sim.run(duration_h=2.5, live_at_ns=t0 + int(2.3 * 3600) * NS_PER_S)
    events = _events(tmp_path / "prefixed")
    assays = [decode_payload("assay", e.payload) for e in events if e.type == "assay"]
    assert assays and {e.source for e in events if e.type == "assay"} == {"bedX.lab"}
    assert all(a.assay_id.startswith("bedX-AS-") for a in assays)
    assert all(a.supersedes == "" or a.supersedes.startswith("bedX-AS-") for a in assays)
    assert {e.source for e in events} <= {"bedX.clock", "bedX.lab", "bwr1.encoders"}
    truth = _truth(tmp_path / "prefixed")
    assert truth["assays"] and all(a["assay_id"].startswith("bedX-AS-") for a in truth["assays"])


@pytest.mark.parametrize("emits_clock", [False, True])
def test_a_run_without_the_clock_publishes_no_clock_event(tmp_path, emits_clock):
    sc = replace(demo(), emits_clock=emits_clock, scan_hz=1.0, gnss_hz=1.0, encoder_hz=1.0)
    pty = PtyDevice(write_timeout_s=0.0)     # a scanner pty: a tick before each telegram
    try:
        sim = Simulation(sc, SEED, tmp_path, scanner_pty=pty)
        stats = sim.run(duration_h=0.1)
    finally:
        pty.close()
    clocks = [e for e in _events(tmp_path) if e.type == "clock"]
    assert stats.scans > 0 and stats.passes == 0
    assert ("clock" in sim.producers) is emits_clock
    assert (len(clocks) > stats.scans) if emits_clock else clocks == []


def test_bed_b_stacks_inside_its_own_footprint(tmp_path, capsys):
    """40 site minutes of bed B (its first pass) through the CLI."""
    code, out, err = stockpile(capsys, "sim", "--scenario", "two-bed-reclaim", "--duration",
                               "40min", "--out", str(tmp_path))
    assert code == 0, err
    sc = two_bed_reclaim()
    truth = np.load(tmp_path / "truth.npz")
    columns = truth["thickness"].sum(axis=0)
    rows, cols = np.nonzero(columns > 0)
    y, x = truth["y_centres"][rows], truth["x_centres"][cols]
    y0, x0 = sc.pile_origin_y_m, sc.pile_origin_x_m
    assert y0 == BED_B_ORIGIN_Y_M and rows.size > 0
    assert y0 <= y.min() and y.max() <= y0 + sc.pile_length_m
    assert x0 <= x.min() and x.max() <= x0 + sc.pile_width_m
    assert _truth(tmp_path)["world"]["tonnes"] == pytest.approx(sc.tonnes_per_pass)
    travel = truth["joints"][:, 1]
    assert y0 <= travel.min() and travel.max() <= y0 + sc.pile_length_m
    events = _events(tmp_path)
    assert "clock" not in {e.type for e in events}
    pile = [decode_payload("pile_declared", e.payload) for e in events if e.type == "pile_declared"]
    assert [(p.pile_id, p.origin_y_m) for p in pile] == [("B", BED_B_ORIGIN_Y_M)]
    assert {e.source for e in events} == {"bedB.config", "bedB.lims", "stk2.plc", "bwr2.encoders"}
    lots = [decode_payload("lot_declared", e.payload).lot_id for e in events
            if e.type == "lot_declared"]
    assert lots == ["LOT-A0-B"]


def test_the_two_beds_overlap_in_time_and_space():
    a, b = two_bed_stack(), two_bed_reclaim()
    ma, mb = milestones(a, SEED), milestones(b, SEED)
    assert a.start_ns < mb["reclaim_start_ns"] < ma["stacking_end_ns"]
    assert a.pile_origin_y_m + a.pile_length_m < b.pile_origin_y_m
    assert {lot.lot_id for lot in a.lots}.isdisjoint(lot.lot_id for lot in b.lots)
    assert set(a.yard_sources().values()).isdisjoint(b.yard_sources().values())
    assert (a.machine_id, a.stacker_id, b.machine_id, b.stacker_id) == ("bwr1", "stk1", "bwr2", "stk2")
    assert (a.emits_clock, b.emits_clock) == (True, False)


def test_milestones_say_when_the_run_reclaims(tmp_path, capsys, runs):
    code, out, err = stockpile(capsys, "sim", "--scenario", "demo", "--milestones")
    assert code == 0, err
    ms = json.loads(out)
    assert ms["start_ns"] == demo().start_ns and ms["first_cut_start_ns"] is None
    assert ms["start_ns"] < ms["stacking_end_ns"] < ms["survey_end_ns"] < ms["reclaim_start_ns"]
    assert ms["reclaim_start_ns"] < ms["default_end_ns"] == ms["end_ns"]
    # the stacking plan does not depend on the sensors: the last stack_ended of SCENARIO's
    # plain run is the demo's stacking end
    ends = [e.valid_time_ns for e in _events(runs["plain"]) if e.type == "stack_ended"]
    assert max(ends) == ms["stacking_end_ns"]
    # a live demo run from 30 s before the reclaim start to its first cut's end: the
    # reclaimer is parked until the reclaim start and moves right after it
    reclaim = ms["reclaim_start_ns"]
    end_s = (reclaim - ms["start_ns"]) // NS_PER_S + 210
    code, out, err = stockpile(capsys, "sim", "--scenario", "demo", "--live-at",
                               format_time_ns(reclaim - 30 * NS_PER_S), "--duration",
                               f"{end_s}s", "--out", str(tmp_path))
    assert code == 0, err
    assert f"live from {reclaim - 30 * NS_PER_S}" in out
    joints = np.load(tmp_path / "truth.npz")["joints"]
    parked, moving = joints[joints[:, 0] <= reclaim], joints[joints[:, 0] > reclaim]
    assert len(parked) >= 2 and len(moving) >= 2
    assert (parked[:, 1:] == parked[0, 1:]).all()
    assert (moving[0, 1:] != parked[0, 1:]).any()
    cuts = _truth(tmp_path)["cuts"]
    assert cuts and cuts[0]["t0_ns"] > reclaim


@pytest.mark.parametrize("args, message", [
    (["--live-at", "2026-10-31T23:00:00Z"], "before the scenario's start"),
    (["--live-at", "2026-11-01T03:00:00Z", "--duration", "2h"], "after the run's end"),
    (["--live-at", "yesterday"], "not an ISO-8601 time"),
    (["--live-at", "1793491200500000000"], "in a later second"),
    (["--live-wall", "1800000000"], "--live-wall needs --live-at"),
    (["--live-at", "2026-11-01T01:00:00Z", "--live-wall", "1800000000"], "needs --speed > 0"),
    (["--live-at", "2026-11-01T01:00:00Z", "--live-wall", "nan", "--speed", "1"], "finite"),
    (["--live-at", "2026-11-01T01:00:00Z", "--adapters", "real"], "--adapters sim only"),
])
def test_live_option_errors_are_one_line(tmp_path, capsys, args, message):
    code, out, err = stockpile(capsys, "sim", "--scenario", "demo", "--out",
                               str(tmp_path / "out"), *args)
    assert code == 2 and out == ""
    assert len(err.splitlines()) == 1 and err.startswith("stockpile sim: error:")
    assert message in err
    assert not (tmp_path / "out").exists()

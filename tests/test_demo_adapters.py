"""``stockpile demo --adapters real``: the yard's machine, lab and scanner facts reach the
ledger through the real adapters (OPC UA, LIMS files, an LMS511 on TCP), exactly once.

The run goes far enough for every kind of fact: stacking, the bench's first cuts and the
first late assays (reported 2-6 h after their window), the idle wait for them at 2000x.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from devices.opcua_tags import load_map
from ledger import open_ledger
from schemas.events import decode_payload
from services.plc import only_source
from sim.adapters import LMS511_FIELD_DEG, PLC_MAP, RealDevices
from sim.runner import Simulation
from sim.scenario import demo

#: site time the run covers: the nine passes (0.9 h), the bench of cuts, the first assays
#: (seed 3: from 2.3 h)
DURATION = "3h"
SPEED = "40"
#: the adapters' sources -> the event types each carries
ADAPTER_TYPES = {"bwr1.encoders": {"joint_reading"}, "stk1.plc": {"stack_started", "stack_ended"},
                 "bwr1.plc": {"reclaim_cut"}, "lab1": {"assay"}, "bwr1.scanner": {"scan"}}
#: the emulated LMS511's field and step in the demo, deg, and its beams
FIELD_DEG, STEP_DEG = LMS511_FIELD_DEG
LMS511_BEAMS = math.floor(FIELD_DEG / STEP_DEG + 1e-9) + 1


@pytest.fixture(scope="module")
def adapters_demo(tmp_path_factory):
    """``stockpile demo --adapters real --duration 3h --seed 3``: (out dir, completed run)."""
    out = tmp_path_factory.mktemp("adapters-demo") / "demo"
    run = subprocess.run(
        [sys.executable, "-m", "stockpile.cli", "demo", "--adapters", "real", "--out", str(out),
         "--seed", "3", "--duration", DURATION, "--speed", SPEED],
        capture_output=True, text=True, timeout=1200)
    print(run.stdout[-4000:])
    return out, run


def _published_by(out, child: str) -> dict[str, tuple[int, int]]:
    """``source -> (epoch, count)`` from a child's ``published`` log lines."""
    found = {}
    for line in (out / "logs" / f"{child}.log").read_text().splitlines():
        if line.startswith("{"):
            record = json.loads(line)
        elif " msg=published " in line:
            record = dict(part.split("=", 1) for part in line.split() if "=" in part)
        else:
            continue
        if record.get("msg") == "published" and "source" in record:
            found[record["source"]] = (int(record["epoch"]), int(record["count"]))
    return found


@pytest.mark.slow
def test_real_adapters_deliver_every_fact_exactly_once(adapters_demo):
    out, run = adapters_demo
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ok"] and summary["verify_ok"] and summary["open_gaps"] == 0
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    for row in summary["exactly_once"]:
        assert row["exact"] and not row["open_gaps"] and row["duplicates"] == 0, row
    # the adapters' sources were published by the adapters, none by the simulator
    by_sim = _published_by(out, "sim")
    assert not set(ADAPTER_TYPES) & set(by_sim), by_sim
    by_adapter = {}
    for child in ("plc-bwr1.encoders", "plc-bwr1.plc", "plc-stk1.plc", "lab", "scanner"):
        by_adapter.update(_published_by(out, child))
    assert set(ADAPTER_TYPES) <= set(by_adapter), by_adapter

    truth = json.loads((out / "sim" / "truth.json").read_text())
    held: dict[tuple[str, str], int] = {}
    with open_ledger(out / "ledger.duckdb", read_only=True) as store:
        for r in store.read():
            held[(r.source, r.type)] = held.get((r.source, r.type), 0) + 1
            if r.source in ADAPTER_TYPES:
                assert r.type in ADAPTER_TYPES[r.source], (r.source, r.type)
                assert r.epoch == by_adapter[r.source][0], r.source
            if r.type == "scan":
                scan = decode_payload("scan", r.payload)
                assert len(scan.ranges) == LMS511_BEAMS
                step_deg = math.degrees(scan.end_angle - scan.start_angle) / (len(scan.ranges) - 1)
                assert math.isclose(step_deg, STEP_DEG, abs_tol=1e-4), step_deg
    # every pass and cut the simulator finished, every assay it reported, came through
    assert held[("stk1.plc", "stack_ended")] == len(truth["passes"]) > 0
    assert held[("bwr1.plc", "reclaim_cut")] == len(truth["cuts"]) > 0
    assert held[("lab1", "assay")] > 0
    assert held[("bwr1.encoders", "joint_reading")] > 1000
    assert held[("bwr1.scanner", "scan")] > 1000
    assert summary["localizer"]["localizer_samples"] > 100


# -- the pieces, fast ----------------------------------------------------------------------


def test_real_devices_get_the_facts_the_simulator_records(tmp_path):
    """A short run with real devices records the same events in events.jsonl as one without
    (and more clock ticks), and hands the encoder samples, passes and scans to the devices (a client reads the
    LMS511's telegrams: the output is on only while one listens)."""
    sc = demo()
    plain = Simulation(sc, 5, tmp_path / "sim")
    plain.run(duration_h=0.2)
    devices = RealDevices(sc, tmp_path / "real").start()
    try:
        real = Simulation(sc, 5, tmp_path / "real", adapters="real", devices=devices)
        stats = real.run(duration_h=0.2)
    finally:
        devices.close()
    recorded = (tmp_path / "real" / "events.jsonl").read_bytes()
    # the same events, but for the clock ticks the LMS511 gets before each telegram
    facts = [[line for line in path.read_bytes().splitlines()
              if not line.startswith(b'{"type":"clock"')]
             for path in (tmp_path / "real" / "events.jsonl", tmp_path / "sim" / "events.jsonl")]
    assert facts[0] == facts[1] and len(facts[0]) > 100
    assert recorded.count(b'{"type":"clock"') > (tmp_path / "sim" / "events.jsonl").read_bytes(
        ).count(b'{"type":"clock"')
    readings = recorded.count(b'"joint_reading"')
    assert devices.counts["encoder_samples"] == readings > 0
    assert devices.counts["passes"] == stats.passes > 0
    assert devices.counts["scans_sent"] == 0   # nobody turned the LMS511's output on
    assert real.scanner.n_beams == LMS511_BEAMS
    published = [p.source for name, p in real.producers.items() if name not in real.record_only]
    assert published == ["yard.config", "sim.clock", "lims"]


def test_plc_source_option_keeps_one_machine():
    plc_map = load_map(PLC_MAP)
    assert set(only_source(plc_map, "bwr1.encoders").machines) == {"bwr1"}
    assert set(only_source(plc_map, "stk1.plc").machines) == {"stk1"}
    assert only_source(plc_map, None) is plc_map
    for bad in ("stk1.encoders", "bwr9.plc", "bwr1.scanner", "bwr1"):
        with pytest.raises(ValueError, match="no such source"):
            only_source(plc_map, bad)

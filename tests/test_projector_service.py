"""``stockpile service projector`` as a real process beside a real ledger service.

A short simulated yard is imported into a DuckDB ledger; the ledger service serves it,
and the projector service catches up from it over Zenoh.  Then, live, a late assay and
a reclaim cut whose valid time lies before what the projector already folded (it must
rebuild) go through the ledger service.  Each answer of the projector is checked against
``project()`` on the ledger file, a separate read of the same facts (the file is read
before the ledger service opens it and after it stops).
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from ledger import open_ledger
from projector.query import project
from schemas import pb
from schemas.events import decode_payload, set_timestamp_ns
from services.ledger_client import LedgerClient
from services.projector_service import state_key
from services.service import EventPublisher
from zenoh_helpers import (
    client_args,
    log_lines,
    open_router,
    stockpile,
    stop_all,
    wait_liveliness,
    wait_until,
)

SITE = "proj"
PILE = "P1"
from schemas.times import NS_PER_S as S  # noqa: E402


@pytest.fixture(scope="module")
def small_ledger(small_yard_sim, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("projsvc") / "ledger.duckdb"
    subprocess.run([sys.executable, "-m", "stockpile.cli", "ledger", "import",
                    str(small_yard_sim / "events.jsonl"), "--ledger", str(path), "--clock",
                    "events"], check=True, capture_output=True, timeout=300)
    return path


def _ask(session: zenoh.Session) -> dict | None:
    for reply in session.get(state_key(SITE, PILE), timeout=5.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def _same(answer: dict, expected) -> None:
    assert answer["tonnes"] == pytest.approx(expected.tonnes, rel=1e-9)
    assert answer["volume_m3"] == pytest.approx(expected.volume_m3, rel=1e-9)
    assert answer["assayed_fraction"] == pytest.approx(expected.assayed_fraction, abs=1e-12)
    for analyte, value in expected.grade.items():
        if math.isfinite(value):
            assert answer["grade"][analyte] == pytest.approx(value, rel=1e-9), analyte
    assert [c["cut_id"] for c in answer["cuts"]] == [c.cut_id for c in expected.cuts]
    for mine, theirs in zip(answer["cuts"], expected.cuts):
        assert mine["tonnes"] == pytest.approx(theirs.tonnes, rel=1e-9)


def test_projector_service_follows_the_ledger_and_rebuilds_on_late_geometry(
        small_ledger, tmp_path):
    path = tmp_path / "ledger.duckdb"
    shutil.copy(small_ledger, path)
    with open_ledger(path, read_only=True) as store:
        before = project(store, PILE)
        events = list(store.read())
    assert before.tonnes > 0, "the simulated pass must have left material"
    lot = next(decode_payload(e.type, e.payload).lot_id for e in events
               if e.type == "stack_started")
    machine = next(decode_payload(e.type, e.payload) for e in events
                   if e.type == "machine_declared")
    started = next(e.valid_time_ns for e in events if e.type == "stack_started")
    ended = next(e.valid_time_ns for e in events if e.type == "stack_ended")

    router, endpoint = open_router()
    ledger = stockpile("service", "ledger", "--ledger", str(path), "--site", SITE,
                       "--status-period", "1", *client_args(endpoint),
                       stderr_path=tmp_path / "ledger.log")
    projector = None
    try:
        wait_liveliness(router, f"stockpile/{SITE}/@live/ledger/**", 30)
        projector = stockpile("service", "projector", "--pile", PILE, "--site", SITE,
                              "--publish-period-s", "0", "--status-period", "1",
                              "--reorder-s", "5",    # so the late cut below is late
                              *client_args(endpoint), stderr_path=tmp_path / "projector.log")
        wait_liveliness(router, f"stockpile/{SITE}/@live/projector/**", 60)
        head = LedgerClient(router, SITE).head()["global_seq"]
        answers: list[dict] = []

        def answered_at(seq: int) -> bool:
            answer = _ask(router)
            if answer is not None and answer["ledger_seq"] >= seq:
                answers.append(answer)
                return True
            return False

        wait_until(lambda: answered_at(head), 60, "the projector's catch-up answer")
        _same(answers[-1], before)
        assert answers[-1]["rebuilds"] == 0
        assert answers[-1]["assayed_fraction"] == 0.0   # no assay known yet

        # live: an assay of the stacked lot arrives (recorded now, hours after its window)
        lab = EventPublisher(router, SITE, "lab9", epoch=7)
        assay = pb.Assay(assay_id="AS-LIVE", lot_id=lot, status=pb.FINAL, lab_id="lab9",
                         bulk_density_t_m3=2.5)
        assay.analytes.update({"Fe": 64.0, "SiO2": 3.0})
        set_timestamp_ns(assay.window_start, started - 60 * S)
        set_timestamp_ns(assay.window_end, ended + 60 * S)
        set_timestamp_ns(assay.reported_time, ended + 3 * 3600 * S)
        lab.wait_matched("assay", 30)
        lab.publish(assay)
        wait_until(lambda: answered_at(head + 1), 30, "the answer after the assay")
        assert answers[-1]["assayed_fraction"] > 0.9
        # the assayed share now carries 64 % Fe; the rest keeps the planned grade
        planned = before.grade["Fe"]
        share = answers[-1]["assayed_fraction"]
        assert answers[-1]["grade"]["Fe"] == pytest.approx(
            share * 64.0 + (1 - share) * planned, abs=0.5)
        assert abs(answers[-1]["grade"]["Fe"] - 64.0) < abs(planned - 64.0)

        # a reclaim cut whose valid time is before what was folded: a rebuild
        plc = EventPublisher(router, SITE, "bwr9.plc", epoch=7)
        pivot_z = machine.rail_z_m + machine.l2_m + machine.l3_m
        luff = math.asin((1.0 + machine.cutting_radius_m - pivot_z) / machine.l5_m)
        rho = machine.l4_m + machine.l5_m * math.cos(luff)
        slew = math.asin(min(1.0, (30.0 - machine.rail_x_m) / rho))
        cut = pb.ReclaimCut(pile_id=PILE, cut_id="LATE-C01", bench_id="LATE",
                            machine_id=machine.machine_id, travel_m=30.0, luff_rad=luff,
                            slew_start_rad=slew - 0.15, slew_end_rad=slew + 0.15, tonnes=50.0)
        set_timestamp_ns(cut.start_time, ended + 5 * S)
        set_timestamp_ns(cut.end_time, ended + 65 * S)
        plc.wait_matched("reclaim_cut", 30)
        plc.publish(cut)
        wait_until(lambda: answered_at(head + 2), 60, "the answer after the late cut")
        assert answers[-1]["rebuilds"] >= 1
        assert [c["cut_id"] for c in answers[-1]["cuts"]] == ["LATE-C01"]
        assert answers[-1]["tonnes"] < before.tonnes
        final = answers[-1]
    finally:
        try:
            codes = stop_all(projector, ledger)
        finally:
            router.close()
    assert codes == [0, 0]
    with open_ledger(path, read_only=True) as store:
        after = project(store, PILE)
    _same(final, after)
    lines = log_lines(tmp_path / "projector.log")
    assert any(line["msg"] == "rebuilt" for line in lines)
    assert lines[-1]["msg"] == "stopped"

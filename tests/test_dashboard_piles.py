"""Several piles on one dashboard (a blending yard's two beds), read back with Rerun.

The ledger is the short simulated yard (``small_yard_sim``, pile ``P1`` stacked by one
pass) plus a second bed ``P2``: its own ``pile_declared`` (a wider footprint on a coarser
grid, 2 m voxels) and a stacking pass of its own over the same window, so the same scans
fall on both beds and each pile folds to different tonnes.  It is imported with the real
``stockpile ledger import``.  The offline command, the live catch-up driver (no Zenoh) and
the live service (over Zenoh, following a real ledger service) each write an .rrd that is
loaded with Rerun's own reader (``rerun.chunk.RrdReader``): with two piles every entity is
under ``/piles/<id>``; with one the paths are today's.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import rerun.chunk as rrc

from ledger import open_ledger
from projector.query import project
from schemas import pb
from schemas.events import set_timestamp_ns
from schemas.times import NS_PER_S as S
from services.dashboard import Config, PileSet
from services.dashboard.viewer import close_recording, make_recording
from services.ledger_client import LedgerClient
from services.service import EventPublisher
from stockpile import cli
from test_dashboard import Rrd
from zenoh_helpers import last_status, live_dashboard, log_lines, wait_until

PILES = ("P1", "P2")
SITE = "beds"
#: entities every drawn pile has (relative to its prefix) and their archetypes
EXPECTED = {"/site": "ViewCoordinates", "/site/pile/surface/Fe": "Mesh3D",
            "/site/pile/voxels": "Points3D", "/site/machines/bwr1": "LineStrips3D",
            "/site/scan": "Points3D", "/series/pile/tonnes_t/known_then": "Scalars",
            "/series/pile/tonnes_t/known_now": "Scalars",
            "/series/pile/grade_pct/Fe/known_then": "Scalars", "/log": "TextLog",
            "/status": "TextDocument", "/legend": "TextDocument"}
#: what Rerun adds to every recording (not ours)
RERUN_OWN = {"/__properties"}


def _line(event: dict, source: str, seq: int, **body) -> str:
    return json.dumps({"type": event["type"], "source": source, "epoch": event["epoch"],
                       "seq": seq, "valid_time_ns": event["valid_time_ns"],
                       "body": {**event["body"], **body}}) + "\n"


@pytest.fixture(scope="module")
def ledger(small_yard_sim, tmp_path_factory) -> Path:
    """The small yard plus bed P2 (declared beside P1, one stacking pass of its own)."""
    base = tmp_path_factory.mktemp("two-beds")
    lines = []
    for line in (small_yard_sim / "events.jsonl").read_text().splitlines(keepends=True):
        lines.append(line)
        event = json.loads(line)
        kind, body = event["type"], event["body"]
        if kind == "pile_declared" and body["pile_id"] == "P1":
            lines.append(_line(event, "bed2.config", 0, pile_id="P2", origin_x_m=5.0,
                               origin_y_m=-5.0, width_m=50.0, length_m=70.0, cell_m=0.5,
                               voxel_m=2.0))
        elif kind in ("stack_started", "stack_ended") and body["pass_id"] == "LOT-A-P1":
            lines.append(_line(event, "stk2.plc", int(kind == "stack_ended"), pile_id="P2",
                               pass_id="P2-LOT-A-1"))
    jsonl = base / "two-beds.jsonl"
    jsonl.write_text("".join(lines))
    path = base / "two-beds.duckdb"
    assert cli.main(["ledger", "import", str(jsonl), "--ledger", str(path), "--clock",
                     "events"]) == 0
    with open_ledger(path, read_only=True) as store:
        declared = [e for e in store.read(types=["pile_declared"])]
        assert len(declared) == 2
    return path


@pytest.fixture(scope="module")
def truth(ledger) -> dict:
    """``project()`` of each pile at the head, and the head's seq."""
    with open_ledger(ledger, read_only=True) as store:
        return {"head": store.head().global_seq, **{p: project(store, p) for p in PILES}}


def _paths(rrd: Rrd) -> set[str]:
    return {c.entity_path for c in rrd.chunks} - RERUN_OWN


def _origins(path: Path) -> set[str]:
    """The origins of the views of every blueprint in the .rrd."""
    reader = rrc.RrdReader(path)
    out = set()
    for bp in reader.blueprints():
        for chunk in reader.stream(store=bp).collect().stream().to_chunks():
            batch = chunk.to_record_batch()
            if "ViewBlueprint:space_origin" in batch.schema.names:
                out.update(o for row in batch.column("ViewBlueprint:space_origin").to_pylist()
                           if row for o in row)
    return out


def _texts(rrd: Rrd, entity: str, column: str) -> list[str]:
    return [t for _v, _s, batch in rrd.rows(entity, column) for t in batch]


def _check_two_piles(rrd: Rrd, truth: dict, head: int) -> None:
    """Every entity under its pile's prefix, both piles drawn, each with its own figures."""
    paths = _paths(rrd)
    assert paths and all(p.startswith(("/piles/P1/", "/piles/P2/")) for p in paths), \
        sorted(p for p in paths if not p.startswith("/piles/"))
    for pile in PILES:
        for entity, archetype in EXPECTED.items():
            assert archetype in rrd.archetypes.get(f"/piles/{pile}{entity}", set()), (pile, entity)
        then = rrd.scalars(f"/piles/{pile}/series/pile/tonnes_t/known_then")
        assert then[-1][1] == head
        assert then[-1][2] == truth[pile].tonnes, pile
        (status,) = _texts(rrd, f"/piles/{pile}/status", "TextDocument:text")[-1:]
        assert status.startswith(f"### Pile {pile}\n")
    assert truth["P1"].tonnes != truth["P2"].tonnes   # a pile's figures under another's fail


def test_offline_command_renders_two_piles_each_under_its_prefix(ledger, truth, tmp_path,
                                                                   capsys):
    two, one = tmp_path / "two.rrd", tmp_path / "one.rrd"
    assert cli.main(["dashboard", "--ledger", str(ledger), "--pile", "P1", "--pile", "P2",
                     "--out", str(two), "--every", "10min", "--no-progress"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert [line.split(":")[1].strip() for line in out] == ["pile P1", "pile P2"]
    assert cli.main(["dashboard", "--ledger", str(ledger), "--pile", "P1", "--out", str(one),
                     "--every", "10min", "--no-progress"]) == 0
    rrd2, rrd1 = Rrd(two), Rrd(one)
    assert len(rrd2.recordings) == 1 and len(rrd2.blueprints) == 1
    _check_two_piles(rrd2, truth, truth["head"])
    # one pile: today's paths, nothing under /piles; two: the same entities under /piles/P1
    one_paths = _paths(rrd1)
    assert set(EXPECTED) <= one_paths
    assert not any(p.startswith("/piles") for p in one_paths)
    assert {p[len("/piles/P1"):] for p in _paths(rrd2) if p.startswith("/piles/P1/")} == one_paths
    assert (rrd2.scalars("/piles/P1/series/pile/tonnes_t/known_then")
            == rrd1.scalars("/series/pile/tonnes_t/known_then"))
    # the blueprint: a tab per pile, every view on its pile's entities
    origins2, origins1 = _origins(two), _origins(one)
    assert {"/piles/P1/site", "/piles/P2/site", "/piles/P1/log", "/piles/P2/log",
            "/piles/P2/series/pile/tonnes_t"} <= origins2
    assert all(o.startswith(("/piles/P1/", "/piles/P2/")) for o in origins2), origins2
    assert {o[len("/piles/P2"):] for o in origins2 if o.startswith("/piles/P2/")} == origins1
    assert {"/site", "/log", "/series/pile/tonnes_t"} <= origins1


def test_live_catch_up_feeds_each_pile_from_one_reading(ledger, truth, tmp_path):
    """The live service's driver (:class:`PileSet`, as its catch-up runs it) without Zenoh:
    the records read once, each pile's own fold and updates, the blueprint sent live."""
    with open_ledger(ledger, read_only=True) as store:
        records = list(store.read(0, truth["head"] + 1))
    results = {}
    for piles in (PILES, PILES[:1]):
        config = Config(site="test", piles=piles, rrd=str(tmp_path / f"{len(piles)}.rrd"),
                        every_s=600.0)
        rec, _uri = make_recording(config)
        dashes = PileSet(rec, config)
        for start in range(0, len(records), 5000):   # in reads, as the live catch-up reads
            assert dashes.feed(records[start:start + 5000]) == len(records[start:start + 5000])
        for dash in dashes:
            dash.update()
        dashes.flush_known_now()
        close_recording(rec)
        assert dashes.seq == truth["head"]
        results[piles] = dashes
    two, one = results[PILES], results[PILES[:1]]
    # each pile keeps its own fold, tracker and history
    assert two.first.tracker is not two.dashes[1].tracker
    assert [d.last_state.tonnes for d in two] == [truth[p].tonnes for p in PILES]
    assert two.first.updates == one.first.updates
    assert two.updates == sum(d.updates for d in two) > one.updates
    rrd2, rrd1 = Rrd(tmp_path / "2.rrd"), Rrd(tmp_path / "1.rrd")
    _check_two_piles(rrd2, truth, truth["head"])
    assert {p[len("/piles/P1"):] for p in _paths(rrd2) if p.startswith("/piles/P1/")} \
        == _paths(rrd1)
    assert not any(p.startswith("/piles") for p in _paths(rrd1))
    assert (rrd2.scalars("/piles/P1/series/pile/tonnes_t/known_now")
            == rrd1.scalars("/series/pile/tonnes_t/known_now"))
    origins = _origins(tmp_path / "2.rrd")
    assert {"/piles/P1/site", "/piles/P2/site"} <= origins
    assert all(o.startswith("/piles/") for o in origins), origins



def test_live_service_follows_the_ledger_once_for_two_piles(ledger, truth, tmp_path):
    path = tmp_path / "ledger.duckdb"
    shutil.copy(ledger, path)
    head = truth["head"]
    out, dash_log = tmp_path / "live.rrd", tmp_path / "dashboard.log"
    # one process, one token naming both piles
    with live_dashboard(path, SITE, ("P1", "P2"), out, tmp_path) as run:
        caught = run.caught
        assert int(caught["head"]) == head and caught["piles"] == "P1,P2"
        assert int(caught["records"]) == head + 1   # read once, not once per pile
        # live: the lab's first assay of LOT-A, the lot of both beds' passes
        lab = EventPublisher(run.router, SITE, "lab9", epoch=7)
        assay = pb.Assay(assay_id="AS-BEDS", lot_id="LOT-A", status=pb.FINAL, lab_id="lab9",
                         bulk_density_t_m3=2.2)
        assay.analytes.update({"Fe": 64.5, "SiO2": 3.0})
        set_timestamp_ns(assay.window_start, 1793491500 * S)
        set_timestamp_ns(assay.window_end, 1793491800 * S)
        set_timestamp_ns(assay.reported_time, 1793520000 * S)
        lab.wait_matched("assay", 30)
        lab.publish(assay)
        LedgerClient(run.router, SITE).wait_for(lambda h: h["global_seq"] >= head + 1, 30)
        updates0 = int(caught["updates"])
        wait_until(lambda: int(last_status(dash_log).get("records", 0)) >= head + 2
                   and int(last_status(dash_log).get("updates", 0)) >= updates0 + 2,
                   60, "both piles' updates after the live assay")
    assert run.codes == [0, 0]
    stopped = log_lines(dash_log)[-1]
    assert stopped["msg"] == "stopped" and int(stopped["records"]) == head + 2
    with open_ledger(path, read_only=True) as store:
        assert store.head().global_seq == head + 1
        now = {p: project(store, p) for p in PILES}
    rrd = Rrd(out)
    _check_two_piles(rrd, now, head + 1)
    for pile in PILES:   # each pile updated live with the assay, from the one reading
        fe = rrd.scalars(f"/piles/{pile}/series/pile/grade_pct/Fe/known_then")
        assert fe[-1][1] == head + 1 and fe[-1][2] == now[pile].grade["Fe"]
        assert fe[-2][2] != pytest.approx(fe[-1][2], abs=0.5)   # planned 56.23 -> assayed
        texts = _texts(rrd, f"/piles/{pile}/log", "TextLog:text")
        assert any(t.startswith("assay AS-BEDS (FINAL) for lot LOT-A") for t in texts)


def test_argument_errors_are_one_line(ledger, tmp_path, capsys):
    x = str(tmp_path / "x.rrd")
    # the service in a child (its SIGUSR1 stack dump wants a real stderr): before any Zenoh
    service = subprocess.run([sys.executable, "-m", "stockpile.cli", "service", "dashboard",
                              "--pile", "P1", "--pile", "P1", "--out", x],
                             capture_output=True, text=True, timeout=120)
    assert service.returncode == 2
    assert service.stderr.strip().splitlines() == ["stockpile: error: --pile P1 is given twice"]
    for argv, needle in (
            (["dashboard", "--ledger", str(ledger), "--pile", "P2", "--pile", "P2", "--out", x],
             "--pile P2 is given twice"),
            (["dashboard", "--ledger", str(ledger), "--pile", "P1", "--pile", "NOPE",
              "--out", x], "pile 'NOPE' is not declared"),
            (["dashboard", "--ledger", str(ledger), "--out", x],
             "declares several piles (P1, P2): pass --pile"),
            (["dashboard", "--ledger", str(ledger), "--pile", "P1", "--pile", "P2", "--out", x,
              "--plan-machine", "bwr1"], "--plan-machine plans one pile")):
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("stockpile: error:") and needle in err[0], err
    assert not Path(x).exists()
    with pytest.raises(ValueError, match="given twice"):
        Config(piles=("A", "B", "A"))
    with pytest.raises(ValueError, match="not the first"):
        Config(pile_id="B", piles=("A", "B"))
    assert Config(piles=("A", "B")).pile_id == "A"
    assert Config(pile_id="A").piles == ("A",)

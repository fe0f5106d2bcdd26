"""The operators' Rerun dashboard, rendered from a real ledger and read back with Rerun.

The ledger is the one of ``test_audit`` (the short simulated yard of ``small_yard_sim``,
seed 2, plus a reclaim cut and the lab's late assays), imported once per session.  The
offline renderer (``stockpile dashboard``) and the live service (``stockpile service
dashboard`` following a real ledger service over Zenoh) write .rrd files; they are
loaded with Rerun's own reader (``rerun.chunk.RrdReader``) and checked: entities and
archetypes, the ``valid_time``/``ledger_seq`` timelines (and no wall-clock timeline),
the blueprint, and the pile tonnes against ``project()`` on the same ledger.
"""

from __future__ import annotations

import shutil
from collections import defaultdict
from pathlib import Path

import pytest

import rerun.chunk as rrc

from ledger import open_ledger
from projector.query import project
from schemas import pb
from schemas.events import set_timestamp_ns
from stockpile import cli
from services.dashboard import Config, render_ledger
from services.ledger_client import LedgerClient
from services.service import EventPublisher
from test_audit import CUT, PILE, SEED, audit_ledger
from zenoh_helpers import (last_status, live_dashboard, log_lines, service_on_a_stuck_ledger,
                           stop, wait_until)

from schemas.times import NS_PER_S as S  # noqa: E402
SITE = "dash"


class Rrd:
    """What an .rrd holds, read with Rerun's own reader."""

    def __init__(self, path: Path) -> None:
        reader = rrc.RrdReader(path)
        self.recordings = reader.recordings()
        self.blueprints = reader.blueprints()
        store = reader.stream().collect()
        self.chunks = store.stream().to_chunks()
        self.schema = store.schema()
        self.blueprint_paths = {c.entity_path for c in
                                reader.stream(store=self.blueprints[0]).collect().stream()
                                .to_chunks()} if self.blueprints else set()
        self.archetypes: dict[str, set[str]] = defaultdict(set)
        self.timelines: dict[str, set[tuple[str, ...]]] = defaultdict(set)
        for chunk in self.chunks:
            batch = chunk.to_record_batch()
            for name in batch.schema.names:
                if ":" in name:
                    self.archetypes[chunk.entity_path].add(name.split(":")[0])
            self.timelines[chunk.entity_path].add(tuple(sorted(chunk.timeline_names)))

    def rows(self, entity: str, column: str) -> list[tuple[int, int, object]]:
        """``(valid_time ns, ledger_seq, value)`` of a temporal column, sorted."""
        out = []
        for chunk in self.chunks:
            if chunk.entity_path != entity or chunk.is_static:
                continue
            batch = chunk.to_record_batch()
            if column not in batch.schema.names:
                continue
            valid = batch.column("valid_time").cast("int64").to_pylist()
            seq = batch.column("ledger_seq").to_pylist()
            out.extend(zip(valid, seq, batch.column(column).to_pylist()))
        return sorted(out, key=lambda r: (r[0], r[1]))

    def scalars(self, entity: str) -> list[tuple[int, int, float]]:
        return [(v, s, x[0]) for v, s, x in self.rows(entity, "Scalars:scalars") if x]


@pytest.fixture(scope="module")
def ledger(small_yard_sim, tmp_path_factory) -> Path:
    print(f"simulated yard seed {SEED}")
    return audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())[0]


@pytest.fixture(scope="module")
def offline(ledger, tmp_path_factory):
    out = tmp_path_factory.mktemp("dashboard") / "pile.rrd"
    config = Config(rrd=str(out), every_s=120.0, layers=True)
    result = render_ledger(str(ledger), None, config)
    return result, Rrd(out)


def test_offline_rrd_has_the_entities_archetypes_timelines_and_blueprint(offline):
    result, rrd = offline
    assert result.pile_id == PILE and result.updates >= 5
    assert len(rrd.recordings) == 1 and len(rrd.blueprints) == 1
    expected = {
        "/site": "ViewCoordinates",
        "/site/pile/surface/Fe": "Mesh3D", "/site/pile/surface/SiO2": "Mesh3D",
        "/site/pile/voxels": "Points3D", "/site/pile/layers": "LineStrips3D",
        "/site/machines/bwr1": "LineStrips3D", "/site/machines/bwr1/rail_m": "LineStrips3D",
        "/site/scan": "Points3D", "/site/cuts": "LineStrips3D",
        "/series/pile/tonnes_t/known_then": "Scalars", "/series/pile/tonnes_t/known_now": "Scalars",
        "/series/pile/grade_pct/Fe/known_then": "Scalars",
        "/series/pile/grade_pct/SiO2/known_now": "Scalars",
        "/series/pile/assayed_fraction/known_now": "Scalars",
        "/series/cuts/tonnes_t/geometry": "Scalars", "/series/cuts/tonnes_t/belt_scale": "Scalars",
        "/series/cuts/grade_pct/Fe/at_end": "Scalars",
        "/series/cuts/grade_pct/Fe/known_now": "Scalars",
        "/log": "TextLog", "/cuts/table": "TextDocument", "/status": "TextDocument",
    }
    for entity, archetype in expected.items():
        assert archetype in rrd.archetypes.get(entity, set()), (entity, rrd.archetypes.get(entity))
    # the timelines come from the data: valid_time (timestamp) and ledger_seq (sequence)
    for entity, sets in rrd.timelines.items():
        for names in sets:
            assert names in ((), ("ledger_seq", "valid_time")), (entity, names)
    assert not any("log_time" in t or "log_tick" in t for sets in rrd.timelines.values()
                   for names in sets for t in names)
    valid = rrd.rows("/series/pile/tonnes_t/known_then", "Scalars:scalars")
    chunk = next(c for c in rrd.chunks if c.entity_path == "/series/pile/tonnes_t/known_then"
                 and not c.is_static)
    batch = chunk.to_record_batch()
    assert str(batch.schema.field("valid_time").type).startswith("timestamp[ns")
    assert str(batch.schema.field("ledger_seq").type) == "int64"
    assert len(valid) == result.updates
    # the blueprint lays out a 3D view, time series, the log and documents
    assert any(p.startswith("/view/") for p in rrd.blueprint_paths)
    assert "/time_panel" in rrd.blueprint_paths


def test_logged_tonnes_match_the_projector(offline, ledger):
    result, rrd = offline
    then = rrd.scalars("/series/pile/tonnes_t/known_then")
    now = rrd.scalars("/series/pile/tonnes_t/known_now")
    assert [v for v, _s, _x in then] == sorted({v for v, _s, _x in then})  # one row per update
    with open_ledger(ledger, read_only=True) as store:
        recorded = {e.global_seq: e.recorded_time_ns for e in store.read()}
        head = store.head()
        everything = project(store, PILE)
        # each update is the pile as of V as known at K (K = the recorded time of its seq)
        picks = [then[len(then) // 3]]
        expected = [project(store, PILE, v, recorded[s]) for v, s, _x in picks]
    for (v, s, tonnes), exp in zip(picks, expected):
        assert tonnes == exp.tonnes, (v, s)
    assert then[-1][1] == head.global_seq
    assert then[-1][2] == everything.tonnes
    assert result.tonnes_t == everything.tonnes
    # "as known now": once per history point, all at the head; the last one is exact
    assert [v for v, _s, _x in now] == [v for v, _s, _x in then]
    assert {s for _v, s, _x in now} == {head.global_seq}
    assert now[-1][2] == everything.tonnes
    fe_now = rrd.scalars("/series/pile/grade_pct/Fe/known_now")[-1][2]
    assert fe_now == everything.grade["Fe"]
    # before the lab answered, "then" used the planned density and grade; now the assays
    early = next(i for i, (v, s, x) in enumerate(then) if x > 0)
    assert now[early][2] != pytest.approx(then[early][2], rel=1e-6)
    cut = next(c for c in everything.cuts if c.cut_id == CUT)
    (at_end,) = rrd.scalars("/series/cuts/grade_pct/Fe/at_end")
    (cut_now,) = rrd.scalars("/series/cuts/grade_pct/Fe/known_now")
    assert at_end[0] == cut_now[0] == cut.end_time_ns
    assert cut_now[2] == cut.grade["Fe"]
    assert abs(cut_now[2] - at_end[2]) > 1.0   # the late assays moved it
    (geometry,) = rrd.scalars("/series/cuts/tonnes_t/geometry")
    (belt,) = rrd.scalars("/series/cuts/tonnes_t/belt_scale")
    assert belt[2] == cut.tonnes_scale
    assert geometry[2] > 0


def test_offline_render_shows_the_planned_bench_coloured_by_predicted_grade(ledger, tmp_path):
    from planner.cli import make_plan, plan_args

    out = tmp_path / "plan.rrd"
    config = Config(rrd=str(out), every_s=3600.0, plan_machine="bwr1", plan_cuts=3)
    result = render_ledger(str(ledger), None, config)
    plan = make_plan(plan_args(str(ledger), PILE, "bwr1", cuts=3))
    assert plan["landing"] is not None and len(plan["cuts"]) == 3
    assert result.planned_cuts == 3
    rrd = Rrd(out)
    assert "LineStrips3D" in rrd.archetypes["/site/plan"]
    assert "TextDocument" in rrd.archetypes["/plan/table"]
    (labels,) = [x for _v, _s, x in rrd.rows("/site/plan", "LineStrips3D:labels")]
    (colours,) = [x for _v, _s, x in rrd.rows("/site/plan", "LineStrips3D:colors")]
    expected = [f"plan {c['cut']}: {c['tonnes']:,.4g} t, Fe {c['grade']['Fe']:.2f} %"
                for c in plan["cuts"]]
    assert labels == expected
    # each footprint's colour is its predicted Fe on the scale the table states
    import re

    from services.dashboard.style import colour_map

    (table,) = [x for _v, _s, x in rrd.rows("/plan/table", "TextDocument:text")]
    lo, hi = map(float, re.search(r"predicted Fe: ([-0-9.]+) % blue to ([-0-9.]+) % red",
                                  table[0]).groups())
    fe = [c["grade"]["Fe"] for c in plan["cuts"]]
    assert lo <= min(fe) and max(fe) <= hi
    rgb = colour_map(fe, lo, hi)
    assert [int(c) >> 8 for c in colours] == [(r << 16) | (g << 8) | b for r, g, b in
                                              rgb.astype(int).tolist()]


def test_log_and_latest_state_only(offline):
    result, rrd = offline
    texts = [t for _v, _s, batch in rrd.rows("/log", "TextLog:text") for t in batch]
    assert any("assay AS-00001 (FINAL)" in t and "h after its window" in t for t in texts)
    assert any(t.startswith("assay AS-P01 superseded by AS-00001") for t in texts)
    assert any(t.startswith(f"reconciliation: cut {CUT} Fe") for t in texts)
    assert any("AS-Z01" in t and "lot not declared" in t for t in texts)
    assert any(t.startswith(f"cut {CUT}") for t in texts)
    # 3D entities: at most one row per update, each the whole latest state
    for entity, column in (("/site/pile/surface/Fe", "Mesh3D:vertex_colors"),
                           ("/site/pile/voxels", "Points3D:positions"),
                           ("/site/machines/bwr1", "LineStrips3D:strips"),
                           ("/site/cuts", "LineStrips3D:strips")):
        rows = rrd.rows(entity, column)
        assert 0 < len(rows) <= result.updates, entity
        assert len({v for v, _s, _x in rows}) == len(rows), entity
    (cuts_row,) = [r for r in rrd.rows("/site/cuts", "LineStrips3D:labels")][-1:]
    assert cuts_row[2] == [CUT]
    sizes = {len(x) for _v, _s, x in rrd.rows("/site/pile/surface/Fe", "Mesh3D:vertex_colors")}
    assert len(sizes) == 1   # the mesh is the pile's fixed grid: it never grows


def test_bad_input_is_one_line_and_exit_2(ledger, tmp_path, capsys):
    for argv, needle in (
            (["dashboard", "--ledger", str(tmp_path / "none.duckdb"), "--out",
              str(tmp_path / "x.rrd")], "no ledger at"),
            (["dashboard", "--ledger", str(ledger), "--pile", "NOPE", "--out",
              str(tmp_path / "x.rrd")], "pile 'NOPE' is not declared"),
            (["dashboard", "--ledger", str(ledger)], "--out")):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("stockpile: error:") and needle in err[0]
    assert not (tmp_path / "x.rrd").exists()


def test_machine_joints_from_the_localizers_scanner_pose_round_trip():
    """The reclaimer is drawn from its scanner pose: invert the localizer's own forward chain."""
    import numpy as np

    from projector.kinematics import Reclaimer
    from services.dashboard.pose import joints_from_wheel_pose, wheel_from_scanner
    from services.dashboard.pose import quat_matrix as _quat_matrix
    from projector.kinematics import MachineGeometry, scanner_pose

    mount_q = (0.5, 0.5, 0.5, -0.5)   # the simulator's scanner-in-wheel rotation
    geometry = MachineGeometry(rail_x_m=-25.0, rail_z_m=0.5, l2_m=6.0, l3_m=5.0, l4_m=5.0,
                               l5_m=50.0, scanner_translation_m=(0.0, 0.0, 3.0),
                               scanner_rotation_xyzw=mount_q)
    machine = Reclaimer(rail_x_m=-25.0, rail_z_m=0.5, l2_m=6.0, l3_m=5.0, l4_m=5.0, l5_m=50.0,
                        cutting_radius_m=10.0, wheel_tilt_rad=0.087)
    mount = (_quat_matrix(mount_q), np.array([0.0, 0.0, 3.0]))
    for joints in ((12.0, 0.9, -0.05), (-28.7, 1.2, 0.1), (40.0, 2.5, -0.3)):
        p, q = scanner_pose(geometry, np.array(joints))
        centre, rotation = wheel_from_scanner(p, q, mount)
        assert joints_from_wheel_pose(machine, centre, rotation) == pytest.approx(joints,
                                                                                 abs=1e-9)


def test_merged_voxels_keep_tonnes_and_grade_tonnes():
    import numpy as np

    from services.dashboard.scene import merge_voxels as _merge_voxels
    from services.dashboard.style import colour_map

    rng = np.random.default_rng(SEED)
    tonnes = rng.random((7, 5, 3)) * (rng.random((7, 5, 3)) > 0.3)
    grade = 50.0 + 10.0 * rng.random((7, 5, 3))
    merged_t, merged_g = _merge_voxels(tonnes, grade, 2)
    assert merged_t.shape == (4, 3, 2)
    assert merged_t.sum() == pytest.approx(tonnes.sum())
    assert (merged_t * merged_g).sum() == pytest.approx((tonnes * grade).sum())
    assert merged_t[0, 0, 0] == pytest.approx(tonnes[:2, :2, :2].sum())
    colours = colour_map([50.0, 60.0, float("nan")], 50.0, 60.0)
    assert colours[0][2] > colours[0][0] and colours[1][0] > colours[1][2]   # blue .. red
    assert tuple(colours[2]) == (150, 150, 150)



def test_live_service_follows_the_ledger_service(ledger, tmp_path):
    path = tmp_path / "ledger.duckdb"
    shutil.copy(ledger, path)
    with open_ledger(path, read_only=True) as store:
        head = store.head().global_seq
    out = tmp_path / "live.rrd"
    with live_dashboard(path, SITE, (PILE,), out, tmp_path) as run:
        assert int(run.caught["head"]) == head
        # live: the lab revises the FINAL of pass 1 (Fe up 2 points)
        lab = EventPublisher(run.router, SITE, "lab9", epoch=7)
        assay = pb.Assay(assay_id="AS-LIVE", lot_id="LOT-A", status=pb.FINAL, lab_id="lab9",
                         supersedes="AS-00001", bulk_density_t_m3=2.39)
        assay.analytes.update({"Fe": 60.728, "SiO2": 4.0})
        set_timestamp_ns(assay.window_start, 1793491500 * S)
        set_timestamp_ns(assay.window_end, 1793491800 * S)
        set_timestamp_ns(assay.reported_time, 1793520000 * S)
        lab.wait_matched("assay", 30)
        lab.publish(assay)
        LedgerClient(run.router, SITE).wait_for(lambda h: h["global_seq"] >= head + 1, 30)
        updates0 = int(run.caught["updates"])
        wait_until(lambda: int(last_status(run.log).get("records", 0)) >= head + 2
                   and int(last_status(run.log).get("updates", 0)) > updates0,
                   60, "the dashboard's update after the live assay")
    assert run.codes == [0, 0]
    with open_ledger(path, read_only=True) as store:
        everything = project(store, PILE)
        assert store.head().global_seq == head + 1
    rrd = Rrd(out)
    then = rrd.scalars("/series/pile/tonnes_t/known_then")
    fe = rrd.scalars("/series/pile/grade_pct/Fe/known_then")
    assert then[-1][1] == fe[-1][1] == head + 1
    # project() in this process and the service's live fold in its own agree exactly (the
    # live assay moved the pile's tonnes by ~1.5e-3 and its Fe by ~2 pp)
    assert then[-1][2] == everything.tonnes
    assert then[-2][2] != pytest.approx(everything.tonnes, rel=5e-4)
    assert fe[-1][2] == everything.grade["Fe"]
    # the cut was re-logged as known now with the live assay: two rows at its end time
    cut_now = rrd.scalars("/series/cuts/grade_pct/Fe/known_now")
    cut = next(c for c in everything.cuts if c.cut_id == CUT)
    assert [s for _v, s, _x in cut_now] == [head, head + 1]
    assert cut_now[-1][2] == cut.grade["Fe"]
    assert cut_now[-1][2] > cut_now[0][2] + 1.0
    texts = [t for _v, _s, batch in rrd.rows("/log", "TextLog:text") for t in batch]
    assert any(t.startswith("assay AS-00001 superseded by AS-LIVE") for t in texts)
    assert sum(t.startswith(f"reconciliation: cut {CUT} Fe") for t in texts) >= 2
    assert any("revised as known now" in t for t in texts)
    assert log_lines(tmp_path / "dashboard.log")[-1]["msg"] == "stopped"


@pytest.mark.parametrize("service", ["dashboard", "projector"])
def test_a_live_service_waiting_for_the_ledger_stops_at_once_on_sigterm(service, tmp_path):
    # a "ledger service" that takes every query and never answers: the live service's
    # first query waits inside Zenoh, where Python runs no signal handler; its client
    # polls the stopper, so SIGTERM ends the wait rather than the query's 30 s timeout
    import time

    extra = ["--out", str(tmp_path / "live.rrd")] if service == "dashboard" else []
    with service_on_a_stuck_ledger(service, tmp_path / "service.log",
                                   "--pile", PILE, *extra) as process:
        t0 = time.monotonic()
        code = stop(process, timeout_s=20)
        waited_s = time.monotonic() - t0
    assert code == 0, (tmp_path / "service.log").read_text()[-2000:]
    assert waited_s < 10, f"the {service} service took {waited_s:.1f} s to stop"
    lines = log_lines(tmp_path / "service.log")
    assert not [line for line in lines if line.get("level") == "error"], lines

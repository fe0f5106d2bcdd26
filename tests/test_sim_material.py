"""The simulator's materials (sim.material): what a cut's faces do, measured on the world.

Real simulator runs of a small yard (the demo's lots, lab and machines; one lot of two
passes, two cuts, slow sensors); each run's seed is printed. A face is measured on the
world's own surface right after its cut (``cut_surfaces``: the surface at the next cut's
start, or the surface at the end): the steepest drop from a column holding material to
any of its 8 neighbours, over the block the cut's slide starts from (its footprint's
bbox, one cell around it).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sim.material import Material
from sim.reclaiming import footprint_bbox
from sim.runner import Simulation
from sim.scenario import SCENARIOS, cohesive, delayed, demo, scenario_by_name, standing

STOCKPILE = str(Path(sys.executable).with_name("stockpile"))
REPOSE_DEG = demo().repose_deg
#: the relaxation stops within 1 % of a cell's critical drop: slopes within 2 % in tan
TAN_TOLERANCE = 1.02
NS_PER_S = 1_000_000_000
#: one seed for every kind: the same pile up to the first cut, which takes the same tonnes
SEED = 11


def small(scenario):
    """The scenario on a small yard: one lot of two passes on a 20 m pile (about 8 m high,
    under the wheel centre's lowest height of 9.8 m, so the wheel leaves faces up to about
    80 deg), two cuts, slow sensors and clock (the run's time goes to casting scans)."""
    return replace(scenario, lots=scenario.lots[:1], passes_per_lot=2, pass_duration_s=200.0,
                   tonnes_per_pass=2_700.0, pile_length_m=20.0, scan_hz=0.2, encoder_hz=0.2,
                   gnss_hz=0.1, idle_hz=0.01, clock_busy_period_s=None, cuts_per_bench=(2,))


class MainPath(Simulation):
    """The runner with main's code path after a cut: the walls slump at once to repose."""

    def _settle_faces(self, t, c, at):
        self.world.settle_cut(c["parts"])


def run(scenario, seed: int, out: Path, *, duration_h: float | None = None,
        cls=Simulation) -> dict:
    """One run with the surface at each cut's start kept, and the pile's tonnes before and
    after each slide (every call of ``World.settle``) watched."""
    print(f"{scenario.name}: seed {seed}, material {scenario.material}")
    sim = cls(scenario, seed, out, cut_surfaces=True)
    watched: list[dict] = []
    settle = sim.world.settle

    def watch(*args, **kwargs):
        before_t = sim.world.tonnes()
        res = settle(*args, **kwargs)
        watched.append({"before_t": before_t, "after_t": sim.world.tonnes(), **res})
        return res

    sim.world.settle = watch
    sim.run(duration_h=duration_h)
    truth = json.loads((out / "truth.json").read_text())
    arrays = np.load(out / "truth.npz")
    surfaces = [*arrays["cut_surface_z"].astype(np.float64), arrays["surface_z"]]
    return {"sim": sim, "truth": truth, "arrays": arrays, "surfaces": surfaces,
            "watched": watched, "out": out}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Runs made once per module, by name, when a test first asks for them."""
    made: dict[str, dict] = {}

    def get(name: str, scenario=None, **kwargs) -> dict:
        if name not in made:
            made[name] = run(scenario, SEED, tmp_path_factory.mktemp(name.replace("/", "-")),
                             **kwargs)
        return made[name]
    return get


def footprints(r: dict) -> list[np.ndarray]:
    """Each cut's footprint (the union of its sub-sweeps'), in the order of the cuts."""
    parts = r["sim"].world.cuts
    n = len(r["truth"]["cuts"])
    per_cut = len(parts) // n
    return [np.logical_or.reduce([p.footprint for p in parts[k * per_cut:(k + 1) * per_cut]])
            for k in range(n)]


def steepest_deg(surface: np.ndarray, cell_m: float, ground_m: float,
                 region: np.ndarray) -> float:
    """The steepest slope (deg) from a column of ``region`` holding material to any of
    its 8 neighbours."""
    ny, nx = surface.shape
    padded = np.pad(surface, 1, mode="edge")
    tan_max = np.zeros_like(surface)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == dx == 0:
                continue
            drop = surface - padded[1 + dy:1 + dy + ny, 1 + dx:1 + dx + nx]
            np.maximum(tan_max, drop / (cell_m * math.hypot(dy, dx)), out=tan_max)
    held = region & (surface > ground_m + 1e-6)
    return math.degrees(math.atan(float(tan_max[held].max())))


def bbox_mask(footprint: np.ndarray) -> np.ndarray:
    """The footprint's bbox, one cell around it (the block its slide starts from)."""
    iy0, iy1, ix0, ix1 = footprint_bbox(footprint)
    mask = np.zeros_like(footprint)
    mask[max(iy0, 0):iy1, max(ix0, 0):ix1] = True
    return mask


def face_angles(r: dict) -> list[float]:
    """Per cut, the steepest slope (deg) around it right after it (the next cut's start)."""
    g = r["sim"].world.grid
    return [steepest_deg(r["surfaces"][k + 1], g.cell_m, g.ground_z_m, bbox_mask(fp))
            for k, fp in enumerate(footprints(r))]


def check_mass(r: dict) -> None:
    """Every slide moved material without losing any: the pile's tonnes before = after +
    lost over the border, and the world's accounts balance at the end."""
    for w in r["watched"]:
        assert abs(w["before_t"] - w["after_t"] - w["lost_tonnes"]) <= 1e-9 * w["before_t"], w
    balance = r["sim"].world.mass_balance()
    assert abs(balance["relative_residual"]) < 1e-12, balance
    assert all(abs(v) < 1e-12 for v in r["sim"].world.grade_balance().values())


def test_repose_is_mains_code_path_byte_for_byte(runs):
    """The default material is today's behaviour: a run equals, byte for byte, a run
    whose walls slump through main's call (``World.settle_cut`` after each cut)."""
    default = runs("repose", small(demo()))
    main = runs("repose/main", small(demo()), cls=MainPath)
    for name in ("events.jsonl", "lms200.bin", "gnss.nmea"):
        assert (default["out"] / name).read_bytes() == (main["out"] / name).read_bytes(), name
    truths = [dict(r["truth"]) for r in (default, main)]
    for truth in truths:
        truth["stats"] = {k: v for k, v in truth["stats"].items() if k != "wall_s"}
        assert "material" not in truth["scenario"]
        truth.pop("material")
    assert truths[0] == truths[1]
    for key in default["arrays"].files:
        assert np.array_equal(default["arrays"][key], main["arrays"][key]), key
    material = default["truth"]["material"]
    assert material["kind"] == "repose" and material["repose_deg"] == REPOSE_DEG
    # one slide per cut, at the cut's end, of the volume the cut's record says slumped
    cuts = default["truth"]["cuts"]
    assert [(s["cut_id"], s["time_ns"], s["moved_m3"]) for s in material["slides"]] == [
        (c["cut_id"], c["t1_ns"], c["slump_m3"]) for c in cuts]


def test_repose_faces_slump_to_the_angle_of_repose(runs):
    r = runs("repose", small(demo()))
    angles = face_angles(r)
    print("steepest after each cut (deg):", [f"{a:.1f}" for a in angles])
    limit = math.degrees(math.atan(math.tan(math.radians(REPOSE_DEG)) * TAN_TOLERANCE))
    assert all(a <= limit for a in angles), angles
    assert all(s["moved_m3"] > 0 for s in r["truth"]["material"]["slides"])
    check_mass(r)


def test_cohesive_faces_stand_steeper_than_repose_up_to_the_stand_angle(runs):
    r = runs("cohesive", small(cohesive()))
    stand = r["truth"]["material"]["stand_angle_deg"]
    assert stand == cohesive().material.stand_angle_deg > REPOSE_DEG + 10
    angles = face_angles(r)
    print("steepest after each cut (deg):", [f"{a:.1f}" for a in angles])
    limit = math.degrees(math.atan(math.tan(math.radians(stand)) * TAN_TOLERANCE))
    assert all(REPOSE_DEG + 10 < a <= limit for a in angles), angles
    slides = r["truth"]["material"]["slides"]
    assert [s["angle_deg"] for s in slides] == [stand] * len(r["truth"]["cuts"])
    # the same first cut (the same pile: one seed) slides less than it does to repose
    repose = runs("repose", small(demo()))
    first = [x["truth"]["cuts"][0] for x in (r, repose)]
    assert first[0]["true_tonnes"] == first[1]["true_tonnes"]
    assert 0.0 < first[0]["slump_m3"] < first[1]["slump_m3"], first
    check_mass(r)


def test_a_cohesive_face_higher_than_its_critical_height_fails_to_repose(runs):
    scenario = small(replace(cohesive(), material=Material("cohesive", stand_angle_deg=65.0,
                                                           critical_height_m=0.5)))
    r = runs("height", scenario)
    material = r["truth"]["material"]
    assert material["critical_height_m"] == 0.5
    slides = material["slides"]
    assert len(slides) == len(r["truth"]["cuts"]) == 2
    for s in slides:   # the small pile's cuts leave faces of metres
        assert s["face_height_m"] > 1.0 and s["angle_deg"] == REPOSE_DEG, s
    limit = math.degrees(math.atan(math.tan(math.radians(REPOSE_DEG)) * TAN_TOLERANCE))
    angles = face_angles(r)
    assert all(a <= limit for a in angles), angles
    check_mass(r)


def test_standing_faces_keep_the_wheels_cut(runs):
    r = runs("standing", small(standing()))
    truth = r["truth"]
    assert truth["material"]["kind"] == "standing"
    assert truth["material"]["slides"] == [] and r["watched"] == []
    for k, (fp, cut) in enumerate(zip(footprints(r), truth["cuts"])):
        before = r["surfaces"][k].astype(np.float32)
        after = r["surfaces"][k + 1].astype(np.float32)
        assert cut["slump_m3"] == 0.0
        # nothing outside the footprint moved; inside, the wheel only took material
        assert np.array_equal(after[~fp], before[~fp]), cut["cut_id"]
        assert np.all(after[fp] <= before[fp]) and np.any(after[fp] < before[fp] - 0.1)
    angles = face_angles(r)
    print("steepest after each cut (deg):", [f"{a:.1f}" for a in angles])
    assert all(a > cohesive().material.stand_angle_deg for a in angles), angles
    # the same pile (one seed) gives the same first cut as the default material
    assert truth["cuts"][0]["true_tonnes"] == runs("repose", small(demo()))["truth"]["cuts"][0]["true_tonnes"]
    check_mass(r)


def test_delayed_faces_stand_then_fail_to_repose_at_the_drawn_time(runs, tmp_path):
    """Each cut's face stands as cut until its drawn failure time and is at repose after
    it, with one slide at that time; the run goes on past its last assay until a minute
    after the last failure (7-8 h after the cut: later than any assay)."""
    scenario = small(replace(delayed(), material=Material(
        "delayed", failure_delay_s=(7 * 3600.0, 8 * 3600.0))))
    r = runs("delayed", scenario)
    truth = r["truth"]
    material = truth["material"]
    assert material["failure_delay_s"] == [7 * 3600.0, 8 * 3600.0]
    failures, slides, cuts = material["failures"], material["slides"], truth["cuts"]
    assert [f["cut_id"] for f in failures] == [c["cut_id"] for c in cuts]
    assert [s["cut_id"] for s in slides] == [c["cut_id"] for c in cuts]   # one slide each
    for f, s, c in zip(failures, slides, cuts):
        assert 7 * 3600 <= f["delay_s"] <= 8 * 3600 and f["happened"], f
        assert f["cut_end_ns"] == c["t1_ns"] and c["slump_m3"] == 0.0
        assert f["due_ns"] == c["t1_ns"] + round(f["delay_s"] * NS_PER_S)
        assert s["time_ns"] == f["due_ns"] and s["delay_s"] == f["delay_s"] and s["moved_m3"] >= 0
    # the first failure moves material (a slide takes whatever is unstable around it, a
    # later cut's face too: that cut's own failure then moves what is left, maybe nothing)
    assert slides[0]["moved_m3"] > 0
    assert failures[0]["delay_s"] != failures[1]["delay_s"]   # drawn per cut
    end_ns = scenario.start_ns + round(truth["stats"]["site_s"] * NS_PER_S)
    last_assay_ns = max(a["reported_ns"] for a in truth["assays"])
    last_failure_ns = max(f["due_ns"] for f in failures)
    print(f"last assay {(last_assay_ns - scenario.start_ns) / 3.6e12:.2f} h, last failure "
          f"{(last_failure_ns - scenario.start_ns) / 3.6e12:.2f} h, end "
          f"{(end_ns - scenario.start_ns) / 3.6e12:.2f} h after the start")
    assert last_assay_ns < last_failure_ns and abs(end_ns - last_failure_ns - 60 * NS_PER_S) < 1e3
    # after the failures: at repose around each cut
    g = r["sim"].world.grid
    limit = math.degrees(math.atan(math.tan(math.radians(REPOSE_DEG)) * TAN_TOLERANCE))
    final = [steepest_deg(r["surfaces"][-1], g.cell_m, g.ground_z_m, bbox_mask(fp))
             for fp in footprints(r)]
    assert all(a <= limit for a in final), final
    check_mass(r)
    # the same world, stopped a second before the first failure: the faces stand as cut
    first_due_ns = min(f["due_ns"] for f in failures)
    stop_h = (first_due_ns - NS_PER_S - scenario.start_ns) / 3.6e12
    early = run(scenario, SEED, tmp_path, duration_h=stop_h)
    assert early["truth"]["material"]["slides"] == [] and early["watched"] == []
    assert [f["happened"] for f in early["truth"]["material"]["failures"]] == [False, False]
    assert [f["due_ns"] for f in early["truth"]["material"]["failures"]] == [
        f["due_ns"] for f in failures]
    assert np.array_equal(early["surfaces"][1], r["surfaces"][1])   # the same second cut
    fps = footprints(early)
    cut_m = np.logical_or.reduce(fps)
    stood = early["surfaces"][-1].astype(np.float32)
    assert np.array_equal(stood[~cut_m], early["surfaces"][0].astype(np.float32)[~cut_m])
    standing_deg = [steepest_deg(early["surfaces"][-1], g.cell_m, g.ground_z_m, bbox_mask(fp))
                    for fp in fps]
    print("steepest before the failures (deg):", [f"{a:.1f}" for a in standing_deg],
          "after:", [f"{a:.1f}" for a in final])
    assert all(a > cohesive().material.stand_angle_deg for a in standing_deg), standing_deg


def test_every_scenario_writes_its_material(tmp_path):
    """``stockpile sim --scenario NAME`` for the new kinds; truth.json's ``material`` has
    the parameters the kind uses (None for those it does not)."""
    expected = {"demo": ("repose", None, None), "cohesive": ("cohesive", 50.0, None),
                "delayed": ("delayed", None, [300.0, 3_600.0]),
                "standing": ("standing", None, None)}
    for name, (kind, stand, delay) in expected.items():
        sc = scenario_by_name(name)
        assert sc.material.kind == kind and name in SCENARIOS
        assert (sc.lots, sc.machine, sc.assay_delay_h) == (demo().lots, demo().machine,
                                                           demo().assay_delay_h)
    proc = subprocess.run([STOCKPILE, "sim", "--scenario", "delayed", "--seed", "3",
                           "--duration", "2min", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    material = json.loads((tmp_path / "truth.json").read_text())["material"]
    assert material == {"kind": "delayed", "repose_deg": REPOSE_DEG, "stand_angle_deg": None,
                        "critical_height_m": None, "failure_delay_s": [300.0, 3_600.0],
                        "slides": [], "failures": []}
    assert Material("cohesive").parameters(37.0)["stand_angle_deg"] == 50.0


@pytest.mark.parametrize("kwargs, message", [
    ({"kind": "wet"}, "material kind must be one of"),
    ({"stand_angle_deg": 90.0}, "stand_angle_deg must be in (0, 90)"),
    ({"critical_height_m": -1.0}, "critical_height_m must be > 0 m"),
    ({"failure_delay_s": (10.0, 5.0)}, "failure_delay_s must be (lo, hi)"),
    ({"failure_delay_s": (-1.0, 5.0)}, "failure_delay_s must be (lo, hi)"),
    ({"failure_delay_s": (1.0,)}, "failure_delay_s must be (lo, hi)"),
])
def test_bad_material_is_one_clear_error(kwargs, message):
    with pytest.raises(ValueError) as err:
        Material(**kwargs)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_cohesive_face_must_stand_steeper_than_repose():
    with pytest.raises(ValueError, match="steeper than the angle of repose"):
        replace(demo(), material=Material("cohesive", stand_angle_deg=30.0))

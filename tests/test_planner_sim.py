"""The reclaim planner against the simulator: collisions and predicted cuts, from truth and
from a real ledger.

Ground truth is the simulator's own world model and geometry (:mod:`sim.world`,
:mod:`sim.kinematics`, through :mod:`sim.drive`), never the planner's.

- ``truth_runs``: the simulator stacks a pile (``demo`` twice, ``bench-scale`` once, seeds
  printed); the planner works on the true layers (so projector error stays out); landings
  it calls valid are driven into copies of the world and checked for collisions in the
  simulator's geometry; the chosen landing's bench is then really cut, and the next bench
  planned on what is left (slumps included), twice.
- ``yard``: a small simulated yard with scans, imported into a DuckDB ledger with the real
  ``stockpile ledger`` code; ``stockpile plan reclaim`` plans from the projection and the
  plan is driven into the world.
"""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

import targets
from ledger import EventClock, open_ledger
from ledger.cli import import_lines
from planner.grades import predict_cuts
from projector.kinematics import PlannerMachine
from planner.plan import evaluate_landings, plan_bench_from, plan_reclaim
from sim import kinematics as simk
from sim.drive import drive_bench, lab_assays, stacked_world, truth_stack
from sim.runner import Simulation
from sim.scenario import bench_scale, demo

#: (scenario, seed, valid landings besides the chosen one driven per bench)
CASES = (("demo", 31, (2, 0)), ("demo", 32, (0,)), ("bench-scale", 31, (3, 2)))
CUTS = 3
T0_NS = 1_800_000_000_000_000_000


@pytest.fixture(scope="module")
def truth_runs(tmp_path_factory) -> list[dict]:
    """Per case and bench: the landings checked, what the world said, the chosen bench."""
    records = []
    for name, seed, samples in CASES:
        print(f"case {name} seed {seed}")
        scenario = demo() if name == "demo" else bench_scale()
        sim = stacked_world(scenario, seed, tmp_path_factory.mktemp(f"{name}-{seed}"))
        world, machine = sim.world, sim.machine
        planner_machine = PlannerMachine.from_message(machine)
        lots, assays = lab_assays(sim)
        before = copy.deepcopy(world)
        for bench, sample in enumerate(samples):
            stack = truth_stack(world)
            table = evaluate_landings(stack, planner_machine, n_cuts=CUTS, sample=sample)
            checked = []
            for i in np.flatnonzero(table.valid):
                plan = plan_bench_from(stack, planner_machine, table.landing(i), n_cuts=CUTS)
                driven = drive_bench(copy.deepcopy(world), machine, plan.cuts, T0_NS)
                checked.append((table.landing(i), plan, driven))
            chosen = plan_reclaim(stack, planner_machine, n_cuts=CUTS)
            predicted = predict_cuts(stack.geometry, [c.removal for c in chosen.cuts], lots,
                                     assays, 2 ** 62, scenario.bulk_density_t_m3)
            driven = drive_bench(world, machine, chosen.cuts, T0_NS + bench * 10 ** 13)
            records.append({"case": name, "seed": seed, "bench": bench, "table": table,
                            "checked": checked, "chosen": chosen, "predicted": predicted,
                            "driven": driven, "world": before if bench == 0 else None,
                            "machine": machine})
    return records


def _collisions(driven) -> list[str]:
    return [f"cut {k + 1}: wheel {c.collision.wheel_cells} cells "
            f"({c.collision.wheel_intrusion_m:.3f} m), boom {c.collision.boom_points} points, "
            f"bank {c.collision.bank_m:.3f} / {c.collision.max_bank_m:.3f} m"
            for k, c in enumerate(driven) if c.collision.collided]


def test_valid_landings_never_collide_in_the_simulators_geometry(truth_runs):
    benches = 0
    for r in truth_runs:
        where = f"{r['case']} seed {r['seed']} bench {r['bench'] + 1}"
        assert r["chosen"].landing is not None, f"{where}: no valid landing"
        assert len(r["chosen"].cuts) >= 2, where
        runs = r["checked"] + [(r["chosen"].landing, r["chosen"], r["driven"])]
        for landing, plan, driven in runs:
            assert len(driven) == len(plan.cuts) > 0
            bad = _collisions(driven)
            assert not bad, f"{where}, landing at {landing.point_m}: " + "; ".join(bad)
            benches += 1
        # the simulator cut material in every planned cut
        assert all(c.tonnes > 0 for c in r["driven"]), where
    print(f"{benches} benches of up to {CUTS} cuts driven, no collision")
    # besides each chosen bench, some other valid landings were driven too
    assert benches - len(truth_runs) >= 4


def test_invalid_landings_are_refused_for_a_reason(truth_runs):
    """Stage 1 rejects landings the simulator's geometry also calls colliding."""
    r = truth_runs[0]
    table = r["table"]
    bad = [i for i in range(len(table.candidates))
           if not table.landing_ok[i] and table.first_cuts[i].wheel_cells > 0]
    assert bad, "no candidate bumped the wheel body: the test sees nothing"
    from sim.drive import collisions

    deep = 0
    for i in bad:
        cut = table.first_cuts[i]
        # the planner's body torus is Rk + clearance: where it intrudes by more than the
        # clearance (plus a cell's slope) the simulator's own Rk torus holds material too
        if cut.wheel_intrusion_m > table.params.clearance_m + 0.2:
            report = collisions(r["world"], r["machine"], cut.travel_m, cut.luff_rad,
                                cut.slew_lo_rad, cut.slew_hi_rad)
            assert report.wheel_cells > 0, (i, cut.wheel_intrusion_m)
            deep += 1
    assert deep >= 3


def test_predicted_cuts_match_what_the_simulator_cuts(truth_runs):
    """Planner on the true layers, grades joined from the lab's assays (all known): every
    case (demo and bench-scale), every cut within ``bench/planner_truth.py``'s targets,
    tonnes 5 % and Fe 0.5 pp.

    Measured: tonnes -2.00 .. +2.80 %, Fe -0.20 .. +0.12 pp.  (The Fe tolerance was 1.0 pp
    while an assay was the mean of a whole stacking pass; the lab's windows are now one
    minute in the demo and 30 s in the laboratory pile, docs/planner.md.)
    """
    lines, misses = [], []
    for r in truth_runs:
        p_t = p_fe = d_t = d_fe = 0.0
        for k, (p, d) in enumerate(zip(r["predicted"], r["driven"])):
            err = (p.tonnes / d.tonnes - 1) * 100
            lines.append(f"{r['case']:<11} {r['seed']:>4} B{r['bench'] + 1} C{k + 1} "
                         f"{p.tonnes:>11.5g} {d.tonnes:>11.5g} {err:+6.2f} % "
                         f"Fe {p.grade['Fe']:6.2f} {d.grade['Fe']:6.2f} "
                         f"{p.grade['Fe'] - d.grade['Fe']:+5.2f}")
            if (abs(err) > targets.PLANNED_TONNES_PCT
                    or abs(p.grade["Fe"] - d.grade["Fe"]) > targets.PLANNED_FE_PP):
                misses.append(lines[-1])
            p_t, p_fe = p_t + p.tonnes, p_fe + p.tonnes * p.grade["Fe"]
            d_t, d_fe = d_t + d.tonnes, d_fe + d.tonnes * d.grade["Fe"]
        bench_fe = p_fe / p_t - d_fe / d_t
        lines.append(f"{'':<11} {'':>4} B{r['bench'] + 1} bench Fe {bench_fe:+5.2f} pp")
    print("\n".join(lines))
    assert not misses, "\n".join(misses)


# -- a ledger from the simulator, and the command line ------------------------------------


@pytest.fixture(scope="module")
def yard(tmp_path_factory) -> dict:
    """A two-pass yard with scans (seed 7) in a DuckDB ledger, and its true world."""
    base = demo()
    scenario = replace(base, lots=base.lots[:2], passes_per_lot=1, pass_duration_s=200.0,
                       scan_hz=1.0, encoder_hz=1.0, gnss_hz=0.2, idle_hz=0.01,
                       cuts_per_bench=())
    out = tmp_path_factory.mktemp("yard")
    sim = Simulation(scenario, 7, out / "sim", scan_events="truth")
    # stacking, then 15 min: the assays are not in yet
    sim.run(duration_h=(300 + scenario.stacking_s + 900) / 3600)
    path = out / "ledger.duckdb"
    with open_ledger(path, EventClock()) as store:
        with open(out / "sim" / "events.jsonl", "rb") as lines:
            counts = import_lines(store, lines)
    assert counts["appended"] == counts["lines"] > 0
    end_ns = scenario.start_ns + int((300 + scenario.stacking_s + 900) * 1e9)
    return {"sim": sim, "ledger": str(path), "end_ns": end_ns, "scenario": scenario}


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=300)


def test_plan_reclaim_command_from_a_simulated_ledger(yard):
    sim = yard["sim"]
    proc = _cli("plan", "reclaim", "--ledger", yard["ledger"], "--pile", "P1", "--machine",
                "bwr1", "--cuts", "4", "--bound", "Fe>=99", "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    landing = out["landing"]
    assert landing["candidates_tried"] >= landing["candidates_valid"] >= 1
    j = landing["joints"]
    # the joints put the wheel where the plan says (the simulator's forward kinematics)
    np.testing.assert_allclose(simk.wheel_centre(sim.machine, j["travel_m"], j["slew_rad"],
                                                 j["luff_rad"]), landing["wheel_centre_m"],
                               atol=1e-9)
    # the wheel centre is Rv from the landing point, along the surface normal
    rv = sim.machine.cutting_radius_m
    np.testing.assert_allclose(np.subtract(landing["wheel_centre_m"], landing["point_m"]),
                               rv * np.asarray(landing["normal"]), atol=1e-9)
    cuts = out["cuts"]
    assert len(cuts) == 4
    step = sim.machine.cut_depth_m * landing["direction"]
    np.testing.assert_allclose([c["travel_m"] - j["travel_m"] for c in cuts],
                               [k * step for k in range(4)], atol=1e-9)
    for a, b in zip(cuts, cuts[1:]):   # the boom turns back where the last cut ended
        turn = abs(b["slew_start_rad"] - a["slew_end_rad"])
        assert turn < abs(b["slew_end_rad"] - a["slew_end_rad"])
    for c in cuts:
        assert c["tonnes"] > 0 and set(c["grade"]) >= {"Fe", "SiO2"}
        assert c["assayed_fraction"] == 0.0     # no assay is in the ledger yet: planned grades
    assert out["bench"]["tonnes"] == pytest.approx(sum(c["tonnes"] for c in cuts))
    assert [o["cut"] for o in out["bounds"]["cuts_outside"]] == [1, 2, 3, 4]
    # drive the true pile with the planned joints: no collision in the simulator's geometry
    plan = [SimpleNamespace(**c) for c in cuts]
    driven = drive_bench(copy.deepcopy(sim.world), sim.machine, plan, yard["end_ns"])
    assert not sum((_collisions([d]) for d in driven), [])
    # the plan from the ledger (the projector's error included) against what the simulator
    # cuts: tonnes within the planner's target (measured -2.6 .. -1.0 %).  Its Fe is not
    # judged: no assay is in the ledger yet, so the plan's grades are the lots' planned
    # grades, and the Fe target holds once assays are known (bench/planner_truth.py's
    # ledger section, docs/planner.md: demo seed 1, -0.10 .. +0.28 pp)
    misses = []
    for c, d in zip(cuts, driven):
        err = (c["tonnes"] / d.tonnes - 1) * 100
        print(f"cut {c['cut']}: predicted {c['tonnes']:.1f} t, simulator {d.tonnes:.1f} t "
              f"({err:+.2f} %)")
        assert d.tonnes > 0
        if abs(err) > targets.PLANNED_TONNES_PCT:
            misses.append(f"cut {c['cut']}: {err:+.2f} %")
    assert not misses, misses


def test_plan_reclaim_as_of_a_valid_time(yard, capsys):
    """Before anything was stacked there is no pile to land on: exit 1, one line."""
    from stockpile.cli import main

    start = yard["scenario"].start_ns + 60 * 10 ** 9
    code = main(["plan", "reclaim", "--ledger", yard["ledger"], "--pile", "P1", "--machine",
                 "bwr1", "--valid-time", str(start), "--json"])
    captured = capsys.readouterr()
    assert code == 1, captured.out + captured.err
    assert captured.err.count("\n") == 1 and "no valid landing" in captured.err
    out = json.loads(captured.out)
    assert out["landing"] is None and out["cuts"] == [] and out["search"]["tried"] == 0


@pytest.mark.parametrize("args, message", [
    (["--pile", "P9", "--machine", "bwr1"], "unknown pile 'P9'"),
    (["--pile", "P1", "--machine", "bwr9"], "machine 'bwr9' is unknown"),
    (["--pile", "P1", "--machine", "stk1"], "machine 'stk1' is not a bucket-wheel reclaimer"),
    (["--pile", "P1", "--machine", "bwr1", "--bound", "Fe=60"], "bad --bound 'Fe=60'"),
    (["--pile", "P1", "--machine", "bwr1", "--cuts", "0"], "--cuts must be >= 1"),
    (["--pile", "P1", "--machine", "bwr1", "--spacing", "-1"], "--spacing must be > 0"),
])
def test_bad_input_is_one_line_and_exit_2(yard, capsys, args, message):
    from stockpile.cli import main

    code = main(["plan", "reclaim", "--ledger", yard["ledger"], *args])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("stockpile: error: ") and message in err
    assert err.count("\n") == 1 and "Traceback" not in err


def test_missing_ledger_is_an_error(tmp_path, capsys):
    from stockpile.cli import main

    code = main(["plan", "reclaim", "--ledger", str(tmp_path / "none.duckdb"), "--pile", "P1",
                 "--machine", "bwr1"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith("stockpile: error: ")

"""The projector against the simulator's truth: pile tonnes, and every cut's tonnes and Fe.

    .venv/bin/python bench/projector_truth.py                 # demo and bench-scale, seed 1
    .venv/bin/python bench/projector_truth.py --scenario demo --seed 3 --keep /tmp/pt
    .venv/bin/python bench/projector_truth.py --scenario bench-scale --seed 1 --seed 2 --seed 3
    .venv/bin/python bench/projector_truth.py --scenario bench-scale --explain --keep /tmp/pe
    .venv/bin/python bench/projector_truth.py --scenario demo --poses truth  # true poses
    .venv/bin/python bench/projector_truth.py --matrix --keep /work/ptm  # issue 42's runs

For each scenario: ``stockpile sim --scan-events truth`` (scans and scanner poses as
events, the poses the simulator cast with), ``stockpile ledger import --clock events``
into a DuckDB ledger, then :func:`projector.query.project` with everything known.
``--poses`` chooses which scanner poses place the scans (the scans are the same):
``localizer`` (default, a yard's path) drops the simulator's true poses and imports the
poses the product's localizer estimates from the run's encoders and GNSS (its UKF, as in
the process demo: :func:`services.localizer_offline.write_ledger_input`, the ledger
input ``events-localizer.jsonl`` in the run's folder, the ledger ``<run>-localizer.duckdb``);
``truth`` imports the simulator's true poses, a diagnosis of the projector apart from
the localizer.  ``bench-scale`` takes the true poses unless ``--poses`` says otherwise:
it is a laboratory pile 1.2 m long, placed by its rig, and a yard's GNSS (decimetres)
cannot place it.  Each table's heading names its path.
Truth is the simulator's own world model (its deposition grid and parcels), a different
method from the projector's scans -> height map -> layer stack.

``--explain`` also splits each cut's error: the simulator keeps the true surface at each
cut's start (``--truth-cut-surfaces``), and for every cut the table gives the true
surface above the projector's cutting-envelope floor on the simulator's grid (the
envelope's own error: its difference from the true cut), the same on the projector's
grid (the grid's: the footprint's edge cells differ), and the projector's layer stack
and height map above that floor as of the cut's start (the surface's error, against the
true surface on the projector's grid).  One fold gives the states at every cut's start.
Then each buried deposit top as the first cut finds it, against the simulator's layers
as stacked: as fused and as that cut fits them (``FoldConfig.boundary_fit_cells``).
``seen %`` is the share of those cells the height map measured between the cut before
and this one (the first cut: ever; a measurement held as change evidence counts): where
it is small, the cut's surface is the model's prediction (the slide after the cut
before), not a measurement.  ``slid`` is the volume our model's face slid after the cut
(``CutSummary.slumped_in_m3``), ``sim slid`` the simulator's (its relaxation after the
cut, ``slump_m3`` in truth.json; NaN for a run simulated before it was kept): both the
volume that left the cells it fell from.  A second table gives what slid into each
cut's hole: our slide run on our stack and on the true surface at the cut's start,
beside the simulator's (:func:`_truth_explain.hole_fill`).  The ``--explain`` tables
are in ``bench/_truth_explain.py``, the diagnosis tables below in ``bench/_truth_tables.py``.

The column ``exact lab`` is each cut's Fe error again with every assay's analytes
replaced by the simulator's true grade of its window: the simulator's lab measures with
error (sd 0.15 pp Fe per window), which the ``d pp`` column holds and no projector can
remove; the difference between the two columns is the lab's share.  The column ``lab
floor`` is the Fe error a projector with the true composition and the true deposition
times would still have from the assays: the simulator carries with every piece of belt
flow the lab's final Fe of the window it fell in (one grade per window, as the assays
report it), and a cut's tonnage-weighted mean of that, less its true Fe, is the lab's
error in the windows the cut takes from plus the belt's drift inside them, which one
grade per window cannot follow (NaN for a run simulated before the simulator kept it).
The verdicts judge Fe on the ``exact lab`` column (issue 42's target: the lab's own
error is no projector's); ``lab floor`` is a diagnosis.  Likewise a
cut's tonnes error (``err %``) splits into its volume's (``vol %``, the geometry's) and
its bulk density's (``dens %``): the tonnes-weighted density the assays reported against
the simulator's, whose lab measures density with 1 % error per window (the verdicts use
``err %``).

``--noise-seed N`` (repeatable) measures each seed's world again with the sensors'
noise drawn from N (``stockpile sim --noise-seed``: scanner, encoders and GNSS; the
belt, the stacking, the cuts and the lab follow ``--seed`` alone, so the truth is the
same), and a last table gives each cut's tonnes and Fe error in every draw, the seed's
own first, with their mean and sd and how many draws meet both targets
(:func:`noise_spread`).  A cut some draws miss and others meet is missed by the luck of
the noise; one every draw misses, by the world or the model.

After the cuts, each cut that took more than one lot: each lot's share of its tonnes,
ours against the simulator's, and the Fe those shares alone move (:func:`cut_lots`; a
floor grazing the boundary between two lots takes the lower one in a slice a few mm
thick, and lots differ by points of Fe). Then the tonnes of each lot the pile holds,
ours against the simulator's (material given to the wrong pass makes one lot heavy and
the next light), and each pass's deposition times against the simulator's (mean and rms
error, s; and the mean before the stacker's start, in each fifth of its run and past its
end): the grade of a cut's material is looked up by them. With more than one run
(several ``--seed``, or both scenarios) a last table gives each run's figures side by
side: the seed is the noise and the machine's timing, so a target met on one seed only
is not met.

Targets: pile tonnes within 1 % of truth, its volume within 0.3 %; each cut's tonnes
within 3 % and its Fe within 0.3 percentage points once all assays are known.
``--scenario`` takes ``cohesive``, ``delayed`` and ``standing`` too (the demo's pile with
faces that stand or fail later, :mod:`sim.material`); ``--duration`` (site hours) cuts a
run short while developing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _coverage_tables import print_table, z_rows  # noqa: E402
from _truth_explain import explain  # noqa: E402
from _truth_tables import (cut_lots, deposition_times, fmt_tonnes, lot_tonnes,  # noqa: E402
                           mean_over_draws, noise_spread, pct)
from ledger import open_ledger  # noqa: E402
from projector.query import grade_inputs, project, summarise  # noqa: E402
from services.localizer_offline import write_ledger_input  # noqa: E402

TARGET_PILE_PCT = 1.0
TARGET_CUT_PCT = 3.0
TARGET_FE_PP = 0.3
TARGET_VOLUME_PCT = 0.3
#: the scenarios it runs: the demo, the laboratory pile, and the demo's other materials
SCENARIOS = ("demo", "bench-scale", "cohesive", "delayed", "standing")
#: the seed run when none is given (tests/test_accuracy_targets.py checks it in CI)
DEFAULT_SEED = 1
#: the scenarios with a material of their own, and the demo's (``--matrix``)
MATERIAL_SCENARIOS = ("demo", "cohesive", "delayed", "standing")
#: ``--matrix``'s draws of the sensors' noise besides each seed's own: noise seeds
#: ``1000 d + seed`` (``bench/coverage.py --noise-draws``'s, so the two share kept runs)
MATRIX_DRAWS = 3
#: where the scans' poses come from (``--poses``): the localizer's estimate, or the truth
POSES = {"localizer": "localizer poses (encoders + GNSS through the UKF)",
         "truth": "true poses (the simulator's, a diagnosis)"}
#: the scenarios whose runs take another path than the localizer's unless ``--poses`` says
DEFAULT_POSES = {"bench-scale": "truth"}


def run_stockpile(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "stockpile.cli", *args], check=True,
                   stdout=subprocess.DEVNULL)


def run_name(scenario: str, seed: int, noise_seed: int | None = None) -> str:
    """The name of a run's simulation directory (and of what is kept beside it)."""
    return f"{scenario}-seed{seed}" + ("" if noise_seed is None else f"-noise{noise_seed}")


def simulate(scenario: str, seed: int, out: Path, duration_h: float | None = None,
             cut_surfaces: bool = False, noise_seed: int | None = None) -> tuple[Path, dict]:
    """The run's simulation directory under ``out`` (simulated unless it holds the run's
    ``truth.json``) and its truth; ``noise_seed`` None: the simulator's default."""
    sim_dir = out / run_name(scenario, seed, noise_seed)
    if not (sim_dir / "truth.json").exists():
        extra = ["--duration", f"{duration_h}h"] if duration_h else []
        if cut_surfaces:
            extra.append("--truth-cut-surfaces")
        if noise_seed is not None:
            extra += ["--noise-seed", str(noise_seed)]
        run_stockpile("sim", "--scenario", scenario, "--seed", str(seed), "--speed", "0",
                      "--scan-events", "truth", "--out", str(sim_dir), *extra)
    return sim_dir, json.loads((sim_dir / "truth.json").read_text())


def run(scenario: str, seed: int, out: Path, duration_h: float | None = None,
        cut_surfaces: bool = False, noise_seed: int | None = None,
        poses: str = "localizer") -> dict:
    """Simulate (unless ``out`` holds the run), import and project one run.

    ``noise_seed``: the seed of the sensors' noise (``stockpile sim --noise-seed``), None
    or ``seed``: the simulator's default (the same run as without it).  ``poses``: a key
    of :data:`POSES`; both paths share the run's simulation, each has its own ledger
    (``<run>-localizer.duckdb`` for the localizer's).
    """
    if poses not in POSES:
        raise ValueError(f"poses must be one of {', '.join(POSES)}, got {poses!r}")
    noise_seed = None if noise_seed == seed else noise_seed
    started = time.perf_counter()
    sim_dir, truth = simulate(scenario, seed, out, duration_h, cut_surfaces, noise_seed)
    ledger = out / (sim_dir.name + ("-localizer" if poses == "localizer" else "") + ".duckdb")
    if not ledger.exists():
        run_stockpile("ledger", "import", str(ledger_input(sim_dir, truth, poses)), "--ledger",
                      str(ledger), "--clock", "events")
    prepared = time.perf_counter() - started
    pile_id = truth["scenario"].get("pile_id", "P1")
    with open_ledger(ledger, read_only=True) as store:
        t0 = time.perf_counter()
        state = project(store, pile_id)
        project_s = time.perf_counter() - t0
        lots, assays = grade_inputs(store, state.valid_time_ns, state.known_time_ns)
    return {"scenario": scenario, "seed": seed, "poses": poses,
            "noise_seed": seed if noise_seed is None else noise_seed,
            "state": state, "truth": truth,
            "prepare_s": prepared, "project_s": project_s, "sim_dir": sim_dir,
            "ledger": ledger, "exact_lab": _exact_lab(state, lots, assays, truth)}


def ledger_input(sim_dir: Path, truth: dict, poses: str) -> Path:
    """The JSON lines a run's ledger is imported from: the simulator's ``events.jsonl``
    (true poses), or ``events-localizer.jsonl`` (written unless kept: the localizer's
    poses in place of the true ones)."""
    if poses == "truth":
        return sim_dir / "events.jsonl"
    path = sim_dir / "events-localizer.jsonl"
    if not path.exists():
        write_ledger_input(sim_dir / "events.jsonl", sim_dir / "gnss.nmea", path,
                           machine_id=truth["scenario"]["machine_id"])
    return path


def _exact_lab(state, lots, assays, truth: dict):
    """The same fold's cuts graded by an exact laboratory: each assay's analytes replaced by
    the simulator's true grade of its window (``true_grade_pct``), densities kept.

    The simulator's lab measures with error (sd 0.15 pp Fe per window), and the targets
    compare our grades with the true grade of the material, so a cut's Fe error holds the
    lab's error of the windows it takes from; this separates the projector's own error
    (geometry, layers, deposition times) from it.  A diagnosis, not a target.
    """
    true = {a["assay_id"]: a["true_grade_pct"] for a in truth["assays"]}
    exact = [dataclasses.replace(a, analytes={**a.analytes, **true.get(a.assay_id, {})})
             for a in assays]
    return summarise(state.state, lots, exact, valid_time_ns=state.valid_time_ns,
                     known_time_ns=state.known_time_ns)


def report(result: dict) -> dict:
    """Print a run's pile and cuts against truth; returns its figures for :func:`summary`
    (``ok``: every target met)."""
    state, truth = result["state"], result["truth"]
    world = truth["world"]
    ok = True
    worst_pct, worst_pp, within = 0.0, 0.0, 0
    vol_errs = []
    err = (state.tonnes / world["tonnes"] - 1) * 100
    vol_err = (state.volume_m3 / world["volume_m3"] - 1) * 100
    verdict = "PASS" if abs(err) <= TARGET_PILE_PCT else "MISS"
    vol_verdict = "PASS" if abs(vol_err) <= TARGET_VOLUME_PCT else "MISS"
    ok &= verdict == "PASS"   # the volume's verdict is printed beside it, a diagnosis
    print(f"\n== {_label(result)}: projected in "
          f"{result['project_s']:.1f} s ({result['prepare_s']:.0f} s to simulate and import)")
    print(f"pile: ours {state.tonnes:,.3f} t, {state.volume_m3:,.3f} m3; truth "
          f"{world['tonnes']:,.3f} t, {world['volume_m3']:,.3f} m3; error {err:+.2f} % "
          f"(target <= {TARGET_PILE_PCT:g} %) {verdict}; volume {vol_err:+.2f} % "
          f"(target <= {TARGET_VOLUME_PCT:g} %) {vol_verdict}")
    print(f"      grade Fe ours {state.grade.get('Fe', float('nan')):.2f} % vs truth "
          f"{world['grade']['Fe']:.2f} %, assayed fraction {state.assayed_fraction:.2f}")
    ours = {c.cut_id: c for c in state.cuts}
    exact = {c.cut_id: c for c in result["exact_lab"].cuts}
    worst_exact_pp, floor_pps = 0.0, []
    cut_errors: dict[str, tuple[float, float, bool]] = {}   # tonnes %, Fe pp, both met
    cut_exact_fe: dict[str, float] = {}                     # Fe pp with an exact lab
    print(f"{'cut':<8} {'ours t':>10} {'truth t':>10} {'err %':>7} {'vol %':>6} {'dens %':>6} "
          f"{'belt t':>10} {'Fe ours':>8} {'Fe truth':>8} {'d pp':>6} {'exact lab':>9} "
          f"{'lab floor':>9} {'assayed':>7} {'resid m3':>9}  verdict")
    for c in truth["cuts"]:
        mine = ours.get(c["cut_id"])
        if mine is None:
            print(f"{c['cut_id']:<8} missing")
            ok = False
            continue
        t_err = pct(mine.tonnes, c["true_tonnes"])
        # (a folder kept from a simulator that did not report a cut's volume: NaN)
        true_m3 = c.get("true_volume_m3", float("nan"))
        v_err = pct(mine.volume_m3, true_m3)
        # the lab's share: the bulk density the assays gave against the simulator's
        d_err = pct(mine.tonnes / mine.volume_m3, c["true_tonnes"] / true_m3) \
            if mine.volume_m3 > 0 and true_m3 > 0 else float("nan")
        fe = mine.grade.get("Fe", float("nan"))
        d_fe = fe - c["grade"]["Fe"]
        d_exact = exact[c["cut_id"]].grade.get("Fe", float("nan")) - c["grade"]["Fe"]
        good = abs(t_err) <= TARGET_CUT_PCT and abs(d_exact) <= TARGET_FE_PP
        ok &= good
        within += good
        cut_errors[c["cut_id"]] = (t_err, d_fe, good)
        worst_pct, worst_pp = max(worst_pct, abs(t_err)), max(worst_pp, abs(d_fe))
        vol_errs.append(abs(v_err))
        worst_exact_pp = max(worst_exact_pp, abs(d_exact))
        cut_exact_fe[c["cut_id"]] = d_exact
        # NaN for a run simulated before the simulator kept it
        floor_pp = c.get("lab_window_fe_pct", math.nan) - c["grade"]["Fe"]
        floor_pps.append(abs(floor_pp))
        print(f"{c['cut_id']:<8} {fmt_tonnes(mine.tonnes):>10} "
              f"{fmt_tonnes(c['true_tonnes']):>10} {t_err:>+7.2f} "
              f"{v_err:>+6.2f} {d_err:>+6.2f} {fmt_tonnes(mine.tonnes_scale):>10} {fe:>8.2f} "
              f"{c['grade']['Fe']:>8.2f} {d_fe:>+6.2f} "
              f"{d_exact:>+9.2f} {floor_pp:>+9.2f} {mine.assayed_fraction:>7.2f} {mine.residual_m3:>+9.3f}  "
              f"{'PASS' if good else 'MISS'}")
    print("counters: " + ", ".join(f"{k} {v:,}" for k, v in sorted(state.counters.items())))
    cut_lots(result)
    worst_lot_pct = lot_tonnes(result)
    deposition_times(result)
    return {"scenario": result["scenario"], "seed": result["seed"],
            "poses": result.get("poses", "truth"),
            "noise_seed": result.get("noise_seed", result["seed"]),
            "cut_errors": cut_errors, "cut_exact_fe": cut_exact_fe, "pile_pct": err,
            "z": z_rows(state, truth), "volume_pct": vol_err,
            "cuts": len(truth["cuts"]), "within": within, "worst_pct": worst_pct,
            "worst_pp": worst_pp, "worst_exact_pp": worst_exact_pp,
            "worst_floor_pp": max((e for e in floor_pps if not math.isnan(e)), default=math.nan),
            "worst_lot_pct": worst_lot_pct,
            # NaN when no cut's volume is known
            "worst_vol_pct": max((e for e in vol_errs if not math.isnan(e)), default=math.nan),
            "ok": ok}


def summary(figures: list[dict]) -> None:
    """One line per run: pile error, cuts meeting both targets, worst tonnes, volume and Fe,
    and the worst lot's tonnes in the pile (a diagnosis, :func:`lot_tonnes`)."""
    width = max(22, *(len(_run_name(f)) for f in figures))
    print(f"\n{'run':<{width}} {'pile %':>7} {'vol %':>6} {'cuts met':>9} {'worst t %':>9} {'worst vol %':>11} "
          f"{'worst Fe pp':>11} {'exact lab':>9} {'lab floor':>9} {'worst lot %':>11}  verdict")
    for f in figures:
        print(f"{_run_name(f):<{width}} {f['pile_pct']:>+7.2f} {f['volume_pct']:>+6.2f} "
              f"{str(f['within']) + '/' + str(f['cuts']):>9} {f['worst_pct']:>9.2f} "
              f"{f['worst_vol_pct']:>11.2f} "
              f"{f['worst_pp']:>11.2f} {f['worst_exact_pp']:>9.2f} {f['worst_floor_pp']:>9.2f} "
              f"{f['worst_lot_pct']:>11.2f}  {'PASS' if f['ok'] else 'MISS'}")


def _draw(run: dict) -> str:
    """``seed 5``, or with another draw of the sensors' noise ``seed 5, noise 1005``
    (``run``: a :func:`run` result or :func:`report` figures)."""
    noise = run.get("noise_seed", run["seed"])
    return f"seed {run['seed']}" + ("" if noise == run["seed"] else f", noise {noise}")


def _run_name(figures: dict) -> str:
    """``bench-scale seed 5`` or ``bench-scale seed 5, noise 1005``."""
    return f"{figures['scenario']} {_draw(figures)}"


def _label(result: dict) -> str:
    """``bench-scale (seed 5), localizer poses (...)`` or ``bench-scale (seed 5, noise
    1005), true poses (...)``."""
    return f"{result['scenario']} ({_draw(result)}), {POSES[result.get('poses', 'truth')]}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", action="append", choices=SCENARIOS,
                    help="repeat for several (default: demo and bench-scale); cohesive, "
                    "delayed and standing are the demo with another material (sim.material)")
    ap.add_argument("--seed", type=int, action="append",
                    help=f"simulator seed; repeat for several (default: {DEFAULT_SEED})")
    ap.add_argument("--duration", type=float, default=None, help="site hours (default: all)")
    ap.add_argument("--noise-seed", type=int, action="append", metavar="N",
                    help="also measure each seed's world with the sensors' noise from seed N "
                    "(stockpile sim --noise-seed); repeatable; a table then gives each cut's "
                    "error over the draws, the seed's own first")
    ap.add_argument("--keep", metavar="DIR", help="keep (and reuse) the runs in DIR")
    ap.add_argument("--poses", choices=tuple(POSES),
                    help="the scanner poses that place the scans: the localizer's estimate "
                    "from encoders and GNSS (a yard's path, the default) or the simulator's "
                    "true poses (a diagnosis; bench-scale's default, a laboratory pile)")
    ap.add_argument("--matrix", action="store_true",
                    help="issue 42's runs: every material scenario (demo, cohesive, delayed, "
                    f"standing), seeds 1-5, {MATRIX_DRAWS} draws of the sensors' noise "
                    "besides each seed's own (noise seeds 1000 d + seed), judged on the mean "
                    "over the draws, and the standard deviations' coverage per scenario "
                    "(hours; --scenario and --seed narrow it)")
    ap.add_argument("--explain", action="store_true",
                    help="split each cut's error into the envelope's and the surface's "
                    "(simulates with --truth-cut-surfaces)")
    args = ap.parse_args(argv)
    if args.matrix:
        args.scenario = args.scenario or list(MATERIAL_SCENARIOS)
        args.seed = args.seed or list(range(1, 6))
    scenarios = args.scenario or ["demo", "bench-scale"]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.keep or tmp)
        out.mkdir(parents=True, exist_ok=True)
        figures = []
        for seed in args.seed or [DEFAULT_SEED]:
            for scenario in scenarios:
                noise_seeds = [1000 * d + seed for d in range(1, MATRIX_DRAWS + 1)] \
                    if args.matrix else [n for n in args.noise_seed or [] if n != seed]
                for noise_seed in [None, *noise_seeds]:
                    poses = args.poses or DEFAULT_POSES.get(scenario, "localizer")
                    result = run(scenario, seed, out, args.duration, cut_surfaces=args.explain,
                                 noise_seed=noise_seed, poses=poses)
                    figures.append(report(result))
                    if args.explain:
                        explain(result)
        ok = all(f["ok"] for f in figures)
        if len(figures) > 1:
            if args.poses:
                print(f"\n(all runs: {POSES[args.poses]})")
            summary(figures)
        if args.noise_seed or args.matrix:
            always = noise_spread(figures)
            print(f"\ncuts every draw misses: {', '.join(always) or 'none'}")
            ok = mean_over_draws(figures, {"pile_pct": TARGET_PILE_PCT,
                                           "volume_pct": TARGET_VOLUME_PCT,
                                           "cut_pct": TARGET_CUT_PCT, "fe_pp": TARGET_FE_PP})
        if args.matrix:
            for scenario in scenarios:
                mine = [f for f in figures if f["scenario"] == scenario]
                print_table(scenario, {k: [(_run_name(f), *r) for f in mine for r in f["z"][k]]
                                       for k in mine[0]["z"]}, len(mine))
    print(f"\n{'all targets met' if ok else 'some targets missed'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())

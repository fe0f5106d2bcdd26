"""The projector against the simulator's truth: pile tonnes, and every cut's tonnes and Fe.

    .venv/bin/python bench/projector_truth.py                 # demo and bench-scale, seed 1
    .venv/bin/python bench/projector_truth.py --scenario demo --seed 3 --keep /tmp/pt
    .venv/bin/python bench/projector_truth.py --scenario bench-scale --seed 1 --seed 2 --seed 3
    .venv/bin/python bench/projector_truth.py --scenario bench-scale --explain --keep /tmp/pe

For each scenario: ``stockpile sim --scan-events truth`` (scans and scanner poses as
events, the poses the simulator cast with), ``stockpile ledger import --clock events``
into a DuckDB ledger, then :func:`projector.query.project` with everything known.
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
volume that left the cells it fell from.  Bench-scale, every seed: bench 2's slides
match the simulator's within 4 %, the later cuts of bench 1 slide 1.1-2 times as much,
and the first cut's slide moves 12-24 times as much (215-254 cm3 against 9-21): the
first relaxation of the noisy stacked surface levels its bumps, a cell's noise being a
few times the repose drop across a cell.  A second table gives what slid into each
cut's hole: our slide run on our stack and on the true surface at the cut's start,
beside the simulator's (:func:`_hole_fill`).

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
Seeds 1-5: its rms over bench-scale's 75 cuts is 0.15 pp, and three cuts of seed 5 have
one beyond 0.3 pp (demo: 0.06 pp over 50 cuts, at most 0.14).  Both are diagnoses: the verdicts use ``d pp``.  Likewise a
cut's tonnes error (``err %``) splits into its volume's (``vol %``, the geometry's) and
its bulk density's (``dens %``): the tonnes-weighted density the assays reported against
the simulator's, whose lab measures density with 1 % error per window; a cut a few
windows wide can carry 2 % of it (the verdicts use ``err %``).

``--noise-seed N`` (repeatable) measures each seed's world again with the sensors'
noise drawn from N (``stockpile sim --noise-seed``: scanner, encoders and GNSS; the
belt, the stacking, the cuts and the lab follow ``--seed`` alone, so the truth is the
same), and a last table gives each cut's tonnes and Fe error in every draw, the seed's
own first, with their mean and sd and how many draws meet both targets
(:func:`noise_spread`).  A cut some draws miss and others meet is missed by the luck of
the noise; one every draw misses, by the world or the model.  Bench-scale seeds 1-5,
four draws each: a first cut's tonnes move by an sd of 0.6-3.6 % between draws (a slice
a few mm thick under 15 mm of point noise), around a mean of -0.5 to +0.7 % per seed
(+1.4 to +2.8 % before the fold measured a first cut on a fitted top,
``FoldConfig.cut_fit_cells``), and the only cuts every draw misses are the three of seed 5
at the lab floor.

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

Targets (issue 5): pile tonnes within 1 % of truth; each cut's tonnes within 3 % and
its Fe within 0.3 percentage points once all assays are known.
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

from ledger import open_ledger  # noqa: E402
from projector.query import grade_inputs, project, summarise  # noqa: E402

TARGET_PILE_PCT = 1.0
TARGET_CUT_PCT = 3.0
TARGET_FE_PP = 0.3


def _stockpile(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "stockpile.cli", *args], check=True,
                   stdout=subprocess.DEVNULL)


def run(scenario: str, seed: int, out: Path, duration_h: float | None = None,
        cut_surfaces: bool = False, noise_seed: int | None = None) -> dict:
    """Simulate (unless ``out`` holds the run), import and project one run.

    ``noise_seed``: the seed of the sensors' noise (``stockpile sim --noise-seed``), None
    or ``seed``: the simulator's default (the same run as without it).
    """
    noise_seed = None if noise_seed == seed else noise_seed
    name = f"{scenario}-seed{seed}" + ("" if noise_seed is None else f"-noise{noise_seed}")
    sim_dir = out / name
    ledger = out / f"{name}.duckdb"
    started = time.perf_counter()
    if not (sim_dir / "truth.json").exists():
        extra = ["--duration", str(duration_h)] if duration_h else []
        if cut_surfaces:
            extra.append("--truth-cut-surfaces")
        if noise_seed is not None:
            extra += ["--noise-seed", str(noise_seed)]
        _stockpile("sim", "--scenario", scenario, "--seed", str(seed), "--speed", "0",
                   "--scan-events", "truth", "--out", str(sim_dir), *extra)
    if not ledger.exists():
        _stockpile("ledger", "import", str(sim_dir / "events.jsonl"), "--ledger", str(ledger),
                   "--clock", "events")
    prepared = time.perf_counter() - started
    truth = json.loads((sim_dir / "truth.json").read_text())
    pile_id = truth["scenario"].get("pile_id", "P1")
    with open_ledger(ledger, read_only=True) as store:
        t0 = time.perf_counter()
        state = project(store, pile_id)
        project_s = time.perf_counter() - t0
        lots, assays = grade_inputs(store, state.valid_time_ns, state.known_time_ns)
    return {"scenario": scenario, "seed": seed,
            "noise_seed": seed if noise_seed is None else noise_seed,
            "state": state, "truth": truth,
            "prepare_s": prepared, "project_s": project_s, "sim_dir": sim_dir,
            "ledger": ledger, "exact_lab": _exact_lab(state, lots, assays, truth)}


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


def explain(result: dict) -> None:
    """Per cut: the envelope's error and the surface's error (see the module docstring)."""
    import numpy as np

    from projector.envelope import cut_floor
    from projector.grid import GridGeometry

    arrays = np.load(result["sim_dir"] / "truth.npz")
    if "cut_surface_z" not in arrays:
        raise SystemExit(f"{result['sim_dir']} was simulated without --truth-cut-surfaces: "
                         "give --explain a new --keep folder")
    truth, pile_id = result["truth"], result["truth"]["scenario"].get("pile_id", "P1")
    ground_m = float(truth["scenario"].get("ground_z_m", 0.0))
    # bench-scale cuts hold tens of cm3
    unit, scale = (("cm3", 1e6) if max((c["true_volume_m3"] for c in truth["cuts"]), default=1.0)
                   < 0.01 else ("m3", 1.0))
    print(f"\n-- {result['scenario']} (seed {result['seed']}): each cut's error, split "
          f"({unit} above our envelope floor at the cut's start)")
    print(f"{'cut':<8} {'true cut':>10} {'sim grid':>10} {'envelope %':>10} {'our grid':>10} "
          f"{'grid %':>7} {'our stack':>10} {'stack %':>8} {'our map':>10} {'map %':>7} "
          f"{'stack-true mm':>13} {'seen %':>6} {'slid':>8} {'sim slid':>8}")
    xc, yc = arrays["x_centres"], arrays["y_centres"]
    sim_grid = GridGeometry(origin_x_m=float(xc[0] - (xc[1] - xc[0]) / 2),
                            origin_y_m=float(yc[0] - (yc[1] - yc[0]) / 2),
                            cell_m=float(xc[1] - xc[0]), nx=len(xc), ny=len(yc), frame="site")
    with open_ledger(result["ledger"], read_only=True) as store:
        befores = _states_before(store, pile_id, [c["t0_ns"] for c in truth["cuts"]])
    previous_end_ns = None
    slid_m3 = {c.cut_id: c.slumped_in_m3 for c in result["state"].cuts}
    # the true surface at each cut's start and, last, after the last cut, on our grid
    true_surfaces = [] if not befores else [
        _on_our_grid(arrays, befores[0].pile.geometry, z)
        for z in (*arrays["cut_surface_z"][:len(befores)], arrays["surface_z"])]
    fills = []
    for i, (c, true_z, before) in enumerate(zip(truth["cuts"], arrays["cut_surface_z"], befores)):
        g, surface = before.pile.geometry, true_surfaces[i]
        machine = before.machines[truth["scenario"]["machine_id"]]
        joints = (c["travel_m"], c["luff_rad"], c["slew_start_rad"], c["slew_end_rad"])
        # material is above the floor and the ground: a floor below the ground takes
        # nothing there
        base = np.fmax(cut_floor(g, machine, *joints), ground_m)
        # the envelope on the simulator's own grid (its arrays are (ny, nx)), then on ours
        sim_m3 = _above_m3(true_z.T.astype(np.float64),
                           np.fmax(cut_floor(sim_grid, machine, *joints), ground_m),
                           sim_grid.cell_area_m2)
        top = before.stack.surface()
        true_m3, ours_m3 = _above_m3(surface, base, g.cell_area_m2), _above_m3(top, base, g.cell_area_m2)
        map_m3 = _above_m3(before.height.elevation, base, g.cell_area_m2)
        cells = np.isfinite(base) & ((surface > base) | (top > base))
        bias_mm = float(np.nanmean((top - surface)[cells])) * 1e3 if cells.any() else 0.0
        # how much of that the height map saw since the cut before ended (the rest of the
        # map is that cut's predicted slide, or older looks)
        looked_ns = np.fmax(before.height.grid["last_update_ns"],
                            before.height.grid["pending_since_ns"])
        seen = looked_ns[cells] >= (previous_end_ns or 0)
        seen_pct = 100.0 * float(seen.mean()) if cells.any() else float("nan")
        previous_end_ns = c["t1_ns"]
        cut_m3 = c["true_volume_m3"]
        print(f"{c['cut_id']:<8} {cut_m3 * scale:>10.4g} {sim_m3 * scale:>10.4g} "
              f"{_pct(sim_m3, cut_m3):>+10.2f} {true_m3 * scale:>10.4g} "
              f"{_pct(true_m3, sim_m3):>+7.2f} {ours_m3 * scale:>10.4g} "
              f"{_pct(ours_m3, true_m3):>+8.2f} {map_m3 * scale:>10.4g} "
              f"{_pct(map_m3, true_m3):>+7.2f} {bias_mm:>+13.2f} {seen_pct:>6.0f} "
              f"{slid_m3.get(c['cut_id'], math.nan) * scale:>8.4g} "
              f"{c.get('slump_m3', math.nan) * scale:>8.4g}", flush=True)
        if i + 1 < len(true_surfaces):
            fills.append((c["cut_id"], _hole_fill(before, base, surface, true_surfaces[i + 1],
                                                  c["t0_ns"], ground_m)))
    print(f"\nwhat slid into each cut's hole ({unit}): our slide on our stack and on the true "
          "surface at the cut's start, and the simulator's")
    print(f"{'cut':<8} {'on ours':>9} {'on true':>9} {'sim':>9}")
    for cut_id, row in fills:
        print(f"{cut_id:<8} " + " ".join(f"{m3 * scale:>9.4g}" for m3 in row))
    if "first_cut_thickness" in arrays and befores:
        _buried_tops(befores[0], arrays, truth, ground_m)


def _hole_fill(before, floor_m, true_before_m, true_after_m, t0_ns: int,
               ground_m: float) -> tuple[float, float, float]:
    """What slid into one cut's hole (m3): our slide (``cuts.slump_face`` after clamping to
    the envelope floor ``floor_m``, +inf outside the footprint) run on our stack at the
    cut's start (``before``) and on the simulator's true surface then, and the simulator's
    own slide (its surface at the next cut's start less what the cut left).  The hole's
    fill is the volume above what the cut left in its footprint; the true surfaces are on
    our grid (NaN off the simulator's: its ground).

    Where our slide on the true surface matches the simulator's, the slide model is right
    and a difference in the first figure is our surface's: the relaxation is nonlinear,
    and noise in the surface shortens the slide.  Bench-scale, seeds 1-5, the first cut:
    on the true surface our slide fills 2-4 % more than the simulator's (our repose
    estimate, 36.7 deg, is shallower than its 37; at 37 deg seed 3 gives its 7.37 cm3
    exactly), on our stack 9-33 % less (seed 3: 4.93 cm3; the true surface with 2.5 mm of
    white noise added gives 4.59).  The later cuts' faces, slid before, come within a few
    % on our stack.
    """
    import numpy as np

    from projector import cuts

    footprint = np.isfinite(floor_m)
    true_before = np.nan_to_num(true_before_m, nan=ground_m)
    true_after = np.nan_to_num(true_after_m, nan=ground_m)
    area_m2 = before.pile.geometry.cell_area_m2
    fills = []
    for surface in (None, true_before):
        state = before.copy()
        if surface is not None:
            state.stack, _ = state.stack.clamp(surface)
            state.stack, _ = state.stack.raise_to(surface, int(t0_ns))
        start = state.stack.surface()
        state.stack, _ = state.stack.clamp(floor_m)
        cuts.slump_face(state, floor_m)
        fills.append(float(np.sum((state.stack.surface() - np.minimum(start, floor_m))[footprint]))
                     * area_m2)
    sim = float(np.sum((true_after - np.minimum(true_before, floor_m))[footprint])) * area_m2
    return fills[0], fills[1], sim


def _buried_tops(before, arrays, truth: dict, ground_m: float) -> None:
    """Each deposit's top under the top one as the first cut finds it, ours against the
    simulator's layers as stacked (``first_cut_thickness``): mean and rms (mm) over the
    cells where the simulator has both that deposit and one above it, as fused and as
    that cut fits them (``FoldConfig.boundary_fit_cells``)."""
    import numpy as np

    from projector import cuts

    thickness = arrays["first_cut_thickness"].astype(np.float64)
    tops = ground_m + np.cumsum(thickness, axis=0)
    slot_lots = [s["lot"] for s in sorted(truth["world"]["slots"], key=lambda s: s["slot"])]
    stack = before.stack
    ours = [k for k in range(1, stack.n_deposits + 1) if not stack.info(k).flagged]
    if len(ours) != len(tops) or [stack.info(k).lot_id for k in ours] != slot_lots[:len(tops)]:
        print("\n(buried tops: our deposits and the simulator's layers do not pair one to one)")
        return
    fitted = before.copy()
    cuts.fit_buried_boundaries(fitted)

    def on_ours(z_m):
        return _on_our_grid(arrays, stack.geometry, z_m)

    print("\nburied tops at the first cut, ours - the simulator's (mm): as fused / as fitted")
    print(f"{'deposit':<16} {'cells':>7} {'mean':>7} {'rms':>7} {'mean':>7} {'rms':>7}")
    top = on_ours(tops[-1])
    below = np.full(top.shape, ground_m)
    for slot, k in enumerate(ours[:-1]):
        level = on_ours(tops[slot])
        cells = (level - below > 1e-9) & (top - level > 1e-9)
        below = level
        if not cells.any():
            continue
        fused = (stack.surface_k(k) - level)[cells] * 1e3
        fit = (fitted.stack.surface_k(k) - level)[cells] * 1e3
        print(f"{stack.info(k).pass_id:<16} {int(cells.sum()):>7} {np.mean(fused):>+7.2f} "
              f"{np.sqrt(np.mean(fused ** 2)):>7.2f} {np.mean(fit):>+7.2f} "
              f"{np.sqrt(np.mean(fit ** 2)):>7.2f}")


def _on_our_grid(arrays, geometry, z_m):
    """A simulator array (``(ny, nx)`` on its cell centres ``arrays["x_centres"]``,
    ``["y_centres"]``) interpolated to our cell centres: ``(nx, ny)``, NaN off its grid."""
    import numpy as np
    from scipy.interpolate import RegularGridInterpolator

    from projector.grid import cell_centres

    x, y = cell_centres(geometry)
    return RegularGridInterpolator((arrays["y_centres"], arrays["x_centres"]),
                                   np.asarray(z_m, np.float64), bounds_error=False)(
        np.column_stack([y.ravel(), x.ravel()])).reshape(x.shape)


def _states_before(store, pile_id: str, times_ns: list[int]) -> list:
    """The fold state (flushed, as :func:`project` leaves it) just before each time, with
    everything known: what ``project(store, pile_id, t - 1).state`` gives, from one fold."""
    from projector import fold as F
    from projector.query import FAR_FUTURE_NS

    if times_ns != sorted(times_ns):
        raise ValueError("the times must be in order")
    state, states = F.initial_state(F.FoldConfig(pile_id=pile_id)), []
    for event in store.as_of(FAR_FUTURE_NS, FAR_FUTURE_NS, types=list(F.GEOMETRY_TYPES)):
        while len(states) < len(times_ns) and event.valid_time_ns >= times_ns[len(states)]:
            states.append(F.flush(state.copy()))
        F.apply(state, event)
    return states + [F.flush(state.copy()) for _ in times_ns[len(states):]]


def _above_m3(z_m, base_m, cell_area_m2: float) -> float:
    """Volume (m3) of a surface above a base (NaN surface: unseen; inf base: outside)."""
    import numpy as np

    return float(np.nansum(np.clip(z_m - base_m, 0.0, None))) * cell_area_m2


def _pct(value: float, reference: float) -> float:
    """``value`` against ``reference`` in % (NaN for a cut that took nothing)."""
    return (value / reference - 1) * 100 if reference > 0 else float("nan")


def _t(tonnes: float) -> str:
    """Tonnes with four significant digits (bench-scale cuts weigh grams)."""
    return f"{tonnes:,.1f}" if abs(tonnes) >= 100 else f"{tonnes:.4g}"


def report(result: dict) -> dict:
    """Print a run's pile and cuts against truth; returns its figures for :func:`summary`
    (``ok``: every target met)."""
    state, truth = result["state"], result["truth"]
    world = truth["world"]
    ok = True
    worst_pct, worst_pp, within = 0.0, 0.0, 0
    vol_errs = []
    err = (state.tonnes / world["tonnes"] - 1) * 100
    verdict = "PASS" if abs(err) <= TARGET_PILE_PCT else "MISS"
    ok &= verdict == "PASS"
    print(f"\n== {_label(result)}: projected in "
          f"{result['project_s']:.1f} s ({result['prepare_s']:.0f} s to simulate and import)")
    print(f"pile: ours {state.tonnes:,.3f} t, {state.volume_m3:,.3f} m3; truth "
          f"{world['tonnes']:,.3f} t, {world['volume_m3']:,.3f} m3; error {err:+.2f} % "
          f"(target <= {TARGET_PILE_PCT:g} %) {verdict}")
    print(f"      grade Fe ours {state.grade.get('Fe', float('nan')):.2f} % vs truth "
          f"{world['grade']['Fe']:.2f} %, assayed fraction {state.assayed_fraction:.2f}")
    ours = {c.cut_id: c for c in state.cuts}
    exact = {c.cut_id: c for c in result["exact_lab"].cuts}
    worst_exact_pp, floor_pps = 0.0, []
    cut_errors: dict[str, tuple[float, float, bool]] = {}   # tonnes %, Fe pp, both met
    print(f"{'cut':<8} {'ours t':>10} {'truth t':>10} {'err %':>7} {'vol %':>6} {'dens %':>6} "
          f"{'belt t':>10} {'Fe ours':>8} {'Fe truth':>8} {'d pp':>6} {'exact lab':>9} "
          f"{'lab floor':>9} {'assayed':>7} {'resid m3':>9}  verdict")
    for c in truth["cuts"]:
        mine = ours.get(c["cut_id"])
        if mine is None:
            print(f"{c['cut_id']:<8} missing")
            ok = False
            continue
        t_err = _pct(mine.tonnes, c["true_tonnes"])
        # (a folder kept from a simulator that did not report a cut's volume: NaN)
        true_m3 = c.get("true_volume_m3", float("nan"))
        v_err = _pct(mine.volume_m3, true_m3)
        # the lab's share: the bulk density the assays gave against the simulator's
        d_err = _pct(mine.tonnes / mine.volume_m3, c["true_tonnes"] / true_m3) \
            if mine.volume_m3 > 0 and true_m3 > 0 else float("nan")
        fe = mine.grade.get("Fe", float("nan"))
        d_fe = fe - c["grade"]["Fe"]
        good = abs(t_err) <= TARGET_CUT_PCT and abs(d_fe) <= TARGET_FE_PP
        ok &= good
        within += good
        cut_errors[c["cut_id"]] = (t_err, d_fe, good)
        worst_pct, worst_pp = max(worst_pct, abs(t_err)), max(worst_pp, abs(d_fe))
        vol_errs.append(abs(v_err))
        d_exact = exact[c["cut_id"]].grade.get("Fe", float("nan")) - c["grade"]["Fe"]
        worst_exact_pp = max(worst_exact_pp, abs(d_exact))
        # NaN for a run simulated before the simulator kept it
        floor_pp = c.get("lab_window_fe_pct", math.nan) - c["grade"]["Fe"]
        floor_pps.append(abs(floor_pp))
        print(f"{c['cut_id']:<8} {_t(mine.tonnes):>10} {_t(c['true_tonnes']):>10} {t_err:>+7.2f} "
              f"{v_err:>+6.2f} {d_err:>+6.2f} {_t(mine.tonnes_scale):>10} {fe:>8.2f} "
              f"{c['grade']['Fe']:>8.2f} {d_fe:>+6.2f} "
              f"{d_exact:>+9.2f} {floor_pp:>+9.2f} {mine.assayed_fraction:>7.2f} {mine.residual_m3:>+9.3f}  "
              f"{'PASS' if good else 'MISS'}")
    print("counters: " + ", ".join(f"{k} {v:,}" for k, v in sorted(state.counters.items())))
    cut_lots(result)
    worst_lot_pct = lot_tonnes(result)
    deposition_times(result)
    return {"scenario": result["scenario"], "seed": result["seed"],
            "noise_seed": result.get("noise_seed", result["seed"]),
            "cut_errors": cut_errors, "pile_pct": err,
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
    print(f"\n{'run':<{width}} {'pile %':>7} {'cuts met':>9} {'worst t %':>9} {'worst vol %':>11} "
          f"{'worst Fe pp':>11} {'exact lab':>9} {'lab floor':>9} {'worst lot %':>11}  verdict")
    for f in figures:
        print(f"{_run_name(f):<{width}} {f['pile_pct']:>+7.2f} "
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
    """``bench-scale (seed 5)`` or ``bench-scale (seed 5, noise 1005)``."""
    return f"{result['scenario']} ({_draw(result)})"


def noise_spread(figures: list[dict]) -> list[str]:
    """Per world (scenario and seed) measured with several draws of the sensors' noise:
    each cut's tonnes and Fe error in every draw, their mean and spread (sd), and whether
    every draw, some or none meets the targets.  Returns the cuts every draw misses.

    The simulator's world (belt, stacking, cuts, lab) follows ``--seed`` alone and the
    scanner's, encoders' and GNSS noise ``--noise-seed``, so a cut missed by some draws
    and not others is missed by the luck of the noise, and one every draw misses by the
    world's geometry or the model.  A diagnosis, not a target.
    """
    import numpy as np

    worlds: dict[tuple[str, int], list[dict]] = {}
    for f in figures:
        worlds.setdefault((f["scenario"], f["seed"]), []).append(f)
    always = []
    for (scenario, seed), runs in worlds.items():
        if len(runs) < 2:
            continue
        print(f"\n-- {scenario} (seed {seed}): each cut's error over {len(runs)} draws of the "
              f"sensors' noise (noise seeds {', '.join(str(r['noise_seed']) for r in runs)})")
        print(f"{'cut':<8} {'err % by draw':>{7 * len(runs) - 1}} {'mean':>6} {'sd':>5}   "
              f"{'d pp by draw':>{7 * len(runs) - 1}} {'mean':>6} {'sd':>5}  met")
        for cut_id in runs[0]["cut_errors"]:
            rows = [r["cut_errors"].get(cut_id, (math.nan, math.nan, False)) for r in runs]
            errs = np.array([row[:2] for row in rows])
            met = sum(row[2] for row in rows)
            verdict = "all" if met == len(runs) else ("none" if met == 0 else f"{met}/{len(runs)}")
            if met == 0:
                always.append(f"{scenario} seed {seed} {cut_id}")
            print(f"{cut_id:<8} {' '.join(f'{e:>+6.2f}' for e in errs[:, 0])} "
                  f"{np.mean(errs[:, 0]):>+6.2f} {np.std(errs[:, 0], ddof=1):>5.2f}   "
                  f"{' '.join(f'{e:>+6.2f}' for e in errs[:, 1])} "
                  f"{np.mean(errs[:, 1]):>+6.2f} {np.std(errs[:, 1], ddof=1):>5.2f}  {verdict}")
    return always


def cut_lots(result: dict, min_share: float = 0.005) -> None:
    """Per cut that took more than one lot (ours or the simulator's, each beyond
    ``min_share`` of its tonnes): each lot's share, ours against the simulator's, and the
    Fe those shares alone move (pp): our cut's Fe less the Fe of our lots' material in
    the cut mixed in the simulator's shares (over graded tonnes: material of no lot has
    no grade).  Not a target; a diagnosis.

    A cut whose floor grazes the boundary between two lots takes the lower one in a
    slice a few mm thick, so the mean error of that buried top over the cut's cells
    moves the lower lot's share, and lots differ in Fe by several points.  Bench-scale
    seed 3's B1-C07 took 19.9 % of lot C where the simulator's took 16.9 % (-0.41 pp of
    its -0.47): our top of lot C stood 0.49 mm high on average over the cells the cut
    took it from (against the simulator's layers at that cut's start, which a run with
    its parcels kept at every cut gave).  Four draws of the sensors' noise: that top
    +0.49, +0.16, -0.21 and +0.41 mm, lot C's share 19.9, 17.7, 16.7 and 18.7 %, the
    cut's Fe error -0.47, -0.18, -0.03 and -0.30 pp.
    """
    state, truth = result["state"], result["truth"]
    join = state._join
    if join is None or "Fe" not in join.analytes:
        return
    fe = join.analytes.index("Fe")
    records = {c.cut_id: c for c in state.state.cuts}
    rows = []
    for c in truth["cuts"]:
        record = records.get(c["cut_id"])
        true_t = c.get("tonnes_by_lot", {})
        if record is None or not true_t or c["true_tonnes"] <= 0:
            continue
        per_lot: dict[str, list[float]] = {}   # lot -> [tonnes, graded tonnes, Fe tonnes]
        for removal in record.removals:
            for d in removal.deposits:
                t, sums, _assayed, g_t = join.material(d.info.lot_id, d.deposition_time_ns,
                                                       d.cell_volume_m3)
                entry = per_lot.setdefault(d.info.lot_id, [0.0, 0.0, 0.0])
                entry[0] += t
                entry[1] += g_t
                entry[2] += float(sums[fe])
        total = sum(t for t, _, _ in per_lot.values())
        total_graded = sum(g for _, g, _ in per_lot.values())
        if total <= 0 or total_graded <= 0:
            continue
        ours = {lot: t / total for lot, (t, _, _) in per_lot.items()}
        true = {lot: t / c["true_tonnes"] for lot, t in true_t.items()}
        lots = sorted(set(ours) | set(true))
        if sum(max(ours.get(lot, 0.0), true.get(lot, 0.0)) > min_share for lot in lots) < 2:
            continue
        # our Fe less the Fe of our lots' grades mixed in the simulator's shares (both over
        # graded tonnes: material of no lot has no grade; lots only one side took drop out)
        fe_of = {lot: f / g for lot, (_, g, f) in per_lot.items() if g > 0}
        weight = sum(true[lot] for lot in fe_of if lot in true)
        if weight <= 0:
            continue
        moved = (sum(f for _, _, f in per_lot.values()) / total_graded
                 - sum(true[lot] * fe_of[lot] for lot in fe_of if lot in true) / weight)
        shares = ", ".join(f"{lot or 'flagged'} {100 * ours.get(lot, 0.0):.1f}/"
                           f"{100 * true.get(lot, 0.0):.1f}" for lot in lots
                           if max(ours.get(lot, 0.0), true.get(lot, 0.0)) >= 0.0005)
        rows.append(f"  {c['cut_id']:<8} {moved:>+6.2f}  {shares}")
    if rows:
        print("cuts taking more than one lot: Fe pp the lot shares alone move, and each lot's "
              "share of the cut's tonnes, ours/truth %")
        print("\n".join(rows))
    else:
        print("cuts taking more than one lot: none")


def lot_tonnes(result: dict) -> float:
    """Per lot: the tonnes the pile holds now, ours (its deposits' tonnes) against the
    simulator's; returns the worst error (%, NaN when the truth has no lots).

    Which lot each piece of material belongs to is what a cut's grade is built from;
    material given to the wrong pass shows here as one lot heavy and the next light (a
    hidden flank completed with the next pass's layer).  Flagged material (outside any
    pass) has no lot and is printed apart.  Not a target; a diagnosis.
    """
    state, truth = result["state"], result["truth"]
    true_t = truth["world"].get("tonnes_by_lot", {})
    ours: dict[str, float] = {}
    for d in state.deposits:
        ours[d.lot_id] = ours.get(d.lot_id, 0.0) + d.tonnes
    errs = {lot: _pct(ours.get(lot, 0.0), t) for lot, t in sorted(true_t.items())}
    if errs:
        print("lots in the pile, ours vs truth (t): " + "; ".join(
            f"{lot} {_t(ours.get(lot, 0.0))} vs {_t(true_t[lot])} ({e:+.2f} %)"
            for lot, e in errs.items())
              + (f"; flagged {_t(ours[''])}" if ours.get("", 0.0) > 0 else ""))
    return max((abs(e) for e in errs.values() if not math.isnan(e)), default=math.nan)


def deposition_times(result: dict) -> None:
    """Per pass: our deposition times against the simulator's, where both hold its material.

    A lot's grade follows belt time (an assay per window of tens of seconds), so a cut's Fe
    depends on when each cell's material was laid.  The simulator keeps a thickness-weighted
    mean time per cell and deposit on its own grid; ours is the layer stack's, per cell of
    ours, compared at the simulator cell holding our cell's centre, weighted by our
    thickness.  Not a target; a diagnosis.

    Each pass's row also splits the mean by where the cells lie along its stacker's run
    (the rail positions of its start and end): before the start, each fifth of the run, past
    the end.  The error has a shape there that the mean hides, the same on all five
    bench-scale seeds: the first pass reads 12-25 s early over the first 60 % of its run,
    the later ones 11-18 s late from 40 % of theirs to the end and up to 15 s early
    before 20 %.
    """
    import numpy as np

    from projector.grid import GridGeometry, cell_centres, cell_index, inside

    arrays = np.load(result["sim_dir"] / "truth.npz")
    truth, state = result["truth"], result["state"].state
    grid = truth["world"]["grid"]
    sim_grid = GridGeometry(float(grid["origin_x_m"]), float(grid["origin_y_m"]),
                            float(grid["cell_m"]), int(grid["nx"]), int(grid["ny"]))
    geometry, stack = state.pile.geometry, state.stack
    x, y = cell_centres(geometry)
    on = inside(sim_grid, x, y)
    jx, jy = cell_index(sim_grid, x, y)
    jx, jy = np.clip(jx, 0, sim_grid.nx - 1), np.clip(jy, 0, sim_grid.ny - 1)
    slot_of = {s["deposit_id"]: s["slot"] for s in truth["world"]["slots"]}
    rows = []
    for p in truth["passes"]:
        mine = state.passes.get(p["pass_id"])
        slot = slot_of.get(p["deposit"])
        if mine is None or slot is None or mine.deposit_index > stack.n_deposits:
            continue
        ours = stack.deposition_time_ns(mine.deposit_index)
        thick = stack.thickness(mine.deposit_index)
        true_t = arrays["time_ns"][slot][jy, jx]
        both = on & (thick > 0) & np.isfinite(ours) & (arrays["thickness"][slot][jy, jx] > 0)
        if not both.any():
            continue
        d_s = (ours[both] - true_t[both]) / 1e9
        w = thick[both]
        run_m = mine.end_y_m - mine.start_y_m
        parts = []
        if math.isfinite(run_m) and run_m != 0:
            frac = (y[both] - mine.start_y_m) / run_m
            for lo, hi in _RUN_PARTS:
                part = (frac >= lo) & (frac < hi)
                parts.append(float(np.average(d_s[part], weights=w[part]))
                             if w[part].sum() > 0 else math.nan)
        rows.append((p["pass_id"], (p["t1_ns"] - p["t0_ns"]) / 1e9, int(both.sum()),
                     float(np.average(d_s, weights=w)),
                     float(np.sqrt(np.average(d_s ** 2, weights=w))), parts))
    if rows:
        print("deposition time, ours - simulator's, per pass (s, weighted by our thickness), "
              "and its mean by where along the stacker's run the cells lie:")
        print(f"  {'pass':<12} {'length':>7} {'cells':>8} {'mean':>6} {'rms':>6}  "
              + " ".join(f"{label:>6}" for label in _RUN_LABELS))
        for pid, dur, n, mean, rms, parts in rows:
            print(f"  {pid:<12} {dur:5.0f} s {n:>8,} {mean:+6.1f} {rms:6.1f}  "
                  + " ".join(f"{v:+6.1f}" if math.isfinite(v) else f"{'':>6}" for v in parts))


#: Where along a stacker's run (its fraction, 0 at the start, 1 at the end) the cells of
#: :func:`deposition_times`' columns lie: before the start (a pile's end slope), each fifth
#: of the run, past the end.
_RUN_PARTS = ((-math.inf, 0.0), (0.0, 0.2), (0.2, 0.4), (0.4, 0.6), (0.6, 0.8), (0.8, 1.0),
              (1.0, math.inf))
_RUN_LABELS = ("<0", "0-.2", ".2-.4", ".4-.6", ".6-.8", ".8-1", ">1")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", action="append", choices=("demo", "bench-scale"))
    ap.add_argument("--seed", type=int, action="append",
                    help="simulator seed; repeat for several (default: 1)")
    ap.add_argument("--duration", type=float, default=None, help="site hours (default: all)")
    ap.add_argument("--noise-seed", type=int, action="append", metavar="N",
                    help="also measure each seed's world with the sensors' noise from seed N "
                    "(stockpile sim --noise-seed); repeatable; a table then gives each cut's "
                    "error over the draws, the seed's own first")
    ap.add_argument("--keep", metavar="DIR", help="keep (and reuse) the runs in DIR")
    ap.add_argument("--explain", action="store_true",
                    help="split each cut's error into the envelope's and the surface's "
                    "(simulates with --truth-cut-surfaces)")
    args = ap.parse_args(argv)
    scenarios = args.scenario or ["demo", "bench-scale"]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.keep or tmp)
        out.mkdir(parents=True, exist_ok=True)
        figures = []
        for seed in args.seed or [1]:
            for scenario in scenarios:
                for noise_seed in [None, *(n for n in args.noise_seed or [] if n != seed)]:
                    result = run(scenario, seed, out, args.duration, cut_surfaces=args.explain,
                                 noise_seed=noise_seed)
                    figures.append(report(result))
                    if args.explain:
                        explain(result)
        ok = all(f["ok"] for f in figures)
        if len(figures) > 1:
            summary(figures)
        if args.noise_seed:
            always = noise_spread(figures)
            print(f"\ncuts every draw misses: {', '.join(always) or 'none'}")
    print(f"\n{'all targets met' if ok else 'some targets missed'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())

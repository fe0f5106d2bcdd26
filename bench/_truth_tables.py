"""``projector_truth.py``'s diagnosis tables: figures beside the targets, not targets.

Per run: each cut that took more than one lot and the Fe its lot shares move
(:func:`cut_lots`), each lot's tonnes in the pile (:func:`lot_tonnes`) and each pass's
deposition times (:func:`deposition_times`), ours against the simulator's.  Over several
draws of the sensors' noise: each cut's errors per draw (:func:`noise_spread`).  Also the
two number formats the tables share (:func:`pct`, :func:`fmt_tonnes`).
"""

from __future__ import annotations

import math

import numpy as np

from projector.grid import GridGeometry, cell_centres, cell_index, inside


def pct(value: float, reference: float) -> float:
    """``value`` against ``reference`` in % (NaN for a cut that took nothing)."""
    return (value / reference - 1) * 100 if reference > 0 else float("nan")


def fmt_tonnes(tonnes: float) -> str:
    """Tonnes with four significant digits (bench-scale cuts weigh grams)."""
    return f"{tonnes:,.1f}" if abs(tonnes) >= 100 else f"{tonnes:.4g}"


def by_world(figures: list[dict]) -> dict[tuple[str, int], list[dict]]:
    """Runs' figures grouped by world (scenario, seed), in the order first met: a world's
    draws of the sensors' noise together."""
    worlds: dict[tuple[str, int], list[dict]] = {}
    for f in figures:
        worlds.setdefault((f["scenario"], f["seed"]), []).append(f)
    return worlds


def noise_spread(figures: list[dict]) -> list[str]:
    """Per world (scenario and seed) measured with several draws of the sensors' noise:
    each cut's tonnes and Fe error in every draw, their mean and spread (sd), and whether
    every draw, some or none meets the targets.  Returns the cuts every draw misses.

    The simulator's world (belt, stacking, cuts, lab) follows ``--seed`` alone and the
    scanner's, encoders' and GNSS noise ``--noise-seed``, so a cut missed by some draws
    and not others is missed by the luck of the noise, and one every draw misses by the
    world's geometry or the model.  A diagnosis, not a target.
    """
    always = []
    for (scenario, seed), runs in by_world(figures).items():
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


def _worst(errors: np.ndarray) -> float:
    """The largest finite absolute error (NaN when there is none)."""
    finite = np.abs(errors[np.isfinite(errors)])
    return float(finite.max()) if finite.size else math.nan


def mean_over_draws(figures: list[dict], targets: dict[str, float]) -> bool:
    """Issue 42's verdicts, per world (scenario and seed) judged on the mean over its
    draws of the sensors' noise: the pile's tonnes and volume, every cut's tonnes, and
    every cut's Fe with an exact lab (the ``exact lab`` column).  Prints one line per
    world and one per scenario; returns whether every world met every target.

    ``targets``: ``pile_pct``, ``volume_pct``, ``cut_pct``, ``fe_pp``.
    """
    print(f"\n-- the targets on the mean over each world's draws (pile {targets['pile_pct']:g} %, "
          f"volume {targets['volume_pct']:g} %, each cut {targets['cut_pct']:g} % and "
          f"{targets['fe_pp']:g} pp Fe with an exact lab)")
    print(f"{'world':<16} {'draws':>5} {'pile %':>7} {'vol %':>6} {'cuts met':>9} "
          f"{'worst t %':>9} {'worst Fe pp':>11}  verdict")
    by_scenario: dict[str, list[bool]] = {}
    for (scenario, seed), runs in by_world(figures).items():
        pile = float(np.mean([r["pile_pct"] for r in runs]))
        volume = float(np.mean([r["volume_pct"] for r in runs]))
        cut_ids = list(runs[0]["cut_errors"])
        t_mean = np.array([np.mean([r["cut_errors"].get(k, (math.nan,))[0] for r in runs])
                           for k in cut_ids])
        fe_mean = np.array([np.mean([r["cut_exact_fe"].get(k, math.nan) for r in runs])
                            for k in cut_ids])
        met = (np.abs(t_mean) <= targets["cut_pct"]) & (np.abs(fe_mean) <= targets["fe_pp"])
        ok = bool(abs(pile) <= targets["pile_pct"] and abs(volume) <= targets["volume_pct"]
                  and met.all())
        by_scenario.setdefault(scenario, []).append(ok)
        print(f"{scenario + ' seed ' + str(seed):<16} {len(runs):>5} {pile:>+7.2f} {volume:>+6.2f} "
              f"{f'{int(met.sum())}/{len(cut_ids)}':>9} {_worst(t_mean):>9.2f} "
              f"{_worst(fe_mean):>11.2f}  {'PASS' if ok else 'MISS'}")
    for scenario, oks in by_scenario.items():
        print(f"{scenario}: {sum(oks)} of {len(oks)} worlds meet every target")
    return all(all(oks) for oks in by_scenario.values())


def cut_lots(result: dict, min_share: float = 0.005) -> None:
    """Per cut that took more than one lot (ours or the simulator's, each beyond
    ``min_share`` of its tonnes): each lot's share, ours against the simulator's, and the
    Fe those shares alone move (pp): our cut's Fe less the Fe of our lots' material in
    the cut mixed in the simulator's shares (over graded tonnes: material of no lot has
    no grade).  Not a target; a diagnosis.

    A cut whose floor grazes the boundary between two lots takes the lower one in a
    slice a few mm thick, so the mean error of that buried top over the cut's cells
    moves the lower lot's share, and lots differ in Fe by several points (see
    docs/design-notes.md).
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
    errs = {lot: pct(ours.get(lot, 0.0), t) for lot, t in sorted(true_t.items())}
    if errs:
        print("lots in the pile, ours vs truth (t): " + "; ".join(
            f"{lot} {fmt_tonnes(ours.get(lot, 0.0))} vs {fmt_tonnes(true_t[lot])} ({e:+.2f} %)"
            for lot, e in errs.items())
              + (f"; flagged {fmt_tonnes(ours[''])}" if ours.get("", 0.0) > 0 else ""))
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
    the end, a shape of the error that the mean hides (see docs/design-notes.md).
    """
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

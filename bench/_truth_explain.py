"""``projector_truth.py --explain``: each cut's error split by where it comes from.

:func:`explain` prints, per cut, the true surface above the projector's cutting-envelope
floor on the simulator's grid and on ours, and our layer stack and height map above that
floor as of the cut's start (volumes, and their errors in %); then what slid into each
cut's hole (:func:`hole_fill`) and each buried deposit top as the first cut finds it
(:func:`buried_tops`).  The helpers put the simulator's arrays on our grid
(:func:`on_our_grid`), give the fold state just before each cut from one fold
(:func:`states_before`) and the volume of a surface above a floor (:func:`above_m3`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from _truth_tables import pct
from ledger import open_ledger
from projector import cuts, fold as F
from projector.envelope import cut_floor
from projector.grid import GridGeometry, cell_centres
from projector.query import FAR_FUTURE_NS


def explain(result: dict) -> None:
    """Per cut: the envelope's error and the surface's error (see the module docstring)."""
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
        befores = states_before(store, pile_id, [c["t0_ns"] for c in truth["cuts"]])
    previous_end_ns = None
    slid_m3 = {c.cut_id: c.slumped_in_m3 for c in result["state"].cuts}
    # the true surface at each cut's start and, last, after the last cut, on our grid
    true_surfaces = [] if not befores else [
        on_our_grid(arrays, befores[0].pile.geometry, z)
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
        sim_m3 = above_m3(true_z.T.astype(np.float64),
                           np.fmax(cut_floor(sim_grid, machine, *joints), ground_m),
                           sim_grid.cell_area_m2)
        top = before.stack.surface()
        true_m3, ours_m3 = above_m3(surface, base, g.cell_area_m2), above_m3(top, base, g.cell_area_m2)
        map_m3 = above_m3(before.height.elevation, base, g.cell_area_m2)
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
              f"{pct(sim_m3, cut_m3):>+10.2f} {true_m3 * scale:>10.4g} "
              f"{pct(true_m3, sim_m3):>+7.2f} {ours_m3 * scale:>10.4g} "
              f"{pct(ours_m3, true_m3):>+8.2f} {map_m3 * scale:>10.4g} "
              f"{pct(map_m3, true_m3):>+7.2f} {bias_mm:>+13.2f} {seen_pct:>6.0f} "
              f"{slid_m3.get(c['cut_id'], math.nan) * scale:>8.4g} "
              f"{c.get('slump_m3', math.nan) * scale:>8.4g}", flush=True)
        if i + 1 < len(true_surfaces):
            fills.append((c["cut_id"], hole_fill(before, base, surface, true_surfaces[i + 1],
                                                  c["t0_ns"], ground_m)))
    print(f"\nwhat slid into each cut's hole ({unit}): our slide on our stack and on the true "
          "surface at the cut's start, and the simulator's")
    print(f"{'cut':<8} {'on ours':>9} {'on true':>9} {'sim':>9}")
    for cut_id, row in fills:
        print(f"{cut_id:<8} " + " ".join(f"{m3 * scale:>9.4g}" for m3 in row))
    if "first_cut_thickness" in arrays and befores:
        buried_tops(befores[0], arrays, truth, ground_m)


def hole_fill(before, floor_m, true_before_m, true_after_m, t0_ns: int,
              ground_m: float) -> tuple[float, float, float]:
    """What slid into one cut's hole (m3): our slide (``cuts.slump_face`` after clamping to
    the envelope floor ``floor_m``, +inf outside the footprint) run on our stack at the
    cut's start (``before``) and on the simulator's true surface then, and the simulator's
    own slide (its surface at the next cut's start less what the cut left).  The hole's
    fill is the volume above what the cut left in its footprint; the true surfaces are on
    our grid (NaN off the simulator's: its ground).

    Where our slide on the true surface matches the simulator's, the slide model is right
    and a difference in the first figure is our surface's (see docs/design-notes.md).
    """
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


def buried_tops(before, arrays, truth: dict, ground_m: float) -> None:
    """Each deposit's top under the top one as the first cut finds it, ours against the
    simulator's layers as stacked (``first_cut_thickness``): mean and rms (mm) over the
    cells where the simulator has both that deposit and one above it, as fused and as
    that cut fits them (``FoldConfig.boundary_fit_cells``)."""
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
        return on_our_grid(arrays, stack.geometry, z_m)

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


def on_our_grid(arrays, geometry, z_m):
    """A simulator array (``(ny, nx)`` on its cell centres ``arrays["x_centres"]``,
    ``["y_centres"]``) interpolated to our cell centres: ``(nx, ny)``, NaN off its grid."""
    x, y = cell_centres(geometry)
    return RegularGridInterpolator((arrays["y_centres"], arrays["x_centres"]),
                                   np.asarray(z_m, np.float64), bounds_error=False)(
        np.column_stack([y.ravel(), x.ravel()])).reshape(x.shape)


def states_before(store, pile_id: str, times_ns: list[int]) -> list:
    """The fold state (flushed, as :func:`project` leaves it) just before each time, with
    everything known: what ``project(store, pile_id, t - 1).state`` gives, from one fold."""
    if times_ns != sorted(times_ns):
        raise ValueError("the times must be in order")
    state, states = F.initial_state(F.FoldConfig(pile_id=pile_id)), []
    for event in store.as_of(FAR_FUTURE_NS, FAR_FUTURE_NS, types=list(F.GEOMETRY_TYPES)):
        while len(states) < len(times_ns) and event.valid_time_ns >= times_ns[len(states)]:
            states.append(F.flush(state.copy()))
        F.apply(state, event)
    return states + [F.flush(state.copy()) for _ in times_ns[len(states):]]


def above_m3(z_m, base_m, cell_area_m2: float) -> float:
    """Volume (m3) of a surface above a base (NaN surface: unseen; inf base: outside)."""
    return float(np.nansum(np.clip(z_m - base_m, 0.0, None))) * cell_area_m2

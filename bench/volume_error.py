"""Where the pile's volume goes missing: the projector's final surface against the truth's,
split by region.

    .venv/bin/python bench/projector_truth.py --scenario demo --seed 1 --keep /tmp/vol --poses truth
    .venv/bin/python bench/volume_error.py /tmp/vol/demo-seed1            # true-pose ledger
    .venv/bin/python bench/volume_error.py /tmp/vol/demo-seed1 --poses localizer
    .venv/bin/python bench/volume_error.py /tmp/vol/demo-seed1 --cache /tmp/vol/state.pkl

The argument is a run kept by ``bench/projector_truth.py --keep`` (the folder with
``truth.npz``; its ledger ``<run>.duckdb``, or ``<run>-localizer.duckdb`` with
``--poses localizer``).  The ledger is projected with everything known
(:func:`projector.query.project`, the default :class:`projector.fold.FoldConfig`), and
``--cache`` keeps the folded state in a pickle (reused when it exists).  The truth is the
simulator's final surface (``surface_z``: heights at its 0.25 m cells' centres, the
volume is their sum times the cell's area); its cells are moved onto our grid by their
centres (the two grids share the cell; a grid not aligned is refused).

Every cell of our grid falls in exactly one region, in this order of precedence:

- ``never seen``: no scan ever measured the cell (its height is the completion's cone,
  :mod:`projector.completion`, or the ground);
- ``off pile``: truth and ours at the ground (within 1 cm): the declared ground level;
- ``toe``: the truth within 0.5 m of the ground, or ours on it and the truth not (the
  band near the ground edge);
- ``cut bench``: a cut's envelope removed material there and the true slope is under
  20 deg;
- ``cut face``: within 2 m of a cut's footprint and the true slope 20 deg or more;
- ``top``: true slope under 10 deg;
- ``flank 10-25``, ``flank 25-33``, ``flank 33+``: the true slope in degrees.

For each region: cells, their area, and the mean difference (mm; ours - truth) of the
layer stack's top (the volume the projector reports is the stack's), of the height
map's fused elevation (as measured, at the points' mean position in the cell) and of the
same moved to the cell's centre (:meth:`projector.heightmap.HeightMap.centred_elevation`),
and the m3 the stack's difference makes.  A second table splits the seen cells by
whether their last update came before or after the last stacking pass ended, a third by
how far the stack's top lies from the height map (the noise margin the stack follows it
by, ``FoldConfig.margin_sigma``).  Findings: ``docs/fidelity.md``, "The pile's volume".
"""

from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ledger import open_ledger  # noqa: E402
from projector.query import project  # noqa: E402

#: the true surface within this of the ground is the toe (m)
TOE_M = 0.5
#: cells within this of a cut's footprint may be its face (m)
FACE_REACH_M = 2.0


def folded_state(run_dir: Path, poses: str, cache: Path | None):
    """The projector's folded state of the run's ledger (everything known)."""
    if cache is not None and cache.exists():
        return pickle.loads(cache.read_bytes())
    ledger = run_dir.parent / (run_dir.name + ("-localizer" if poses == "localizer" else "")
                               + ".duckdb")
    truth = __import__("json").loads((run_dir / "truth.json").read_text())
    with open_ledger(ledger, read_only=True) as store:
        state = project(store, truth["scenario"].get("pile_id", "P1")).state
    if cache is not None:
        cache.write_bytes(pickle.dumps(state))
    return state


def truth_on_grid(run_dir: Path, geometry) -> np.ndarray:
    """The true final surface (m) on our grid ``(nx, ny)`` (cells outside the truth's grid:
    the ground, 0)."""
    t = np.load(run_dir / "truth.npz")
    z, xc, yc = t["surface_z"], t["x_centres"], t["y_centres"]   # z: (ny_t, nx_t)
    cell = float(xc[1] - xc[0])
    if abs(cell - geometry.cell_m) > 1e-9:
        raise SystemExit(f"truth cell {cell} m, ours {geometry.cell_m} m: not supported")
    ox = (geometry.origin_x_m + 0.5 * cell - xc[0]) / cell
    oy = (geometry.origin_y_m + 0.5 * cell - yc[0]) / cell
    if abs(ox - round(ox)) > 1e-6 or abs(oy - round(oy)) > 1e-6:
        raise SystemExit(f"the grids are not aligned (offsets {ox}, {oy} cells)")
    ox, oy = round(ox), round(oy)
    out = np.zeros(geometry.shape)
    ix = np.arange(geometry.nx) + ox
    iy = np.arange(geometry.ny) + oy
    okx = (ix >= 0) & (ix < z.shape[1])
    oky = (iy >= 0) & (iy < z.shape[0])
    out[np.ix_(okx, oky)] = z[np.ix_(iy[oky], ix[okx])].T
    outside = float(z.sum() * cell * cell - out.sum() * cell * cell)
    if abs(outside) > 1e-6:
        print(f"warning: {outside:.3f} m3 of the truth lies outside our grid")
    return out


def slope_deg(z: np.ndarray, cell_m: float) -> np.ndarray:
    gx, gy = np.gradient(z, cell_m)
    return np.degrees(np.arctan(np.hypot(gx, gy)))


def regions(state, truth: np.ndarray) -> dict[str, np.ndarray]:
    """Masks (nx, ny) of the regions, mutually exclusive (see the module's docstring)."""
    g = state.pile.geometry
    ground = state.pile.ground_z_m
    top = state.stack.surface()
    seen = state.height.seen
    slope = slope_deg(truth, g.cell_m)
    cut = np.zeros(g.shape, bool)
    for c in state.cuts:
        for r in c.removals:
            cut.flat[r.flat_cells(g.shape)] = True
    near_cut = ndimage.binary_dilation(cut, iterations=round(FACE_REACH_M / g.cell_m))
    left = np.ones(g.shape, bool)
    out = {}

    def take(name, mask):
        m = mask & left
        left[m] = False
        out[name] = m

    take("never seen", ~seen)
    take("off pile", (truth - ground <= 0.01) & (np.abs(top - ground) <= 0.01))
    take("toe", truth - ground < TOE_M)
    take("cut bench", cut & (slope < 20))
    take("cut face", near_cut & (slope >= 20))
    take("top", slope < 10)
    take("flank 10-25", slope < 25)
    take("flank 25-33", slope < 33)
    take("flank 33+", left.copy())
    return out


def table(title: str, masks: dict[str, np.ndarray], diffs: dict[str, np.ndarray],
          area: float) -> None:
    stack = diffs["stack"]
    print(f"\n{title}")
    names = list(diffs)
    print(f"{'region':<26} {'cells':>7} {'m2':>8} " + " ".join(f"{n + ' mm':>13}" for n in names)
          + f" {'stack m3':>9} {'share %':>8}")
    total = float(np.nansum(stack) * area)
    for name, m in masks.items():
        n = int(m.sum())
        if not n:
            continue
        m3 = float(np.nansum(stack[m]) * area)
        cols = " ".join(f"{np.nanmean(d[m]) * 1000 if np.isfinite(d[m]).any() else np.nan:>+13.1f}"
                        for d in diffs.values())
        print(f"{name:<26} {n:>7,} {n * area:>8,.1f} {cols} {m3:>+9.2f} "
              f"{100 * m3 / total if total else np.nan:>+8.1f}")
    print(f"{'all':<26} {stack.size:>7,} {stack.size * area:>8,.1f} "
          + " ".join(f"{'':>13}" for _ in names) + f" {total:>+9.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path, help="a run kept by bench/projector_truth.py --keep")
    ap.add_argument("--poses", choices=("truth", "localizer"), default="truth")
    ap.add_argument("--cache", type=Path, help="a pickle of the folded state (reused)")
    args = ap.parse_args(argv)
    state = folded_state(args.run, args.poses, args.cache)
    g = state.pile.geometry
    area = g.cell_area_m2
    truth = truth_on_grid(args.run, g)
    ground = state.pile.ground_z_m
    top = state.stack.surface()
    hm = state.height
    elev = hm.elevation
    centred = hm.centred_elevation()
    diffs = {"stack": top - truth, "map": elev - truth, "map centred": centred - truth}
    true_v = float((truth - ground).sum() * area)
    ours_v = float(state.stack.total_volume_m3())
    print(f"pile volume: ours {ours_v:,.2f} m3 (stack top above ground "
          f"{float((top - ground).sum() * area):,.2f}), truth {true_v:,.2f} m3, "
          f"error {ours_v - true_v:+.2f} m3 ({100 * (ours_v / true_v - 1):+.3f} %)")
    seen = hm.seen
    map_m3 = np.nansum(np.where(seen, elev - truth, 0)) * area
    print(f"height map over seen cells: {map_m3:+.2f} m3 "
          f"as fused, {np.nansum(np.where(seen, centred - truth, 0)) * area:+.2f} m3 centred; "
          f"the stack there {np.sum(np.where(seen, top - truth, 0)) * area:+.2f} m3")
    masks = regions(state, truth)
    table("by region (ours - truth; mean over the region's cells)", masks, diffs, area)

    last_pass_end = max((p.ended_ns or p.started_ns) for p in state.passes.values())
    upd = hm.grid["last_update_ns"]
    on_pile = seen & ~masks["off pile"]
    with np.errstate(invalid="ignore"):
        by_time = {"seen, last update before the last pass ended": on_pile & (upd < last_pass_end),
                   "seen, last update after it": on_pile & (upd >= last_pass_end),
                   "never seen": ~seen}
    table("by when the cell was last updated (pile cells)", by_time, diffs, area)

    with np.errstate(invalid="ignore"):
        margin = (state.config.margin_sigma * np.sqrt(np.nan_to_num(hm.variance, nan=0.0))
                  + state.margin_m)
        lag = top - elev
    print("\nthe follow margin over seen pile cells: mean "
          f"{np.mean(margin[on_pile]) * 1000:.1f} mm; "
          f"stack - map mean {np.nanmean(lag[on_pile]) * 1000:+.1f} mm "
          f"({np.nansum(lag[on_pile]) * area:+.2f} m3)")
    with np.errstate(invalid="ignore"):
        bins = {"stack below map by > margin": on_pile & (lag < -margin),
                "stack below map within margin": on_pile & (lag < 0) & (lag >= -margin),
                "stack above map within margin": on_pile & (lag >= 0) & (lag <= margin),
                "stack above map by > margin": on_pile & (lag > margin)}
    table("by the stack's place against the height map (seen pile cells)", bins,
          {**diffs, "stack - map": lag}, area)

    # ground: bare cells far from the pile
    bare = masks["off pile"] | (seen & (truth - ground <= 0.0))
    print(f"\nground: {int(bare.sum()):,} cells true at the ground; height map there mean "
          f"{np.nanmean(elev[bare] - ground) * 1000:+.1f} mm, stack "
          f"{np.mean(top[bare] - ground) * 1000:+.1f} mm")
    counters = state.counters
    print("counters: " + ", ".join(f"{k} {v:,}" for k, v in sorted(counters.items())
                                    if "ground" in k or "complet" in k or "catch" in k))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

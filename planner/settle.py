"""The face a planned cut leaves slides to the angle of repose before the next cut.

A cut leaves walls steeper than repose; they fail and the material runs into the hole,
where the next cut takes it (the simulator's world does the same, by its own avalanche
model; see docs/design-notes.md).

The planner uses the projector's relaxation, :func:`projector.slump.relax_surface`
(volume-conserving flow between neighbours down to the repose slope), on a grid of
``block`` x ``block`` cells around the cut (block means of the surface and the ground),
for speed.  The change of each block is then put back on its cells exactly: a block that
lost material loses it from its highest cells down (a water level from the top), a block
that gained fills its lowest cells up.  Volume is conserved to rounding.

On a layer stack (:func:`settle_stack`) the composition moves with the material, as in the
projector's fold: the stack is clamped where the surface fell (what slid, per deposit) and
what slid is laid where it rose, each deposit in proportion to its share, at its mean
deposition time.
"""

from __future__ import annotations

import math

import numpy as np

from projector.layers import LayerStack, Removal
from projector.slump import relax_surface

__all__ = ["relax_region", "settle_stack", "level_down", "level_up"]


def level_down(values: np.ndarray, amount: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """Remove ``amount`` from each row of ``values`` from the top down (a falling level).

    Parameters
    ----------
    values : ndarray, shape (B, M)
        Heights per row (m).
    amount : ndarray, shape (B,)
        Thickness-sum to remove per row (m, >= 0), at most ``sum(values - floor)``.
    floor : ndarray, shape (B, M)
        Nothing goes below it (m).

    Returns
    -------
    ndarray, shape (B, M)
        ``max(min(values, level), floor)`` with the level solved per row.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or amount.shape != (v.shape[0],) or floor.shape != v.shape:
        raise ValueError("values (B, M), amount (B,), floor (B, M) expected")
    # removable part above the floor; remove from the top of the (v - floor) columns is
    # the same as lowering a level through max(v, floor)
    top = np.maximum(v, floor)
    s = -np.sort(-top, axis=1)                         # descending
    m = v.shape[1]
    csum = np.cumsum(s, axis=1)
    j = np.arange(1, m + 1)
    # removed when the level is at s[:, k]: sum_{i<=k} s_i - (k+1) s_k
    removed_at = csum - j * s
    k = np.sum(removed_at < amount[:, None], axis=1) - 1  # last index with removed < amount
    k = np.clip(k, 0, m - 1)
    rows = np.arange(v.shape[0])
    level = (csum[rows, k] - amount) / (k + 1)
    return np.maximum(np.minimum(top, level[:, None]), floor)


def level_up(values: np.ndarray, amount: np.ndarray) -> np.ndarray:
    """Add ``amount`` to each row of ``values`` filling the lowest cells first (a rising level).

    Parameters
    ----------
    values : ndarray, shape (B, M)
    amount : ndarray, shape (B,)
        Thickness-sum to add per row (m, >= 0).

    Returns
    -------
    ndarray, shape (B, M)
        ``max(values, level)`` with the level solved per row.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or amount.shape != (v.shape[0],):
        raise ValueError("values (B, M) and amount (B,) expected")
    s = np.sort(v, axis=1)
    m = v.shape[1]
    csum = np.cumsum(s, axis=1)
    j = np.arange(1, m + 1)
    added_at = j * s - csum                            # added when the level is at s[:, k]
    k = np.sum(added_at < amount[:, None], axis=1) - 1
    k = np.clip(k, 0, m - 1)
    rows = np.arange(v.shape[0])
    level = (amount + csum[rows, k]) / (k + 1)
    return np.maximum(v, level[:, None])


def relax_region(surface_m: np.ndarray, ground_m: np.ndarray, cell_m: float, tan_repose: float,
                 region: tuple[slice, slice], block: int, *, tol_m: float) -> float:
    """Let over-steep faces in ``region`` slide to ``tan_repose`` (in place, module docstring).

    Parameters
    ----------
    surface_m, ground_m : ndarray, shape (nx, ny)
        Surface (modified in place) and ground (m).
    cell_m : float
        Cell edge (m).
    tan_repose : float
        Tangent of the angle of repose (> 0).
    region : (slice, slice)
        Cells allowed to move (trimmed to whole blocks).
    block : int
        Cells per block edge (>= 1).
    tol_m : float
        Convergence tolerance of the relaxation (m).

    Returns
    -------
    float
        Volume moved (m3).
    """
    if surface_m.shape != ground_m.shape:
        raise ValueError(f"ground_m must have the shape of surface_m {surface_m.shape}")
    if not (math.isfinite(tan_repose) and tan_repose > 0):
        raise ValueError(f"tan_repose must be > 0, got {tan_repose!r}")
    if isinstance(block, bool) or int(block) < 1:
        raise ValueError(f"block must be >= 1, got {block!r}")
    b = int(block)
    xs, ys = region
    x0, x1, _ = xs.indices(surface_m.shape[0])
    y0, y1, _ = ys.indices(surface_m.shape[1])
    x1 = x0 + (x1 - x0) // b * b
    y1 = y0 + (y1 - y0) // b * b
    if x1 - x0 < 2 * b or y1 - y0 < 2 * b:
        return 0.0
    top = surface_m[x0:x1, y0:y1]
    base = ground_m[x0:x1, y0:y1]
    nbx, nby = (x1 - x0) // b, (y1 - y0) // b

    def blocks(a: np.ndarray) -> np.ndarray:   # (nbx*nby, b*b)
        return a.reshape(nbx, b, nby, b).transpose(0, 2, 1, 3).reshape(nbx * nby, b * b)

    def unblocks(a: np.ndarray) -> np.ndarray:
        return a.reshape(nbx, nby, b, b).transpose(0, 2, 1, 3).reshape(nbx * b, nby * b)

    tb, gb = blocks(top), blocks(base)
    tc, gc = tb.mean(axis=1), gb.mean(axis=1)
    relaxed = relax_surface(tc.reshape(nbx, nby), gc.reshape(nbx, nby), cell_m * b, tan_repose,
                            tol_m=tol_m).reshape(-1)
    change = (relaxed - tc) * (b * b)                 # thickness-sum per block
    new = tb.copy()
    lose = change < 0
    gain = change > 0
    if lose.any():
        new[lose] = level_down(tb[lose], -change[lose], gb[lose])
    if gain.any():
        new[gain] = level_up(tb[gain], change[gain])
    fine = unblocks(new)
    moved = float(np.sum(np.clip(top - fine, 0.0, None)) * cell_m * cell_m)
    surface_m[x0:x1, y0:y1] = fine
    return moved


def settle_stack(stack: LayerStack, new_top_m: np.ndarray) -> tuple[LayerStack, Removal]:
    """Move a stack's top to ``new_top_m`` (same volume), the slid material keeping its deposits.

    Where the new top is lower the stack is clamped to it (what slid, per deposit); where it
    is higher the slid material is laid, each deposit in proportion to its share of what
    slid, at that share's mean deposition time
    (:meth:`projector.layers.LayerStack.add_material`).

    Returns
    -------
    stack : LayerStack
    moved : Removal
        What slid (its volume is the volume moved, m3).
    """
    top = np.asarray(stack.surface())
    new = np.asarray(new_top_m, dtype=np.float64)
    if new.shape != top.shape:
        raise ValueError(f"new_top_m must have shape {top.shape}, got {new.shape}")
    fell = new < top
    settled, moved = stack.clamp(np.where(fell, new, np.inf))
    raised = np.where(new > top, new - top, 0.0)
    total = moved.volume_m3
    if total <= 0 or not raised.any():
        return settled, moved
    # what rose is what fell (to rounding); share it out by deposit
    for part in moved.deposits:
        settled = settled.add_material(part.index, raised * (part.volume_m3 / total),
                                       part.mean_deposition_time_ns)
    return settled, moved

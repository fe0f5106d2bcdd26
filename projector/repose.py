"""The angle of repose as the fold uses it.

tan(repose) configured or estimated from the seen slopes (:func:`tan_repose`, over a
baseline :func:`slope_baseline_cells` sets), the repose cone under a seen surface
(:func:`cone`: the floor below which a hidden flank cannot lie) and how far a flank runs
out from the crest (:func:`flank_reach_m`).  Why the baseline is bounded as it is: see
docs/design-notes.md.
"""

from __future__ import annotations

import math

import numpy as np

from projector import slump
from projector.state import ProjectorState

__all__ = ["tan_repose", "slope_baseline_cells", "cone", "flank_reach_m"]

#: the angle of repose assumed until one is estimated (deg)
DEFAULT_REPOSE_DEG = 35.0


def tan_repose(state: ProjectorState, *, estimate: bool = True) -> float:
    """tan(angle of repose): configured, else estimated from the seen slopes (35 deg
    until enough are seen; the last good estimate is kept in ``state.tan_repose``).
    ``estimate=False`` takes the last estimate without a new one (cheap enough for every
    batch of scans)."""
    if state.config.repose_deg is not None:
        return math.tan(math.radians(state.config.repose_deg))
    if estimate:
        cell = state.pile.geometry.cell_m
        deg = slump.estimate_repose_deg(state.height.elevation, cell,
                                        baseline_cells=slope_baseline_cells(state))
        if math.isfinite(deg):
            state.tan_repose = math.tan(math.radians(deg))
    return (state.tan_repose if math.isfinite(state.tan_repose)
            else math.tan(math.radians(DEFAULT_REPOSE_DEG)))


def slope_baseline_cells(state: ProjectorState) -> int:
    """Half the run (cells) the repose angle's slopes are measured over: at least 4, and
    the run at least 8 point sds, but within a quarter of a flank's run.

    Noise in the heights makes a slope read steep, ``|g + n|^2 = |g|^2 + |n|^2``, the more
    so the shorter the run; a young pile's flanks are short, and most long runs would
    straddle the crest or the toe.  So the half run is at most a quarter of the seen
    pile's height over tan(35 deg) (the angle assumed before one is estimated), and never
    under 4 cells.
    """
    cell = state.pile.geometry.cell_m
    half_run = max(4, math.ceil(4.0 * state.point_sd_m / cell))
    if state.stack is not None and state.height is not None and np.isfinite(
            state.height.elevation).any():
        height = float(np.nanmax(state.height.elevation)) - float(np.min(state.stack.ground()))
        flank_cells = height / math.tan(math.radians(DEFAULT_REPOSE_DEG)) / cell
        half_run = min(half_run, max(4, int(flank_cells / 4)))
    return half_run


def cone(state: ProjectorState, elevation: np.ndarray) -> np.ndarray:
    """The repose cone under the seen surface ``elevation`` (m, (nx, ny); NaN where no
    seen cell reaches), at the slope a cut's face slides to (so a face left standing at
    it is not lifted again)."""
    tan = tan_repose(state) * (1.0 + state.config.relax_slack)
    return slump.repose_floor(elevation, state.pile.geometry.cell_m, tan)


def flank_reach_m(state: ProjectorState) -> float:
    """How far a flank runs out horizontally: the pile's height / tan(repose) (m), with the
    last repose estimate (no new one)."""
    height = max(float(np.max(state.stack.surface() - state.stack.ground())), 0.0)
    return height / tan_repose(state, estimate=False)

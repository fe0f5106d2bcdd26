"""The model against each survey of a pile (``stockpile audit survey``).

For each ``survey`` event of the pile (as known at K), over the cells the survey covers
(its points' cells on the pile's grid) and above the model's ground (net volumes: a
surface below the ground counts negative, so a survey's noise on bare ground cancels):

- the model's volume just before the survey's time (a rebase on the survey,
  :mod:`projector.rebase`, is at its time), as known then (K = the survey's time) and as
  known at K; the survey's volume (its mean height per cell);
- the difference, survey minus model, in m3, in tonnes (at the model's bulk density as
  known at K) and in % of the model's volume;
- where it lies: the difference summed over blocks of ``block_m`` (a map, m3 per block,
  and the blocks with the largest differences);
- under the pile's ``survey_rebase`` policy, what the rebase changed (its
  :class:`projector.state.RebaseRecord`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from projector.config import FoldConfig
from projector.query import project
from projector.state import RebaseRecord
from projector.surveys import survey_heights
from schemas.events import decode_payload

__all__ = ["SurveyReconciliation", "audit_surveys", "reconcile_survey"]

#: edge of the blocks the difference map sums over (m)
DEFAULT_BLOCK_M = 10.0


@dataclass(frozen=True)
class SurveyReconciliation:
    """One survey against the model (volumes m3, tonnes t, times UTC ns)."""

    survey_id: str
    time_ns: int
    recorded_time_ns: int
    provider: str
    accuracy_m: float
    points: int
    cells: int
    area_m2: float
    survey_m3: float
    model_then_m3: float
    model_now_m3: float
    density_t_m3: float
    block_m: float
    #: the blocks' corner (site frame, m) and the difference per block, survey - model now
    #: (m3; rows along x, columns along y; NaN: no surveyed cell in the block)
    map_origin_m: tuple[float, float] = (0.0, 0.0)
    map_m3: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), repr=False)
    #: per cell of the pile's grid (from ``map_origin_m``), survey - model now (m; NaN: no
    #: survey point in the cell) and the cell's edge (m)
    cells_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), repr=False)
    cell_m: float = 0.0
    #: what the model's rebase on this survey changed (the pile's ``survey_rebase``
    #: policy), as known at K; None: no rebase
    rebase: RebaseRecord | None = None

    @property
    def diff_then_m3(self) -> float:
        return self.survey_m3 - self.model_then_m3

    @property
    def diff_now_m3(self) -> float:
        return self.survey_m3 - self.model_now_m3

    @property
    def diff_now_t(self) -> float:
        return self.diff_now_m3 * self.density_t_m3

    @property
    def diff_then_t(self) -> float:
        return self.diff_then_m3 * self.density_t_m3

    @property
    def diff_now_pct(self) -> float:
        return 100.0 * self.diff_now_m3 / self.model_now_m3 if self.model_now_m3 else math.nan

    @property
    def diff_then_pct(self) -> float:
        return 100.0 * self.diff_then_m3 / self.model_then_m3 if self.model_then_m3 else math.nan

    def largest_blocks(self, n: int = 5) -> list[tuple[float, float, float]]:
        """The ``n`` blocks with the largest |difference|: ``(centre x, centre y, m3)``."""
        values = np.nan_to_num(self.map_m3, nan=0.0)
        order = np.argsort(-np.abs(values), axis=None)[:n]
        out = []
        for flat in order:
            i, j = np.unravel_index(flat, values.shape)
            if values[i, j] == 0.0:
                break
            out.append((self.map_origin_m[0] + (i + 0.5) * self.block_m,
                        self.map_origin_m[1] + (j + 0.5) * self.block_m, float(values[i, j])))
        return out


def _above_ground_m3(top_m: np.ndarray, ground_m: np.ndarray, cells: np.ndarray,
                     area_m2: float) -> np.ndarray:
    """Per cell, the net volume above the ground (m3, negative where the surface is below
    it) where ``cells``, else 0."""
    return np.where(cells, top_m - ground_m, 0.0) * area_m2


def _block_sums(values: np.ndarray, cells: np.ndarray, per_block: int) -> np.ndarray:
    nx, ny = values.shape
    bx, by = -(-nx // per_block), -(-ny // per_block)
    pad = np.zeros((bx * per_block, by * per_block))
    pad[:nx, :ny] = np.where(cells, values, 0.0)
    seen = np.zeros(pad.shape, bool)
    seen[:nx, :ny] = cells
    sums = pad.reshape(bx, per_block, by, per_block).sum(axis=(1, 3))
    any_seen = seen.reshape(bx, per_block, by, per_block).any(axis=(1, 3))
    return np.where(any_seen, sums, np.nan)


def audit_surveys(store, pile_id: str, known_time_ns: int | None = None, *,
                  block_m: float = DEFAULT_BLOCK_M,
                  config: FoldConfig | None = None) -> list[SurveyReconciliation]:
    """Every survey of ``pile_id`` known at K (default: now), against the model folded
    with ``config`` (default: the fold's defaults)."""
    known = 2**63 - 1 if known_time_ns is None else int(known_time_ns)
    return [reconcile_survey(store, r, known_time_ns, block_m=block_m, config=config)
            for r in store.as_of(2**63 - 1, known, types=["survey"])
            if decode_payload(r.type, r.payload).pile_id == pile_id]


def reconcile_survey(store, record, known_time_ns: int | None = None, *,
                     block_m: float = DEFAULT_BLOCK_M, config: FoldConfig | None = None,
                     then: bool = True) -> SurveyReconciliation:
    """One ``survey`` record of ``store`` against the model as of its time, as known at K
    (default: now) and, with ``then``, as known at the survey's time (else NaN)."""
    if not (block_m > 0 and math.isfinite(block_m)):
        raise ValueError(f"the block edge must be > 0 m, got {block_m}")
    msg = decode_payload(record.type, record.payload)
    pile_id = msg.pile_id
    before_ns = record.valid_time_ns - 1      # the model just before the survey
    now = project(store, pile_id, before_ns, known_time_ns, config=config)
    if now.geometry is None:
        raise ValueError(f"pile {pile_id!r} is not declared as of survey {msg.survey_id}")
    g = now.geometry
    heights, counts = survey_heights(msg, g)
    cells = counts > 0
    area = g.cell_area_m2
    ground = now.state.stack.ground()
    survey_cells = _above_ground_m3(np.nan_to_num(heights), ground, cells, area)
    now_cells = _above_ground_m3(now.state.stack.surface(), ground, cells, area)
    then_m3 = math.nan
    if then:
        before = project(store, pile_id, before_ns, record.valid_time_ns, config=config)
        then_m3 = (float(_above_ground_m3(before.state.stack.surface(),
                                          before.state.stack.ground(), cells, area).sum())
                   if before.geometry is not None else 0.0)
    rebase = None
    if now.state.pile.survey_rebase:
        after = project(store, pile_id, record.valid_time_ns, known_time_ns, config=config)
        rebase = next((r for r in after.state.rebases if r.survey_id == msg.survey_id), None)
    per_block = max(1, int(round(block_m / g.cell_m)))
    density = now.tonnes / now.volume_m3 if now.volume_m3 > 0 else math.nan
    return SurveyReconciliation(
        msg.survey_id, record.valid_time_ns, record.recorded_time_ns, msg.provider,
        msg.accuracy_m, int(msg.points), int(cells.sum()), float(cells.sum() * area),
        float(survey_cells.sum()), then_m3, float(now_cells.sum()), density,
        per_block * g.cell_m, (g.origin_x_m, g.origin_y_m),
        _block_sums(survey_cells - now_cells, cells, per_block),
        np.where(cells, (survey_cells - now_cells) / area, np.nan), g.cell_m, rebase)

"""The model rebased on a survey: under the pile's ``survey_rebase`` policy
(``PileDeclared.survey_rebase``), the fold makes the model follow each ``survey`` of the
pile at the survey's time (:func:`rebase_on_survey`).

In every surveyed cell whose column holds material, every band of the layer stack is
scaled about the ground so that the top is the survey's height
(:meth:`projector.layers.LayerStack.scaled`): each deposit keeps its share of the column,
and so its composition, and a deposit's tonnes follow its volume.  The height map takes
the survey's heights there, with the survey's stated accuracy (at least the scans' point
noise) as their standard deviation, so later scans are gated against the survey.
Surveyed cells the model holds as bare are left bare (there is no composition to
scale); those the survey shows above the ground by more than its accuracy are counted.
Before it, the open face is slid (:func:`projector.material_fit.close_face`) and the
journal of recent rises is cleared: the survey is the new baseline.

Each rebase is kept as a :class:`projector.state.RebaseRecord` in ``state.rebases`` (the
audit trail that ``stockpile audit survey`` prints).  Units: metres, m3, UTC ns.
"""

from __future__ import annotations

import numpy as np

from projector.heightmap import clear_evidence
from projector.material_fit import close_face
from projector.state import ProjectorState, RebaseRecord
from projector.surveys import survey_heights

__all__ = ["rebase_on_survey", "MIN_COLUMN_M"]

#: a column thinner than this (m) holds no material to scale
MIN_COLUMN_M = 1e-3


def rebase_on_survey(state: ProjectorState, event, msg) -> None:
    """Fold handler of ``survey``: rebase the model on ``msg`` (a ``Survey``) when it is of
    this pile and the pile's policy asks for it (:func:`projector.fold.apply` passes a
    survey on only then)."""
    pile = state.pile
    if (pile is None or not pile.survey_rebase or msg.pile_id != pile.pile_id
            or state.stack is None):
        return
    heights, counts = survey_heights(msg, pile.geometry)
    if state.open_face is not None:
        close_face(state)
    stack = state.stack
    ground, top = stack.ground(), stack.surface()
    column = top - ground
    surveyed = counts > 0
    scalable = surveyed & (column > MIN_COLUMN_M)
    accuracy = max(float(msg.accuracy_m), state.point_sd_m)
    bare_above = surveyed & ~scalable & (heights - ground > accuracy)
    factor = np.ones(pile.geometry.shape)
    factor[scalable] = np.clip(heights[scalable] - ground[scalable], 0.0, None) \
        / column[scalable]
    before = [stack.thickness(k) for k in range(1, stack.n_deposits + 1)]
    state.stack = stack.scaled(factor)
    area = pile.geometry.cell_area_m2
    changes = []
    for k, thick in enumerate(before, start=1):
        dv = float((state.stack.thickness(k) - thick)[scalable].sum() * area)
        if dv != 0.0:
            info = stack.info(k)
            changes.append((info.lot_id, info.pass_id, dv))
    grid = state.height.grid
    t = float(event.valid_time_ns)
    grid["elevation"][scalable] = state.stack.surface()[scalable]
    grid["variance"][scalable] = accuracy ** 2
    for name in ("x_offset_m", "y_offset_m"):
        grid[name][scalable] = 0.0
    for name in ("last_update_ns", "observed_ns"):
        grid[name][scalable] = t
    clear_evidence(grid, scalable)
    state.rises_journal.clear()
    state.rebases.append(RebaseRecord(
        msg.survey_id, int(event.valid_time_ns), int(scalable.sum()), int(bare_above.sum()),
        float(sum(dv for _lot, _pass, dv in changes)), tuple(changes)))
    state.count("surveys_rebased")

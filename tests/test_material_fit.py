"""Measurements overrule the prior (projector.material_fit): a cut's face slide fitted to
the heights seen after it, a face the scans see standing kept standing by the fold, and a
delayed failure seen later moved into the toe with its composition, mass conserved.

Faces are built by hand: a bank of one or two deposits with a vertical face, slid by the
same relaxation at a known angle for the "true" surface; random noise comes from seeded
generators whose seeds are printed (shown by pytest on failure or with -s).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import projector.fold as F
from projector import follow, material_fit, slump
from projector.grid import GridGeometry
from projector.heightmap import CellObservations, HeightMap, fuse
from projector.layers import DepositInfo, LayerStack

from schemas.times import NS_PER_S as NS  # noqa: E402

SD = 0.05            # point sd (m)
CELL = 0.25          # m
REPOSE = 37.0        # deg
HEIGHT = 3.0         # the bank's height (m)


def _bank(nx: int = 12, ny: int = 48, face_iy: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """A bank ``HEIGHT`` high for iy >= face_iy, the ground (0 m) before it: (top, base)."""
    top = np.zeros((nx, ny))
    top[:, face_iy:] = HEIGHT
    return top, np.zeros((nx, ny))


@pytest.mark.parametrize("true_deg", [90.0, 55.0, REPOSE])
@pytest.mark.parametrize("seed", [11, 12])
def test_the_fit_recovers_the_angle_a_face_slid_to(true_deg, seed):
    """A face standing, partly slid (55 deg) and fully slid (repose), seen with 1 cm of
    noise on every cell: the fit finds the angle within the refined step (1.25 deg)."""
    print(f"seed={seed}, true angle {true_deg} deg")
    rng = np.random.default_rng(seed)
    top, base = _bank()
    tan = math.inf if true_deg >= 90 else math.tan(math.radians(true_deg))
    truth = top if not math.isfinite(tan) else slump.relax_surface(top, base, CELL, tan)
    seen = truth + rng.normal(0.0, 0.01, truth.shape)
    fit = material_fit.fit_slide_angle(top, base, seen, CELL, REPOSE, change_m=0.02)
    assert fit.cells_seen >= material_fit.MIN_FIT_CELLS and fit.cells_predicted == 0
    assert abs(fit.angle_deg - true_deg) <= 1.25 + 1e-9, fit.angle_deg
    # the residual at the angle found is the noise's, far below the worst angle's
    assert fit.sse_m2[fit.angle_deg] < 0.1 * max(fit.sse_m2.values())


def test_the_fit_on_part_of_the_face_and_too_few_cells():
    """Seen on a third of its cells (the rest never seen) the angle is still found, the
    cells left counted as predicted; seen on fewer than MIN_FIT_CELLS: no fit (NaN)."""
    top, base = _bank()
    truth = slump.relax_surface(top, base, CELL, math.tan(math.radians(60.0)))
    seen = np.full(top.shape, np.nan)
    seen[:4] = truth[:4]
    fit = material_fit.fit_slide_angle(top, base, seen, CELL, REPOSE, change_m=0.02)
    assert abs(fit.angle_deg - 60.0) <= 1.25
    assert fit.cells_predicted > fit.cells_seen > 0
    few = np.full(top.shape, np.nan)
    face = np.argwhere(np.abs(slump.relax_surface(top, base, CELL, math.tan(
        math.radians(REPOSE))) - top) > 0.02)[:material_fit.MIN_FIT_CELLS - 1]
    few[tuple(face.T)] = truth[tuple(face.T)]
    fit = material_fit.fit_slide_angle(top, base, few, CELL, REPOSE, change_m=0.02)
    assert math.isnan(fit.angle_deg) and fit.cells_seen == material_fit.MIN_FIT_CELLS - 1
    with pytest.raises(ValueError, match="repose_deg must be in"):
        material_fit.fit_slide_angle(top, base, seen, CELL, 95.0, change_m=0.02)


def _obs(g: GridGeometry, z: np.ndarray, count: int = 5) -> CellObservations:
    n = g.nx * g.ny
    ix, iy = np.divmod(np.arange(n), g.ny)
    return CellObservations(ix, iy, np.asarray(z, float).ravel().copy(), np.zeros(n),
                            np.full(n, count, dtype=np.int64))


def _state(nx: int = 12, ny: int = 64) -> F.ProjectorState:
    """A bank ``HEIGHT`` high over the whole grid, two deposits (lower 2 m, upper 1 m),
    seen settled for 10 looks (t = 0..9 s)."""
    g = GridGeometry(0.0, 0.0, CELL, nx, ny)
    state = F.initial_state(F.FoldConfig("P1", repose_deg=REPOSE, complete_unseen=False,
                                         fill_gap_cells=0))
    state.pile = F.PileInfo("P1", g, 0.0, 1.0, 2.0)
    state.point_sd_m, state.margin_m, state.process_sd_m = SD, 0.4 * SD, 0.2 * SD
    hm = HeightMap.empty(g)
    for k in range(10):
        hm, _ = fuse(hm, _obs(g, np.full(g.shape, HEIGHT)), k * NS, SD)
    state.height = hm
    stack = LayerStack.empty(g, 0.0).open_deposit(DepositInfo(1, "P0", "L0", 0))
    stack, _ = stack.raise_to(np.full(g.shape, 2.0), 0)
    stack = stack.open_deposit(DepositInfo(2, "P1", "L1", NS))
    state.stack, _ = stack.raise_to(np.full(g.shape, HEIGHT), NS)
    return state


def _cut(state: F.ProjectorState, cut_id: str, y_m: float, start_s: float,
         end_s: float, floor_m: float = 0.0) -> tuple[F.CutRecord, np.ndarray]:
    """A cut taking everything at y < ``y_m`` down to ``floor_m``, as the fold applies
    one: the face before it closes, the envelope clamps, the new face opens."""
    g = state.pile.geometry
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    floor = np.full(g.shape, np.inf)
    floor[:, y < y_m] = floor_m
    material_fit.close_face(state, floor, int(start_s * NS))
    record = F.CutRecord(cut_id, "B1", "bwr1", int(start_s * NS), int(end_s * NS), 0.0)
    F._clamp_to_floor(state, record, floor, None)
    state.cuts.append(record)
    return record, floor


def _see(state: F.ProjectorState, surface: np.ndarray, t_s: float) -> None:
    """The scans see ``surface`` (m, every cell, 5 points each: a strong look) at t_s,
    and the stack follows the rises as after a batch."""
    state.height, _ = fuse(state.height, _obs(state.pile.geometry, surface), int(t_s * NS),
                           SD, change_count=1, process_sd_m=state.process_sd_m)
    follow.follow_height(state, int(t_s * NS), drops=False)


def test_a_face_the_scans_see_standing_stays_standing_and_the_next_cut_is_exact():
    """The first cut leaves a vertical face; the scans see it standing (the prior slides
    it to repose). The face stays as cut, nothing is added as flagged material, and the
    second cut, taking 1 m more of the bank, takes exactly the standing bank's slice."""
    state = _state()
    g = state.pile.geometry
    first, _ = _cut(state, "C1", 2.0, 20, 30)
    assert state.open_face is not None
    # the height map holds the prediction: the face slid to repose
    stood = state.stack.surface().copy()
    assert np.any(state.height.elevation < stood - 0.5)
    for t in (40, 45, 50):
        _see(state, stood, t)
    assert state.stack.n_deposits == 2, "no flagged deposit for the standing face"
    np.testing.assert_array_equal(state.stack.surface(), stood)
    second, _ = _cut(state, "C2", 3.0, 60, 70)
    assert first.slide_angle_deg >= 85.0 and first.face_cells_seen > 0
    assert first.slumped_m3 < 0.01
    true_m3 = HEIGHT * 1.0 * g.nx * g.cell_m          # the bank's 1 m slice
    assert math.isclose(second.predicted_m3, true_m3, rel_tol=1e-6), second.predicted_m3
    assert state.slide_fits[0][0] == "C1" and state.slide_fits[0][1] >= 85.0
    estimate = material_fit.material_estimate(state)
    assert estimate["cuts_fitted"] == 1 and estimate["cuts_stood"] == 1
    # the prior of the second face is the fitted one: its prediction stands too
    assert state.open_face.tan_prior > math.tan(math.radians(80.0))


def test_a_face_the_scans_see_slid_slides_to_repose_before_the_next_cut():
    """The same face seen slid to repose: the stack slides it (mass conserved) and the
    next cut takes the slid bank's material, as the prior had it."""
    state = _state()
    _cut(state, "C1", 2.0, 20, 30)
    before_m3 = state.stack.total_volume_m3()
    top = state.stack.surface()
    slid = slump.relax_surface(top, state.stack.ground(), CELL, math.tan(math.radians(REPOSE)))
    for t in (40, 45, 50):
        _see(state, slid, t)
    second, _ = _cut(state, "C2", 3.0, 60, 70)
    first = state.cuts[0]
    assert abs(first.slide_angle_deg - REPOSE) <= 1.25
    assert first.slumped_m3 > 0.5
    # the slide conserved the volume: what the second cut took is all that left
    assert math.isclose(state.stack.total_volume_m3() + second.predicted_m3, before_m3,
                        rel_tol=1e-9)


@pytest.mark.parametrize("seed", [5])
def test_a_delayed_failure_moves_the_face_into_the_toe_conserving_mass(seed):
    """A face closed standing fails later: the scans see its top drop away from the latest
    cut. The stack slides it to repose when the drop is seen: every deposit keeps its
    volume, the toe rises, the failure is recorded at the time it was seen."""
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    state = _state(ny=96)
    _cut(state, "C1", 2.0, 20, 30)
    stood = state.stack.surface().copy()
    for t in (40, 45, 50):
        _see(state, stood, t)
    # a second cut far along the bank's other end (y > 22 m) closes the first face standing
    g = state.pile.geometry
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    floor = np.full(g.shape, np.inf)
    floor[:, y > 22.0] = 0.0
    material_fit.close_face(state, floor, 60 * NS)
    record = F.CutRecord("C2", "B1", "bwr1", 60 * NS, 70 * NS, 0.0)
    F._clamp_to_floor(state, record, floor, None)
    state.cuts.append(record)
    assert state.cuts[0].slide_angle_deg >= 85.0
    volumes = [state.stack.volume_m3(k) for k in (1, 2)]
    total = state.stack.total_volume_m3()
    # the first face fails to repose at t = 80 s; the scans see it (noise 5 mm)
    top = state.stack.surface()
    failed = top.copy()
    first = (slice(None), slice(0, int(12.0 / CELL)))
    failed[first] = slump.relax_surface(top[first], state.stack.ground()[first], CELL,
                                        math.tan(math.radians(REPOSE)))
    seen = failed + rng.normal(0.0, 0.005, failed.shape)
    _see(state, seen, 80)
    follow.follow_height(state, 80 * NS)
    assert len(state.delayed_failures) == 1
    t_ns, moved_m3 = state.delayed_failures[0]
    assert t_ns == 80 * NS and moved_m3 > 1.0
    for k, v in zip((1, 2), volumes):
        assert math.isclose(state.stack.volume_m3(k), v, rel_tol=1e-9), k
    # the toe's rise, seen before the crest's drop and followed as flagged material, was
    # the failure's own material: no more than the noise's stays flagged
    assert state.stack.total_volume_m3() - total < 0.002 * total
    assert state.counters["failure_flagged_mm3"] > 1000
    # the toe (the first hole, y < 2 m) rose; the face's crest fell
    hole = y < 2.0
    assert state.stack.surface()[:, hole].sum() > top[:, hole].sum() + 1.0
    # a second look at the same surface finds nothing more to fail
    follow.follow_height(state, 90 * NS)
    assert len(state.delayed_failures) == 1


def test_a_drop_below_any_slide_is_the_cut_s_while_its_face_is_open():
    """While the face is open, the scans see part of the hole 0.3 m below the envelope's
    floor (the wheel dug deeper): no slide explains that, so the drop is followed and
    charged to the cut; the face's own cells (its crest seen slid) are not."""
    state = _state()
    g = state.pile.geometry
    record, _ = _cut(state, "C1", 2.0, 20, 30, floor_m=0.5)
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    top = state.stack.surface()
    seen = slump.relax_surface(top, state.stack.ground(), CELL, math.tan(math.radians(REPOSE)))
    deeper = y < 0.5
    seen[:, deeper] = 0.2
    for t in (40, 45, 50):
        _see(state, seen, t)
    follow.follow_height(state, 50 * NS)
    want = 0.3 * g.cell_area_m2 * g.nx * int(deeper.sum())
    assert math.isclose(record.residual_m3, want, rel_tol=1e-9), record.residual_m3
    # the crest, seen slid, still stands in the stack until the face closes
    crest = (y > 2.0) & (y < 3.0)
    np.testing.assert_array_equal(state.stack.surface()[:, crest], top[:, crest])

"""The fold's guards around real change: refreshing cells a stacking pass reached since they
were last seen, charging a cut only with the drops seen in its footprint, undoing what
rose in a footprint while the cut dug, lifting never-seen and stale flanks to the repose
cone, and dating a pass's material by when the stacker crossed it.

States are built by hand (a declared pile, a settled height map, pass and cut records) so
each test isolates one rule; the numbers checked come from the Kalman formulas and the
geometry, not from the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import projector.fold as F
from projector import attribution, completion, cuts, follow, scans, slump
from projector.grid import GridGeometry
from projector.heightmap import CellObservations, HeightMap, fuse
from projector.layers import DepositInfo, LayerStack

from schemas.times import NS_PER_S as NS  # noqa: E402
SD = 0.05          # point sd (m)


def _state(config: F.FoldConfig, nx: int = 8, ny: int = 80, cell: float = 0.25,
           z0: float = 1.0) -> F.ProjectorState:
    """A pile 2 m x 20 m whose surface stood at ``z0`` for 10 looks (t = 0..9 s)."""
    g = GridGeometry(0.0, 0.0, cell, nx, ny)
    state = F.initial_state(config)
    state.pile = F.PileInfo("P1", g, 0.0, 1.0, 2.0)
    state.point_sd_m = SD
    state.margin_m = 0.4 * SD
    state.process_sd_m = 0.2 * SD
    hm = HeightMap.empty(g)
    for k in range(10):
        hm, _ = fuse(hm, _obs(g, z0), k * NS, SD)
    state.height = hm
    stack = LayerStack.empty(g, 0.0).open_deposit(DepositInfo(1, "P0", "L0", 0))
    state.stack, _ = stack.raise_to(np.full(g.shape, z0), 0)
    return state


def _never_seen(state: F.ProjectorState, columns: np.ndarray) -> None:
    """Make the height map's cells in these y columns (bool, (ny,)) never seen."""
    for name in ("elevation", "variance", "last_update_ns"):
        state.height.grid[name][:, columns] = np.nan


def _obs(g: GridGeometry, z: float, count: int = 1) -> CellObservations:
    n = g.nx * g.ny
    ix, iy = np.divmod(np.arange(n), g.ny)
    return CellObservations(ix, iy, np.full(n, float(z)), np.zeros(n),
                            np.full(n, count, dtype=np.int64))


def test_a_cell_a_pass_crossed_takes_the_new_layer_at_the_next_look():
    # a settled cell (10 looks) sees a layer 6 cm higher once, one point: inside the
    # 3-sigma gate, so without the refresh it is a Kalman step of gain P / (P + R)
    rise = 0.06
    results = {}
    for refresh in (False, True):
        state = _state(F.FoldConfig("P1", refresh_crossed=refresh, refresh_reach=False))
        g = state.pile.geometry
        state.passes["A"] = F.PassRecord("A", "L1", "stk1", 20 * NS, 2, 30 * NS,
                                         start_y_m=0.0, end_y_m=g.length_y_m)
        p_before = float(state.height.variance[0, 0])
        obs = _obs(g, 1.0 + rise)
        seen = state.height.grid["last_update_ns"].copy()
        if refresh:
            scans.refresh_crossed(state, obs, 40 * NS, seen)
        p_prior = float(state.height.variance[0, 0]) + state.process_sd_m ** 2
        gain = p_prior / (p_prior + SD ** 2)
        assert rise < 3.0 * math.sqrt(p_prior + SD ** 2)   # inside the 3-sigma gate
        state.height, _ = fuse(state.height, obs, 40 * NS, SD,
                               process_sd_m=state.process_sd_m, inplace=True)
        moved = float(state.height.elevation[0, 0]) - 1.0
        assert math.isclose(moved, gain * rise, rel_tol=1e-9)
        results[refresh] = moved
        if refresh:
            assert math.isclose(float(state.height.variance[0, 0]),
                                (1 - gain) * p_prior, rel_tol=1e-9)
            assert p_before < (3 * SD) ** 2 <= p_prior
    assert results[False] < 0.5 * rise           # the old level held most of it
    assert results[True] > 0.9 * rise            # the layer taken at the next look


def test_refresh_only_where_a_pass_came_since_the_last_look():
    state = _state(F.FoldConfig("P1", refresh_reach=False))
    g = state.pile.geometry
    # a pass that ended before the last look changes nothing; one over y in [0, 5] m
    # after it refreshes the cells there only
    state.passes["old"] = F.PassRecord("old", "L1", "stk1", 0, 2, 5 * NS,
                                       start_y_m=0.0, end_y_m=g.length_y_m)
    state.passes["new"] = F.PassRecord("new", "L1", "stk1", 20 * NS, 3, 30 * NS,
                                       start_y_m=0.0, end_y_m=5.0)
    before = state.height.variance.copy()
    seen = state.height.grid["last_update_ns"].copy()
    scans.refresh_crossed(state, _obs(g, 1.0), 40 * NS, seen)
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    after = state.height.variance
    reached = y <= 5.0
    assert np.all(after[:, reached] >= (3 * SD) ** 2 - 1e-15)
    # beyond the pass's end the stacker is taken to have stood at its end: not crossed
    assert np.array_equal(after[:, ~reached], before[:, ~reached])
    assert state.counters["cells_refreshed"] == g.nx * int(reached.sum())


def test_refresh_reach_is_the_height_over_tan_repose():
    z0 = 3.0
    state = _state(F.FoldConfig("P1", repose_deg=35.0), z0=z0)
    g = state.pile.geometry
    state.passes["new"] = F.PassRecord("new", "L1", "stk1", 20 * NS, 2, 30 * NS,
                                       start_y_m=0.0, end_y_m=5.0)
    seen = state.height.grid["last_update_ns"].copy()
    scans.refresh_crossed(state, _obs(g, z0), 40 * NS, seen)
    reach = z0 / math.tan(math.radians(35.0))     # 4.28 m beyond the pass's end
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    refreshed = state.height.variance[0] >= (3 * SD) ** 2 - 1e-15
    assert np.array_equal(refreshed, y <= 5.0 + reach)


@pytest.mark.parametrize("follow_far", [False, True])
def test_only_a_drop_in_the_cut_s_footprint_is_the_cut_s(follow_far):
    config = F.FoldConfig("P1", complete_unseen=False, fill_gap_cells=0, repose_deg=35.0,
                          follow_far_drops=follow_far)
    state = _state(config, z0=1.0)
    g = state.pile.geometry
    # the cut took the cells y < 1 m down to 0.5 m
    floor = np.full(g.shape, np.inf)
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    floor[:, y < 1.0] = 0.5
    state.stack, removal = state.stack.clamp(floor)
    cut = F.CutRecord("C1", "B1", "bwr1", 40 * NS, 50 * NS, 0.0, [removal],
                      predicted_m3=removal.volume_m3)
    state.cuts.append(cut)
    # a strip at y in [18, 19) m holds no material
    bare = (y >= 18.0) & (y < 19.0)
    state.stack, _ = state.stack.clamp(np.where(bare[None, :], 0.0, np.inf)
                                       * np.ones(g.shape))
    # then the scans see the surface 0.3 m lower in the footprint's half y in [0.5, 1) m
    # (the wheel dug deeper than its envelope), beside it at y in [1.5, 2) m (the face
    # slid into the hole), far off at y in [15, 16) m, and the bare strip's ground
    # too (a cone under never-seen cells can reach below it)
    before = state.stack.surface().copy()
    elevation = before.copy()
    inside = (y >= 0.5) & (y < 1.0)
    beside = (y >= 1.5) & (y < 2.0)
    far = (y >= 15.0) & (y < 16.0)
    elevation[:, inside | beside | far | bare] -= 0.3
    state.height.grid["elevation"][:] = elevation
    state.height.grid["variance"][:] = SD ** 2 / 10
    volume = 0.3 * g.cell_area_m2 * g.nx
    follow.follow_height(state, 60 * NS)
    # in the footprint (grown by a cell) the measurement wins and the cut is charged
    assert math.isclose(cut.residual_m3, volume * inside.sum(), rel_tol=1e-9)
    np.testing.assert_allclose(state.stack.surface()[:, inside], elevation[:, inside])
    away = beside | far
    if follow_far:
        # away from it the measurement wins too, as an unexplained loss
        assert math.isclose(state.flagged_loss_m3, volume * away.sum(), rel_tol=1e-9)
        assert state.counters["unexplained_loss_mm3"] == round(volume * away.sum() * 1e3)
        np.testing.assert_allclose(state.stack.surface()[:, away], elevation[:, away])
    else:
        # away from it the stack keeps its own surface; the gap is reported
        assert state.flagged_loss_m3 == 0.0 and "unexplained_loss_mm3" not in state.counters
        np.testing.assert_array_equal(state.stack.surface()[:, away], before[:, away])
        # the gap reported is what the stack holds above the measurement: none below the
        # ground of the bare strip
        assert state.counters["far_drops_mm3"] == round(volume * away.sum() * 1e3)


def test_a_never_seen_flank_rises_to_the_cone_beyond_the_fixed_margin_only():
    # the pile stands 1 m high and was seen up to y = 15 m; beyond, nothing was ever seen
    # and the stack holds the flank 5 cm (more than margin_m, 2 cm, less than one point's
    # 3 sd + margin_m, 17 cm) below the repose cone of the last seen row; a strip further
    # out is 1 cm below it (within the margin)
    config = F.FoldConfig("P1", fill_gap_cells=0, repose_deg=35.0)
    state = _state(config, z0=1.0)
    g = state.pile.geometry
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    hidden = y > 15.0
    _never_seen(state, hidden)
    last_seen_y = y[~hidden].max()
    tan = math.tan(math.radians(35.0))
    cone = 1.0 - tan * (y - last_seen_y)      # exact along the grid's axis
    low = hidden & (y < 16.0)                  # 5 cm below
    slight = hidden & (y >= 16.0) & (y < 16.6)   # 1 cm below
    target = np.where(low, cone - 0.05, np.where(slight, cone - 0.01, np.inf))
    state.stack, _ = state.stack.clamp(np.broadcast_to(target, g.shape))
    before = state.stack.surface().copy()
    completion.complete_unseen(state, 100 * NS)
    top = state.stack.surface()
    np.testing.assert_allclose(top[:, low], np.broadcast_to(cone[low], (g.nx, low.sum())),
                               atol=1e-9)
    assert np.array_equal(top[:, slight], before[:, slight])
    assert state.counters["cells_completed"] == g.nx * int(low.sum())


def test_a_cut_undoes_the_rises_its_own_digging_caused_in_its_footprint():
    config = F.FoldConfig("P1", complete_unseen=False, fill_gap_cells=0, repose_deg=35.0)
    state = _state(config, z0=1.0)
    g = state.pile.geometry
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    footprint = np.zeros(g.shape, bool)
    footprint[:, y < 5.0] = True
    early = (y >= 2.0) & (y < 3.0)     # rose before the cut started (t = 30 s)
    during = (y >= 4.0) & (y < 6.0)    # rose while it dug (t = 45 s), half in, half out
    for t_s, cells, rise in ((30, early, 0.3), (45, during, 0.4)):
        elevation = state.height.grid["elevation"]
        elevation[:, cells] = 1.0 + rise
        state.height.grid["variance"][:, cells] = SD ** 2 / 10
        follow.follow_height(state, t_s * NS, drops=False)
    np.testing.assert_allclose(state.stack.surface()[:, early], 1.3)
    np.testing.assert_allclose(state.stack.surface()[:, during], 1.4)
    undone = cuts.undo_digging_rises(state, 40 * NS, footprint)
    top = state.stack.surface()
    inside = during & (y < 5.0)
    np.testing.assert_allclose(top[:, inside], 1.0)          # back to where it stood
    np.testing.assert_allclose(top[:, during & ~inside], 1.4)  # outside the footprint
    np.testing.assert_allclose(top[:, early], 1.3)           # before the cut began
    assert math.isclose(undone, 0.4 * g.cell_area_m2 * g.nx * inside.sum(), rel_tol=1e-9)
    # the journal forgets what is older than dig_journal_s
    cuts.journal_rises(state, int((45 + config.dig_journal_s + 1) * NS),
                     np.zeros(0, np.intp), state.stack.surface())
    assert state.rises_journal == []


def test_a_rise_the_map_first_saw_while_the_cut_dug_stays_if_no_look_preceded_it():
    # a pass crossed the whole pile at 20-60 s; then, while a cut dug (from 100 s), the
    # map saw rises in its footprint: where it had looked since the pass (at 0-9 s it
    # had, but also at 70 s: seen after the crossing) the rise is the walls read high
    # and is undone; where it had not looked since the pass crossed (the pile end's toe,
    # first seen from the reclaimer) it is material that was there, and it stays
    config = F.FoldConfig("P1", complete_unseen=False, fill_gap_cells=0, repose_deg=35.0)
    state = _state(config, z0=1.0)
    g = state.pile.geometry
    state.passes["B"] = F.PassRecord("B", "L1", "stk1", 20 * NS, 1, 60 * NS,
                                     start_y_m=0.0, end_y_m=20.0)
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    looked = (y >= 2.0) & (y < 4.0)
    first = (y >= 4.0) & (y < 6.0)
    sighted = state.height.grid["last_update_ns"].copy()      # 9 s everywhere
    sighted[:, looked] = 70 * NS
    sighted[:, first & (y < 5.0)] = np.nan                    # never seen
    elevation = state.height.grid["elevation"]
    elevation[:, looked | first] = 1.4
    state.height.grid["variance"][:, looked | first] = SD ** 2 / 10
    follow.follow_height(state, 110 * NS, drops=False, sighted_before_ns=sighted)
    np.testing.assert_allclose(state.stack.surface()[:, looked | first], 1.4)
    footprint = np.zeros(g.shape, bool)
    footprint[:, y < 8.0] = True
    undone = cuts.undo_digging_rises(state, 100 * NS, footprint)
    top = state.stack.surface()
    np.testing.assert_allclose(top[:, looked], 1.0)     # seen after the pass: the walls
    np.testing.assert_allclose(top[:, first], 1.4)      # never seen, or not since 9 s
    assert math.isclose(undone, 0.4 * g.cell_area_m2 * g.nx * looked.sum(), rel_tol=1e-9)


def test_a_never_seen_cell_s_cone_is_not_the_maximum_of_the_seen_heights_noise():
    # a flank at repose (35 deg) falling along y was seen up to y = 12 m with 1 cm of
    # noise in its fused heights; beyond, nothing was seen and the stack is empty.
    # Every seen cell up the flank gives a hidden cell the same cone height, give or
    # take its noise: the cone from the raw heights is their maximum, the one from
    # heights fitted over 5 x 5 cells is not.
    seed = 5
    print("seed", seed)
    rng = np.random.default_rng(seed)
    tan = math.tan(math.radians(35.0))
    noise_sd = 0.01
    lifted = {}
    for cells in (1, 5):
        config = F.FoldConfig("P1", fill_gap_cells=0, repose_deg=35.0,
                              cone_smooth_cells=cells)
        state = _state(config, nx=24, ny=80, z0=0.0)
        g = state.pile.geometry
        y = (np.arange(g.ny) + 0.5) * g.cell_m
        hidden = y > 12.0
        flank = tan * (g.length_y_m - y)                 # exact along the grid's axis
        grid = state.height.grid
        grid["elevation"][:] = flank[None, :] + rng.normal(0.0, noise_sd, g.shape)
        grid["variance"][:] = noise_sd ** 2
        _never_seen(state, hidden)
        completion.complete_unseen(state, 100 * NS)
        band = hidden & (y < 14.0)                       # the first 8 hidden rows
        lifted[cells] = float(np.mean(state.stack.surface()[:, band] - flank[band]))
    # the raw heights' maximum stands about 2.2 sd high (seeds 0-4: 2.1-2.3); the fitted
    # heights' noise is a fifth of theirs, or more beside the last seen row, and their
    # maximum stands about half an sd high (0.44-0.57)
    assert lifted[1] > 1.5 * noise_sd, lifted
    assert -0.2 * noise_sd < lifted[5] < 0.8 * noise_sd, lifted
    assert lifted[5] < 0.35 * lifted[1], lifted


def test_a_stale_seen_flank_rises_to_the_cone_beyond_the_fixed_margin_only():
    # a flank at repose, seen 10 times; a pass crossed it since.  A strip of it was last
    # seen 5 cm lower (before the pass's layer) and the stack holds it there: the cone of
    # the flank above says it is at least that much higher.  Its fused sd (1.6 cm) says
    # how well the old level was known, not whether it still holds; its margin is the
    # fixed part (2 cm), not 3 sd + 2 cm = 6.7 cm.
    config = F.FoldConfig("P1", fill_gap_cells=0, repose_deg=35.0)
    state = _state(config, z0=0.0)
    g = state.pile.geometry
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    tan = math.tan(math.radians(35.0))
    flank = np.broadcast_to(tan * (g.length_y_m - y), g.shape)
    strip = (y >= 8.0) & (y < 9.0)
    old = np.where(strip, flank - 0.05, flank)
    state.height.grid["elevation"][:] = old
    fused_sd = math.sqrt(float(state.height.variance[0, 0]))
    assert 3 * fused_sd + state.margin_m > 0.05 > state.margin_m
    state.stack = state.stack.open_deposit(DepositInfo(2, "A", "L1", 20 * NS))
    state.stack, _ = state.stack.raise_to(old, 20 * NS)
    state.passes["A"] = F.PassRecord("A", "L1", "stk1", 20 * NS, 2, 30 * NS,
                                     start_y_m=0.0, end_y_m=g.length_y_m)
    before = state.stack.surface().copy()
    completion.complete_unseen(state, 100 * NS)
    top = state.stack.surface()
    np.testing.assert_allclose(top[:, strip], flank[:, strip], atol=1e-9)
    np.testing.assert_array_equal(top[:, ~strip], before[:, ~strip])
    assert state.counters["cells_completed"] == g.nx * int(strip.sum())


def test_a_completed_cell_s_later_rise_goes_to_the_passes_after_its_completion():
    # a flank at repose seen up to y = 12 m; beyond, never seen.  Pass A lays the pile,
    # the completion at t = 40 s lifts the hidden cells to the cone (A's); pass B lays
    # 10 cm more and the completion at t = 70 s lifts them 10 cm further: that is B's
    # alone.  Counted from "never seen", A and B would share it (5 cm each), and the
    # outer layer's material would go to the one under it.
    config = F.FoldConfig("P1", fill_gap_cells=0, repose_deg=35.0)
    state = _state(config, z0=0.0)
    g = state.pile.geometry
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    hidden = y > 12.0
    far = y > 12.5          # beyond the cells that take their seen neighbours' time
    tan = math.tan(math.radians(35.0))
    flank = np.broadcast_to(tan * (g.length_y_m - y), g.shape)
    grid = state.height.grid
    for k, (pass_id, t0_s, rise_m) in enumerate((("A", 20, 0.0), ("B", 50, 0.1))):
        state.stack = state.stack.open_deposit(DepositInfo(k + 2, pass_id, "L1", t0_s * NS))
        state.passes[pass_id] = F.PassRecord(pass_id, "L1", "stk1", t0_s * NS, k + 2,
                                             (t0_s + 10) * NS, start_y_m=0.0,
                                             end_y_m=g.length_y_m)
        # the scanner saw the seen part after the pass
        grid["elevation"][:] = flank + rise_m
        grid["last_update_ns"][:] = (t0_s + 15) * NS
        _never_seen(state, hidden)
        state.stack, _ = state.stack.raise_to(np.where(hidden, np.nan, flank + rise_m),
                                              (t0_s + 15) * NS)
        completion.complete_unseen(state, (t0_s + 20) * NS)
        if pass_id == "A":
            np.testing.assert_allclose(state.stack.surface()[:, far], flank[:, far], atol=1e-9)
            a_m = state.stack.thickness(2)[:, far].copy()
            np.testing.assert_allclose(a_m, flank[:, far] - 0.0, atol=1e-9)
    np.testing.assert_allclose(state.stack.surface()[:, far], flank[:, far] + 0.1, atol=1e-9)
    np.testing.assert_allclose(state.stack.thickness(3)[:, far], 0.1, atol=1e-9)
    np.testing.assert_array_equal(state.stack.thickness(2)[:, far], a_m)
    np.testing.assert_array_equal(state.completed_ns[:, hidden], 70 * NS)


def test_a_pass_layer_seen_late_is_dated_when_the_stacker_crossed_it():
    # the grade of a lot is looked up by deposition time: material of pass B seen at 90 s
    # (the scanner trails the stacker) was laid when the stacker passed over it
    state = _state(F.FoldConfig("P1"))
    g = state.pile.geometry                      # 20 m along y, 0.25 m cells
    state.stack = state.stack.open_deposit(DepositInfo(2, "B", "L1", 20 * NS))
    state.passes["B"] = F.PassRecord("B", "L1", "stk1", 20 * NS, 2, 60 * NS,
                                     start_y_m=20.0, end_y_m=0.0)
    state.stack, _ = state.stack.raise_to(np.full(g.shape, 1.3), attribution.deposition_ns(state, 90 * NS))
    got = state.stack.deposition_time_ns(2)
    for iy in (0, 39, 79):
        y_m = (iy + 0.5) * g.cell_m
        # the stacker ran from y = 20 m at 20 s to y = 0 at 60 s: 2 s per metre
        want_ns = 20 * NS + (20.0 - y_m) * 2 * NS
        assert np.all(np.abs(got[:, iy] - want_ns) <= 2048), (iy, got[0, iy], want_ns)


def test_a_deposition_time_is_never_after_the_rise_was_seen_nor_outside_the_pass():
    state = _state(F.FoldConfig("P1"))
    g = state.pile.geometry
    state.stack = state.stack.open_deposit(DepositInfo(2, "B", "L1", 20 * NS))
    # still running, none ended before it: the run is assumed to end now (30 s), so
    # y = 0 is crossed at 30 s and y = 20 m at 20 s
    state.passes["B"] = F.PassRecord("B", "L1", "stk1", 20 * NS, 2, None,
                                     start_y_m=20.0, end_y_m=0.0)
    times = np.asarray(attribution.deposition_ns(state, 30 * NS))
    assert times.shape == g.shape
    assert times.max() <= 30 * NS and times.min() >= 20 * NS
    assert times[0, -1] < times[0, 0]            # the far end (y = 20 m) was crossed first
    # a pass that declared no rail positions: the time seen, clipped to the pass
    state.passes["B"] = F.PassRecord("B", "L1", "stk1", 20 * NS, 2, 60 * NS)
    assert attribution.deposition_ns(state, 90 * NS) == 60 * NS
    assert attribution.deposition_ns(state, 40 * NS) == 40 * NS
    # material outside any pass (a flagged deposit): when it was seen
    state.stack = state.stack.open_deposit(DepositInfo(3, "", "", 70 * NS, flagged=True))
    assert attribution.deposition_ns(state, 95 * NS) == 95 * NS


def test_a_layer_is_dated_before_the_stacker_crossed_it_by_the_poured_cone_s_front():
    # a ridge (crest at x = 0.875 m) takes a 0.3 m layer of pass B (20 m in 40 s from
    # y = 20 m): the map has seen it, the stack not yet.  On the crest the cone's front
    # arrives h = 0.3 / tan(35 deg) ahead of the boom and the cell fills as the boom
    # closes in: on average h / 2 ahead, h / 2 / (0.5 m/s) before the crossing
    state = _state(F.FoldConfig("P1", repose_deg=35.0))
    g = state.pile.geometry
    x = (np.arange(g.nx) + 0.5) * g.cell_m
    ridge = 1.0 - 0.5 * np.abs(x - x[3])[:, None] * np.ones((1, g.ny))
    stack = LayerStack.empty(g, 0.0).open_deposit(DepositInfo(1, "A", "L0", 0))
    stack, _ = stack.raise_to(ridge, 0)
    state.stack = stack.open_deposit(DepositInfo(2, "B", "L1", 20 * NS))
    state.passes["B"] = F.PassRecord("B", "L1", "stk1", 20 * NS, 2, 60 * NS,
                                     start_y_m=20.0, end_y_m=0.0)
    state.height.grid["elevation"][:] = ridge + 0.3
    times = np.asarray(attribution.deposition_ns(state, 90 * NS))
    tan = math.tan(math.radians(35.0))
    for iy in (0, 39, 79):
        crossing_ns = 20 * NS + (20.0 - (iy + 0.5) * g.cell_m) * 2 * NS
        want_ns = max(crossing_ns - 0.3 / tan / 2 / 0.5 * NS, 20 * NS)
        assert abs(times[3, iy] - want_ns) <= 2048, (iy, times[3, iy], want_ns)
        # down the flank the front comes earlier still, never before the pass began
        assert np.all(times[[0, 7], iy] <= times[3, iy])
    assert times.min() >= 20 * NS and times.max() <= 60 * NS
    assert (times[[0, 7], 40] < times[3, 40]).all()


def _ridge_with_a_pass(pouring_tail: bool, look_after_s: float):
    """A ridge at repose (crest x = 2.625 m) on a 10 m x 10 m grid, and pass A (deposit 2)
    laying 0.3 m on it, its stacker running y = 0 -> 10 m from 20 s to 60 s (0.25 m/s).
    The scanner saw every row 30 s after the stacker crossed it, except a strip down the
    far flank (1.5-2.25 m from the crest), seen ``look_after_s`` after the crossing
    10 cm short of the layer's top.  Returns the state, the layer's top and the strip."""
    config = F.FoldConfig("P1", fill_gap_cells=0, repose_deg=35.0, pouring_tail=pouring_tail)
    state = _state(config, nx=40, ny=40, z0=0.0)
    g = state.pile.geometry
    tan = math.tan(math.radians(35.0))
    x = (np.arange(g.nx) + 0.5) * g.cell_m
    y = (np.arange(g.ny) + 0.5) * g.cell_m
    crest = x[10]
    below = np.broadcast_to(np.maximum(0.0, 2.5 - tan * np.abs(x - crest))[:, None], g.shape)
    layer_top = np.broadcast_to(np.maximum(0.0, 2.8 - tan * np.abs(x - crest))[:, None], g.shape)
    offset = (x - crest)[:, None] * np.ones((1, g.ny))
    strip = (offset >= 1.5) & (offset <= 2.25)
    crossed_ns = (20.0 + y / 0.25)[None, :] * NS * np.ones((g.nx, 1))
    grid = state.height.grid
    grid["elevation"][:] = np.where(strip, layer_top - 0.1, layer_top)
    grid["last_update_ns"][:] = crossed_ns + np.where(strip, look_after_s, 30.0) * NS
    stack = LayerStack.empty(g, 0.0).open_deposit(DepositInfo(1, "P0", "L0", 0))
    stack, _ = stack.raise_to(below, 0)
    stack = stack.open_deposit(DepositInfo(2, "A", "L1", 20 * NS))
    state.stack, _ = stack.raise_to(grid["elevation"], crossed_ns)
    state.passes["A"] = F.PassRecord("A", "L1", "stk1", 20 * NS, 2, 60 * NS,
                                     start_y_m=0.0, end_y_m=g.length_y_m)
    return state, layer_top, strip, crossed_ns


def test_a_flank_seen_while_the_pass_still_poured_on_it_is_completed_as_that_pass_s():
    # The far-flank strip lies 1.5-2.25 m from the crest under a 0.3 m layer: the poured
    # cone reaches it while the boom is within sqrt(h^2 + 2 h offset) >= 1.24 m of it
    # (h = 0.3 / tan 35 deg), 4.9 s of travel at 0.25 m/s.  Seen 2 s after the crossing
    # it was still filling; at the next pass's start it rises to the repose cone of the
    # seen flank above it (the layer's top), and the material is pass A's, dated when
    # its stacker crossed.  Without the rule the strip stays 10 cm short, and the next
    # pass's layer would take the rest.
    tan = math.tan(math.radians(35.0))
    h = 0.3 / tan
    assert math.sqrt(h * h + 2 * h * 1.5) / 0.25 > 2.0 + 1.0
    state, layer_top, strip, crossed_ns = _ridge_with_a_pass(True, 2.0)
    before = state.stack.surface().copy()
    a_before = state.stack.volume_m3(2)
    completion.complete_unseen(state, 100 * NS)
    top = state.stack.surface()
    np.testing.assert_allclose(top[strip], layer_top[strip], atol=1e-9)
    np.testing.assert_array_equal(top[~strip], before[~strip])
    area = state.pile.geometry.cell_area_m2
    assert math.isclose(state.stack.volume_m3(2) - a_before, 0.1 * strip.sum() * area,
                        rel_tol=1e-9)
    times = state.stack.deposition_time_ns(2)
    # dated when its stacker crossed, but for the rows within the cone's reach of the
    # run's end (y = 10 m), where fewer releases followed: earlier, by at most the front's
    # lead (attribution.crossing_dates)
    g = state.pile.geometry
    ahead = g.length_y_m - (np.arange(g.ny) + 0.5) * g.cell_m
    offset = np.broadcast_to((((np.arange(g.nx) + 0.5) - 10.5) * g.cell_m)[:, None], g.shape)
    reach = slump.pour_reach_m(np.full(g.shape, 0.1), offset, tan)
    lead_s = slump.pour_front_lead_m(np.full(g.shape, 0.1), offset, tan) / 0.25
    far = strip & (ahead[None, :] >= reach)
    near = strip & ~far
    assert far.any() and near.any()
    assert np.all(np.abs(times[far] - crossed_ns[far]) <= 2048)
    assert np.all(times[near] < crossed_ns[near] - 1e6)
    assert np.all(times[near] >= crossed_ns[near] - lead_s[near] * NS - 2048)

    state, _, _, _ = _ridge_with_a_pass(False, 2.0)
    before = state.stack.surface().copy()
    completion.complete_unseen(state, 100 * NS)
    np.testing.assert_array_equal(state.stack.surface(), before)


def test_a_flank_seen_after_the_pass_s_cone_left_it_stays_as_seen():
    # seen 8 s after the crossing (past the reach even 2.25 m down the flank: 1.54 m,
    # 6.2 s), the strip's look is the layer as it ended: nothing is completed
    tan = math.tan(math.radians(35.0))
    h = 0.3 / tan
    assert math.sqrt(h * h + 2 * h * 2.25) / 0.25 < 8.0 - 1.0
    state, _, strip, _ = _ridge_with_a_pass(True, 8.0)
    before = state.stack.surface().copy()
    completion.complete_unseen(state, 100 * NS)
    np.testing.assert_array_equal(state.stack.surface(), before)

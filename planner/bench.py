"""One bench, cut by cut, on a height map: slew ranges and the collision model.

A bench is a run of cuts at one luff (wheel-centre height): cut ``i`` is made at travel
``d1_0 + i * advance * direction`` and slews over the arc where the cutting envelope meets
the pile.  After each cut every column of its swept footprint is lowered to the envelope
floor, exactly as :func:`projector.envelope.cut_floor` followed by
:meth:`projector.layers.LayerStack.clamp` lowers the top surface (the same
formula, evaluated at the same cell centres), so the geometry here and the projector's
removal agree to rounding (:func:`planner.plan.plan_reclaim` checks it).

Slew range (per column, analytic)
---------------------------------
A column with centre at horizontal distance ``r`` from the slew axis and azimuth ``a`` is
*hit* by the cut if it lies in the envelope's ring, ``|r - rho| < Rv cos(beta)``, and its
surface is above the envelope floor and above the ground by more than ``min_bite_m``.
The slew range is ``[min a, max a]`` over the hit columns, azimuths unwrapped around a
reference slew (the landing's, then the previous cut's middle), so it is exact at the
resolution of the grid: no angular stepping.  No hit: the bench has run out of material.

Collision model
---------------
Checked on the surface *before* each cut (the planned surface after the previous cuts):

wheel body
    The wheel without its buckets sweeps the elliptic torus of the envelope with the minor
    radius Rk instead of Rv (thesis §5.1.2, eq. 5.2), inflated by ``clearance_m``:
    semi-axes ``(Rk + c) cos(beta)`` across and ``Rk + c`` up.  Over the cut's slew
    range, any column of material whose surface is above that torus' floor means pile
    inside (or above and around) the wheel body: a collision.  The buckets dig only
    between Rk and Rv, so a landing can bite at most Rv - Rk into the bank, and a later
    cut only finds material inside its body torus where the previous cut did not reach.
boom
    The boom is the straight segment from the pivot (L4 from the slew axis, at
    z_r + L2 + L3) to the wheel centre, thickened by ``clearance_m`` below.  At every slew
    angle of the cut, in steps of at most ``slew_step_rad`` (0.5 deg by default) including
    both ends, the part of the boom outside the wheel's cutting ellipse (in its vertical
    plane) must stay above the surface: a column under it whose material reaches
    ``boom height - clearance_m`` is a collision.
bank (overburden)
    The bank a cut faces, ``surface - max(c_z - Rv, ground)`` over its hit columns, must
    not exceed the maximum cutting height H = (Rv + Rk sin phi) cos beta: material above
    it would fall on the wheel and boom rather than into the buckets (thesis Fig. 5.2).
edge
    A hit column on the border of the mapped grid means the pile goes on where the model
    does not know it: the cut cannot be checked, and counts as invalid.

Faces sliding
-------------
After each cut (when ``PlanParams.slump``) the faces it left slide to the angle of repose
before the next cut is planned (:mod:`planner.settle`), as they do in the yard:
the next cut takes what slid into the hole.

Everything here is pure numpy on arrays indexed ``[ix, iy]`` (shape ``(nx, ny)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from projector.grid import GridGeometry
from projector.kinematics import PlannerMachine, boom_height_m, boom_radius_m
from projector.slump import estimate_repose_deg
from planner.settle import relax_region

__all__ = ["PlanParams", "CellSet", "CutGeometry", "cell_set", "cut_step", "simulate_bench",
           "slew_motion", "slump_after"]

_TWO_PI = 2.0 * math.pi
_ARC_PAD_RAD = 1e-12


@dataclass(frozen=True)
class PlanParams:
    """Tuning of the planner (lengths in metres, angles in radians).

    Attributes
    ----------
    clearance_m : float or None
        Safety margin added to the wheel-body radius and under the boom; None: 0.1 x Rv.
    min_bite_m : float or None
        A column counts as hit (and as material) when its surface is this far above the
        envelope floor and the ground; None: 0.01 x Rv (the simulator's threshold).
    cut_depth_m : float or None
        Advance between cuts; None: 0.9 x bucket width.
    slew_step_rad : float
        Largest step between the boom positions checked for collisions (<= 0.5 deg).
    spacing_m : float or None
        Spacing of the square grid of candidate landing points, rounded to whole cells;
        None: Rv / 5 (at least one cell).
    normal_window_m : float or None
        Width of the least-squares plane fitted for the surface normal; None: Rv / 2.
    slump : bool
        Let the faces a cut leaves slide to the angle of repose before the next cut
        (:mod:`planner.settle`).
    repose_deg : float or None
        Angle of repose (deg); None: estimated from the surface by the projector's
        :func:`projector.slump.estimate_repose_deg` (35 deg if it cannot tell).
    slump_block_m : float or None
        Block edge of the slump relaxation (m), rounded to whole cells; None: Rv / 5.
    """

    clearance_m: float | None = None
    min_bite_m: float | None = None
    cut_depth_m: float | None = None
    slew_step_rad: float = math.radians(0.5)
    spacing_m: float | None = None
    normal_window_m: float | None = None
    slump: bool = True
    repose_deg: float | None = None
    slump_block_m: float | None = None

    def __post_init__(self) -> None:
        for name in ("clearance_m", "min_bite_m", "cut_depth_m", "spacing_m",
                     "normal_window_m", "slump_block_m"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not math.isfinite(float(value))
                                      or float(value) < 0):
                raise ValueError(f"{name} must be a finite number >= 0 (or None), got {value!r}")
        for name in ("cut_depth_m", "spacing_m", "normal_window_m", "slump_block_m"):
            value = getattr(self, name)
            if value is not None and not float(value) > 0:
                raise ValueError(f"{name} must be > 0, got {value!r}")
        if self.repose_deg is not None and not (math.isfinite(float(self.repose_deg))
                                                and 0 < float(self.repose_deg) < 89):
            raise ValueError(f"repose_deg must be in (0, 89), got {self.repose_deg!r}")
        if not (math.isfinite(self.slew_step_rad) and 0 < self.slew_step_rad <= math.radians(0.5)):
            raise ValueError(f"slew_step_rad must be in (0, 0.5 deg], got {self.slew_step_rad!r}")

    def resolved(self, machine: PlannerMachine, surface_m=None,
                 cell_m: float | None = None) -> "PlanParams":
        """The parameters with every None replaced by its default for ``machine``.

        The angle of repose is estimated from ``surface_m`` (cells of ``cell_m``) when
        it is None and a surface is given.
        """
        rv = machine.cutting_radius_m
        repose = self.repose_deg
        if repose is None and surface_m is not None:
            repose = estimate_repose_deg(surface_m, float(cell_m))
            repose = repose if math.isfinite(repose) else 35.0
        return replace(
            self, repose_deg=repose,
            slump_block_m=rv / 5 if self.slump_block_m is None else float(self.slump_block_m),
            clearance_m=0.1 * rv if self.clearance_m is None else float(self.clearance_m),
            min_bite_m=0.01 * rv if self.min_bite_m is None else float(self.min_bite_m),
            cut_depth_m=(machine.cut_depth_m if self.cut_depth_m is None
                         else float(self.cut_depth_m)),
            spacing_m=rv / 5 if self.spacing_m is None else float(self.spacing_m),
            normal_window_m=rv / 2 if self.normal_window_m is None else float(self.normal_window_m))


@dataclass(frozen=True)
class CellSet:
    """The columns holding material when planning starts, sorted by y (cell centres).

    Columns without material never gain any during a plan, so only these are looked at.

    Attributes
    ----------
    geometry : GridGeometry
    ix, iy : ndarray, shape (M,), int64
    x_m, y_m : ndarray, shape (M,)
        Cell centres (m).
    ground_m : ndarray, shape (M,)
        Ground level (m).
    border : ndarray of bool, shape (M,)
        Whether the cell is on the outermost ring of the grid.
    ground_grid_m : ndarray, shape (nx, ny)
        The ground everywhere (m).
    """

    geometry: GridGeometry
    ix: np.ndarray
    iy: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    ground_m: np.ndarray
    border: np.ndarray
    ground_grid_m: np.ndarray

    def window(self, y_lo_m: float, y_hi_m: float) -> slice:
        """The cells with ``y_lo_m <= y <= y_hi_m`` (a slice, cells are sorted by y)."""
        a = int(np.searchsorted(self.y_m, y_lo_m, side="left"))
        b = int(np.searchsorted(self.y_m, y_hi_m, side="right"))
        return slice(a, b)


def _check_grid(geometry: GridGeometry, arr, name: str) -> np.ndarray:
    a = np.asarray(arr, dtype=np.float64)
    if a.shape != geometry.shape:
        raise ValueError(f"{name} must have shape {geometry.shape} (nx, ny), got {a.shape}")
    return a


def cell_set(geometry: GridGeometry, surface_m, ground_m, min_bite_m: float) -> CellSet:
    """The columns whose surface is more than ``min_bite_m`` above the ground.

    Parameters
    ----------
    geometry : GridGeometry
    surface_m, ground_m : array_like, shape (nx, ny)
        Top surface and ground (m), finite.
    min_bite_m : float
        Material threshold (m, >= 0).

    Raises
    ------
    ValueError
        On wrong shapes or non-finite heights.
    """
    surface = _check_grid(geometry, surface_m, "surface_m")
    ground = _check_grid(geometry, ground_m, "ground_m")
    if not (np.all(np.isfinite(surface)) and np.all(np.isfinite(ground))):
        raise ValueError("surface_m and ground_m must be finite (fill holes first)")
    ix, iy = np.nonzero(surface > ground + float(min_bite_m))
    order = np.lexsort((ix, iy))  # by y, then x
    ix, iy = ix[order].astype(np.int64), iy[order].astype(np.int64)
    cell = geometry.cell_m
    border = (ix == 0) | (iy == 0) | (ix == geometry.nx - 1) | (iy == geometry.ny - 1)
    return CellSet(geometry, ix, iy, geometry.origin_x_m + (ix + 0.5) * cell,
                   geometry.origin_y_m + (iy + 0.5) * cell, ground[ix, iy], border, ground)


@dataclass(frozen=True)
class CutGeometry:
    """One planned cut and what the collision model found (module docstring).

    Attributes
    ----------
    travel_m, luff_rad : float
        The cut's travel d1 (m) and luff theta3 (rad).
    slew_lo_rad, slew_hi_rad : float
        The slewed arc ``[lo, hi]`` (rad, unwrapped joint angles); NaN when nothing is hit.
    hit_cells : int
        Columns whose material the envelope meets.
    removed_m3 : float
        Volume the cut removes from the height map (m3).
    bank_m : float
        Highest bank over the hit columns above ``max(c_z - Rv, ground)`` (m).
    wheel_cells : int
        Columns with material inside the (inflated) wheel-body torus.
    wheel_intrusion_m : float
        Deepest such intrusion above the body torus' floor (m); 0 when none.
    boom_cells : int
        Boom sample points where the surface reaches ``boom height - clearance``.
    boom_intrusion_m : float
        Deepest such intrusion (m); 0 when none.
    edge : bool
        A hit column lies on the border of the grid.
    max_bank_m : float
        The machine's H (m), for the verdict.
    footprint : tuple of int
        ``(ix0, ix1, iy0, iy1)``: the cells the cut lowers lie in ``[ix0, ix1) x [iy0, iy1)``.
    slumped_m3 : float
        Volume that slid after the cut (m3; set by :func:`simulate_bench`).
    """

    travel_m: float
    luff_rad: float
    slew_lo_rad: float
    slew_hi_rad: float
    hit_cells: int
    removed_m3: float
    bank_m: float
    wheel_cells: int
    wheel_intrusion_m: float
    boom_cells: int
    boom_intrusion_m: float
    edge: bool
    max_bank_m: float
    footprint: tuple[int, int, int, int] = (0, 0, 0, 0)
    slumped_m3: float = 0.0

    @property
    def empty(self) -> bool:
        """Whether the envelope meets no material."""
        return self.hit_cells == 0

    @property
    def reasons(self) -> tuple[str, ...]:
        """Why the cut is not allowed: ``"wheel"``, ``"boom"``, ``"bank"``, ``"edge"``."""
        out = []
        if self.wheel_cells:
            out.append("wheel")
        if self.boom_cells:
            out.append("boom")
        if self.bank_m > self.max_bank_m + 1e-9:
            out.append("bank")
        if self.edge:
            out.append("edge")
        return tuple(out)

    @property
    def ok(self) -> bool:
        """A non-empty cut with no collision, bank <= H, inside the grid."""
        return not self.empty and not self.reasons


def _arc_offsets(azimuth: np.ndarray, lo: float) -> np.ndarray:
    # the projector's in_slew_arc test: counter-clockwise offset from the arc's low end
    return np.mod(azimuth - lo, _TWO_PI)


def _check_cut_inputs(surface_m: np.ndarray, geometry: GridGeometry, travel_m: float,
                      luff_rad: float, reference_slew_rad: float) -> None:
    """ValueError unless the surface has the grid's shape and the joints are finite."""
    if surface_m.shape != geometry.shape:
        raise ValueError(f"surface_m must have shape {geometry.shape}, got {surface_m.shape}")
    for name, value in (("travel_m", travel_m), ("luff_rad", luff_rad),
                        ("reference_slew_rad", reference_slew_rad)):
        if not math.isfinite(float(value)):
            raise ValueError(f"{name} must be finite, got {value!r}")


def _slew_range(azimuth_hit: np.ndarray, reference_slew_rad: float) -> tuple[float, float]:
    """``(lo, hi)`` slew (rad) over the hit columns' azimuths, unwrapped around the reference.

    A hair wider than the extreme columns' azimuths, so that the unwrapping's rounding
    never drops them from the arc test (the projector's and the simulator's alike).
    """
    ref = float(reference_slew_rad)
    unwrapped = ref + np.mod(azimuth_hit - ref + math.pi, _TWO_PI) - math.pi
    return float(unwrapped.min()) - _ARC_PAD_RAD, float(unwrapped.max()) + _ARC_PAD_RAD


def _wheel_body_check(s: np.ndarray, g: np.ndarray, dr: np.ndarray, swept: np.ndarray,
                      c_z: float, rk: float, hw_k: float) -> tuple[int, float]:
    """Columns whose material is above the floor of the (inflated) Rk torus: (count, deepest m).

    ``s``, ``g``, ``dr``: surface, ground (m) and ``r - rho`` (m) of the columns near the
    ring; ``swept``: those on the cut's arc holding material; ``rk``, ``hw_k``: the
    inflated wheel-body radius and its horizontal half-width (m).
    """
    ring_k = (np.abs(dr) < hw_k) & swept
    w_floor = c_z - rk * np.sqrt(np.clip(1.0 - (dr[ring_k] / hw_k) ** 2, 0.0, None))
    intrusion = s[ring_k] - np.maximum(w_floor, g[ring_k])
    wheel_cells = int(np.count_nonzero(intrusion > 0))
    return wheel_cells, (float(intrusion.max()) if wheel_cells else 0.0)


def cut_step(surface_m: np.ndarray, cells: CellSet, machine: PlannerMachine, travel_m: float,
             luff_rad: float, reference_slew_rad: float, params: PlanParams, *,
             apply: bool | str = True) -> CutGeometry:
    """Plan one cut on a height map: its slew range and the collision checks; then cut it.

    Parameters
    ----------
    surface_m : ndarray, shape (nx, ny), float64
        The top surface (m); lowered in place to the envelope floor over the cut's
        footprint when ``apply`` (and the cut is not empty).
    cells : CellSet
        :func:`cell_set` of the surface when planning started.
    machine : PlannerMachine
    travel_m, luff_rad : float
        The cut's travel (m) and luff (rad).
    reference_slew_rad : float
        Azimuths are unwrapped into ``(ref - pi, ref + pi]`` around this slew (rad).
    params : PlanParams
        Resolved (:meth:`PlanParams.resolved`).
    apply : bool or "ok"
        Lower the surface (False: only look; ``"ok"``: only if the cut is allowed).

    Returns
    -------
    CutGeometry
    """
    geometry = cells.geometry
    _check_cut_inputs(surface_m, geometry, travel_m, luff_rad, reference_slew_rad)
    m = machine.reclaimer
    rv = m.cutting_radius_m
    cos_b = math.cos(m.wheel_tilt_rad)
    hw = rv * cos_b
    rk = machine.wheel_radius_m + params.clearance_m
    hw_k = rk * cos_b
    rho = float(boom_radius_m(m, luff_rad))
    c_z = float(boom_height_m(m, luff_rad))
    bite = params.min_bite_m
    big = abs(rho) + max(hw, hw_k)
    sl = cells.window(travel_m - big, travel_m + big)
    dx = cells.x_m[sl] - m.rail_x_m
    dy = cells.y_m[sl] - travel_m
    r = np.hypot(dx, dy)
    dr = r - rho
    near = np.flatnonzero(np.abs(dr) < max(hw, hw_k))
    ix, iy = cells.ix[sl][near], cells.iy[sl][near]
    dr = dr[near]
    s = surface_m[ix, iy]
    g = cells.ground_m[sl][near]
    ring = np.abs(dr) < hw
    floor = np.full(dr.shape, np.inf)
    floor[ring] = c_z - rv * np.sqrt(1.0 - (dr[ring] / hw) ** 2)
    material = s > g + bite
    hit = ring & material & (s > floor + bite)
    nan = math.nan
    if not hit.any():
        return CutGeometry(float(travel_m), float(luff_rad), nan, nan, 0, 0.0, 0.0, 0, 0.0, 0,
                           0.0, False, machine.max_cutting_height_m)
    azimuth = np.arctan2(dx[near], dy[near])
    lo, hi = _slew_range(azimuth[hit], reference_slew_rad)
    in_arc = _arc_offsets(azimuth, lo) <= hi - lo
    # the bank the cut faces, and the border
    bench_floor = np.maximum(c_z - rv, g[hit])
    bank = float(np.max(s[hit] - bench_floor))
    edge = bool(np.any(cells.border[sl][near][hit]))
    wheel_cells, wheel_in = _wheel_body_check(s, g, dr, in_arc & material, c_z, rk, hw_k)
    boom_cells, boom_in = _boom_check(surface_m, geometry, machine, travel_m, luff_rad, lo, hi,
                                      params, rho, c_z, hw)
    # the cut: every footprint column down to the envelope floor (never below ground)
    foot = ring & in_arc
    new = np.minimum(s[foot], np.maximum(floor[foot], g[foot]))
    removed = float(np.sum(s[foot] - new) * geometry.cell_area_m2)
    fx, fy = ix[foot], iy[foot]
    box = (int(fx.min()), int(fx.max()) + 1, int(fy.min()), int(fy.max()) + 1) if fx.size \
        else (0, 0, 0, 0)
    cut = CutGeometry(float(travel_m), float(luff_rad), lo, hi, int(np.count_nonzero(hit)),
                      removed, bank, wheel_cells, wheel_in, boom_cells, boom_in, edge,
                      machine.max_cutting_height_m, box)
    if apply is True or (apply == "ok" and cut.ok):
        surface_m[fx, fy] = new
    return cut


def _boom_check(surface_m, geometry: GridGeometry, machine: PlannerMachine, travel_m: float,
                luff_rad: float, lo: float, hi: float, params: PlanParams, rho: float,
                c_z: float, hw: float) -> tuple[int, float]:
    """Boom sample points (outside the cutting ellipse) the surface reaches: (count, deepest m)."""
    m = machine.reclaimer
    tan_l = math.tan(luff_rad)
    # the boom line leaves the wheel's cutting ellipse |r - rho| = e before the centre
    e = 1.0 / math.sqrt(1.0 / hw ** 2 + (tan_l / m.cutting_radius_m) ** 2)
    r_end = rho - e
    if r_end <= m.l4_m:
        return 0, 0.0
    step_r = 0.5 * geometry.cell_m
    radii = np.append(np.arange(m.l4_m, r_end, step_r), r_end)
    z_boom = machine.pivot_z_m + (radii - m.l4_m) * tan_l - params.clearance_m
    n = max(2, int(math.ceil((hi - lo) / params.slew_step_rad)) + 1)
    theta = np.linspace(lo, hi, n)
    x = m.rail_x_m + np.sin(theta)[:, None] * radii[None, :]
    y = travel_m + np.cos(theta)[:, None] * radii[None, :]
    ix = np.floor((x - geometry.origin_x_m) / geometry.cell_m).astype(np.int64)
    iy = np.floor((y - geometry.origin_y_m) / geometry.cell_m).astype(np.int64)
    inside = (ix >= 0) & (ix < geometry.nx) & (iy >= 0) & (iy < geometry.ny)
    if not inside.any():
        return 0, 0.0
    s = np.full(x.shape, -np.inf)
    s[inside] = surface_m[ix[inside], iy[inside]]
    over = s - z_boom[None, :]
    hits = over >= 0
    count = int(np.count_nonzero(hits))
    return count, (float(over[hits].max()) if count else 0.0)


def slew_motion(cuts: list[CutGeometry], landing_slew_rad: float) -> list[tuple[float, float]]:
    """Start and end slew of each cut in the order the boom moves (rad).

    The first cut starts at the end of its arc nearer the landing slew; every later cut
    starts at the end of its arc nearer where the previous one stopped.
    """
    out = []
    at = float(landing_slew_rad)
    for c in cuts:
        lo, hi = c.slew_lo_rad, c.slew_hi_rad
        start, end = (lo, hi) if abs(at - lo) <= abs(at - hi) else (hi, lo)
        out.append((start, end))
        at = end
    return out


def simulate_bench(surface_m: np.ndarray, cells: CellSet, machine: PlannerMachine,
                   travel_m: float, luff_rad: float, landing_slew_rad: float, direction: int,
                   n_cuts: int, params: PlanParams, *,
                   stop_on_invalid: bool = True, on_cut=None) -> list[CutGeometry]:
    """Cut a bench on a height map (in place): up to ``n_cuts`` cuts, advancing each time.

    Parameters
    ----------
    surface_m : ndarray, shape (nx, ny)
        Top surface (m), lowered in place.
    cells : CellSet
    machine : PlannerMachine
    travel_m, luff_rad : float
        The landing's travel (m) and luff (rad): the first cut's joints.
    landing_slew_rad : float
        The landing's slew (rad): the first cut's azimuths are unwrapped around it.
    direction : {+1, -1}
        Advance along +y or -y.
    n_cuts : int
        Cuts wanted (>= 1); fewer are returned when the envelope meets no more material.
    params : PlanParams
        Resolved.
    stop_on_invalid : bool
        Stop after the first cut that is not :attr:`CutGeometry.ok` (it is returned, and
        the surface is left as it was before it).
    on_cut : callable, optional
        ``on_cut(cut, surface_m)`` after each cut is made and its faces have slid.

    Returns
    -------
    list of CutGeometry
        The non-empty cuts, in order.
    """
    if direction not in (1, -1):
        raise ValueError(f"direction must be +1 or -1, got {direction!r}")
    if isinstance(n_cuts, bool) or int(n_cuts) < 1:
        raise ValueError(f"n_cuts must be >= 1, got {n_cuts!r}")
    out: list[CutGeometry] = []
    ref = float(landing_slew_rad)
    for i in range(int(n_cuts)):
        travel = float(travel_m) + i * params.cut_depth_m * direction
        cut = cut_step(surface_m, cells, machine, travel, luff_rad, ref, params,
                       apply="ok" if stop_on_invalid else True)
        if cut.empty:
            break
        out.append(cut)
        if stop_on_invalid and not cut.ok:
            break
        if params.slump and cut.removed_m3 > 0:
            moved = slump_after(surface_m, cells, cut, params)
            cut = replace(cut, slumped_m3=moved)
            out[-1] = cut
        if on_cut is not None:
            on_cut(cut, surface_m)
        ref = 0.5 * (cut.slew_lo_rad + cut.slew_hi_rad)
    return out


def slump_after(surface_m: np.ndarray, cells: CellSet, cut: CutGeometry,
                params: PlanParams) -> float:
    """Let the faces ``cut`` left slide (in place); returns the volume moved (m3).

    The region is the cut's footprint widened by the run of a slope at repose from the
    top of its bank, ``bank / tan(repose)``, plus two blocks.
    """
    geometry = cells.geometry
    tan = math.tan(math.radians(params.repose_deg if params.repose_deg is not None else 35.0))
    block = max(1, int(round(params.slump_block_m / geometry.cell_m)))
    pad = int(math.ceil(max(cut.bank_m, 0.0) / tan / geometry.cell_m)) + 2 * block
    ix0, ix1, iy0, iy1 = cut.footprint
    region = (slice(max(0, ix0 - pad), min(geometry.nx, ix1 + pad)),
              slice(max(0, iy0 - pad), min(geometry.ny, iy1 + pad)))
    return relax_region(surface_m, cells.ground_grid_m, geometry.cell_m, tan, region, block,
                        tol_m=1e-3 * block * geometry.cell_m)

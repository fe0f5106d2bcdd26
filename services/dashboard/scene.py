"""The 3D scene under ``/site`` and the documents that describe it.

:class:`PileScene` draws the pile: its top surface per analyte (``/site/pile/surface/<A>``,
a mesh coloured by the grade of the top voxel), its voxels (``/site/pile/voxels``, merged
beyond a cap), the deposit boundaries (``/site/pile/layers``) and the ``/legend``.
:func:`log_machines` draws the reclaimers from their latest poses, :func:`log_scan` the
latest scan georeferenced, :func:`log_status` the ``/status`` document.  Only the latest
state of each entity is sent.
"""

from __future__ import annotations

import math

import numpy as np

from projector.grades import coerce_time_ns
from services.dashboard.pose import (joints_from_wheel_pose, machine_strips, scan_points,
                                     scanner_pose_at)
from services.dashboard.recorder import iso, rr
from services.dashboard.style import colour_map, lot_colour

#: the rail is drawn this far beyond each end of the pile, m
RAIL_OVERHANG_M = 40.0


def merge_voxels(tonnes: np.ndarray, grade: np.ndarray, f: int):
    """Voxels merged ``f x f x f``: ``(tonnes, tonnage-weighted grade)`` (grade 0 where empty).

    ``tonnes`` and ``grade`` are (nx, ny, nz); the results (ceil(nx / f), ceil(ny / f),
    ceil(nz / f)).
    """
    pads = [(0, (-n) % f) for n in tonnes.shape]
    t = np.pad(tonnes, pads)
    tg = np.pad(tonnes * grade, pads)
    shape = (t.shape[0] // f, f, t.shape[1] // f, f, t.shape[2] // f, f)
    t = t.reshape(shape).sum(axis=(1, 3, 5))
    tg = tg.reshape(shape).sum(axis=(1, 3, 5))
    with np.errstate(invalid="ignore", divide="ignore"):
        return t, np.where(t > 0, tg / t, 0.0)


def surface_mesh(surface: np.ndarray, grid, cell_m: float, nvx: int, nvy: int,
                 max_vertices: int):
    """The top surface as a mesh of at most ``max_vertices`` vertices.

    Parameters
    ----------
    surface : ndarray, shape (nx, ny)
        Height of each cell column, m.
    grid
        The voxel grid (``cells_per_voxel``, ``origin_x_m``, ``origin_y_m``).
    cell_m : float
        Cell size, m.
    nvx, nvy : int
        Voxel columns along x and y.

    Returns
    -------
    step : int
        Voxel columns per mesh vertex along x and y.
    shape : tuple of int
        ``(mx, my)``: vertices along x and y.
    positions : ndarray, shape (mx * my, 3)
        Vertices, m: one per ``step x step`` voxel columns, at their mean height.
    triangles : ndarray of uint32, shape (2 (mx - 1) (my - 1), 3)
    """
    nx, ny = surface.shape
    step = 1
    while (math.ceil(nvx / step) * math.ceil(nvy / step)) > max_vertices:
        step += 1
    k = grid.cells_per_voxel * step
    pad_x, pad_y = (-nx) % k, (-ny) % k
    z = np.pad(surface, ((0, pad_x), (0, pad_y)), mode="edge")
    z = z.reshape(z.shape[0] // k, k, z.shape[1] // k, k).mean(axis=(1, 3))
    mx, my = z.shape
    xs = grid.origin_x_m + (np.arange(mx) + 0.5) * k * cell_m
    ys = grid.origin_y_m + (np.arange(my) + 0.5) * k * cell_m
    positions = np.column_stack([np.repeat(xs, my), np.tile(ys, mx), z.ravel()])
    ii = (np.arange(mx - 1)[:, None] * my + np.arange(my - 1)[None, :]).ravel()
    tri = np.concatenate([np.column_stack([ii, ii + my, ii + 1]),
                          np.column_stack([ii + 1, ii + my, ii + my + 1])]).astype(np.uint32)
    return step, (mx, my), positions, tri


class PileScene:
    """The pile's surface, voxels, layers and legend.

    Parameters
    ----------
    out : Recorder
    tracker : PileTracker
        The colour scales and whether the geometry changed since the last redraw.
    config : Config
        ``analyte``, ``max_mesh_vertices``, ``max_voxels``, ``layers``, ``layer_step_m``.
    """

    def __init__(self, out, tracker, config) -> None:
        self.out, self.tracker, self.config = out, tracker, config
        self._mesh_shape: tuple[int, int] | None = None
        self._mesh_analytes: set[str] = set()

    def log(self, state) -> None:
        """Draw the pile of ``state`` (a :class:`projector.query.PileState`)."""
        if state.state.stack.n_deposits == 0 or not state.analytes:
            return   # nothing stacked yet
        tonnes, grade, grid = state.voxel_grades()
        nvx, nvy, nvz = tonnes.shape
        step, shape, positions, tri = surface_mesh(state.surface_m, grid,
                                            state.state.pile.geometry.cell_m, nvx, nvy,
                                            self.config.max_mesh_vertices)
        # the top voxel with material of each voxel column, then per mesh vertex
        has = tonnes > 0
        top = np.where(has.any(axis=2), nvz - 1 - np.argmax(has[:, :, ::-1], axis=2), -1)
        self.out.at()
        self._log_surface(state, grade, top, step, shape, positions, tri)
        self._log_voxels(state, tonnes, grade, has, grid)
        if self.config.layers:
            self._log_layers(state)
        self._log_legend(state.analytes)

    def _log_surface(self, state, grade, top, step: int, shape: tuple[int, int], positions,
                     tri) -> None:
        """One mesh per analyte coloured by the grade of each column's top voxel (``top``:
        its index, -1 for an empty column)."""
        rerun = rr()
        nvx, nvy = top.shape
        mx, my = shape
        # the mesh's triangles never change for a pile (its grid is fixed): static, once
        new_shape = (mx, my) != self._mesh_shape
        self._mesh_shape = (mx, my)
        for ai, a in enumerate(state.analytes):
            col = np.full((nvx, nvy), np.nan)
            sel = top >= 0
            col[sel] = grade[np.nonzero(sel)[0], np.nonzero(sel)[1], top[sel], ai]
            col = np.pad(col, ((0, (-nvx) % step), (0, (-nvy) % step)), constant_values=np.nan)
            col = col[::step, ::step][:mx, :my]
            lo, hi = self.tracker.colour_range(a)
            colours = colour_map(col.ravel(), lo, hi)
            path = f"/site/pile/surface/{a}"
            if new_shape or a not in self._mesh_analytes:
                self.out.log(path, rerun.Mesh3D.from_fields(triangle_indices=tri), static=True)
                self._mesh_analytes.add(a)
            if self.tracker.geometry_dirty or new_shape:
                self.out.log(path, rerun.Mesh3D.from_fields(vertex_positions=positions,
                                                            vertex_colors=colours))
            else:   # only the grades moved (an assay): the colours alone
                self.out.log(path, rerun.Mesh3D.from_fields(vertex_colors=colours))

    def _log_voxels(self, state, tonnes, grade, has, grid) -> None:
        """One batched entity coloured by the chosen analyte, radius ~ tonnes^(1/3); a big
        pile's voxels are merged f x f x f (tonnes summed, grades tonnage-weighted) until at
        most ``max_voxels`` remain."""
        rerun = rr()
        a0 = self.config.analyte if self.config.analyte in state.analytes else (
            state.analytes[0] if state.analytes else None)
        if not (has.any() and a0 is not None):
            self.out.log("/site/pile/voxels", rerun.Clear(recursive=False))
            return
        ai = state.analytes.index(a0)
        t_vox = tonnes
        g_vox = np.where(has, grade[..., ai], 0.0)
        f = 1
        while int(np.count_nonzero(t_vox > 0)) > self.config.max_voxels:
            f *= 2
            t_vox, g_vox = merge_voxels(tonnes, np.where(has, grade[..., ai], 0.0), f)
        ix, iy, iz = np.nonzero(t_vox > 0)
        v = grid.voxel_m * f
        centres = np.column_stack([grid.origin_x_m + (ix + 0.5) * v,
                                   grid.origin_y_m + (iy + 0.5) * v,
                                   grid.z0_m + (iz + 0.5) * v])
        t = t_vox[ix, iy, iz]
        full = v ** 3 * state.state.pile.default_bulk_density_t_m3
        radii = 0.5 * v * np.clip(np.cbrt(t / full), 0.15, 1.0)
        lo, hi = self.tracker.colour_range(a0)
        self.out.log("/site/pile/voxels", rerun.Points3D(
            centres, colors=colour_map(g_vox[ix, iy, iz], lo, hi), radii=radii))

    def _log_layers(self, state) -> None:
        """Deposit boundaries in cross-sections every ``layer_step_m``, coloured by lot."""
        stack = state.state.stack
        geometry = state.state.pile.geometry
        xs = geometry.origin_x_m + (np.arange(geometry.nx) + 0.5) * geometry.cell_m
        step = max(1, int(round(self.config.layer_step_m / geometry.cell_m)))
        strips, colours = [], []
        for iy in range(step // 2, geometry.ny, step):
            y = geometry.origin_y_m + (iy + 0.5) * geometry.cell_m
            for k in range(1, stack.n_deposits + 1):
                thick = stack.thickness(k)[:, iy]
                cols = np.nonzero(thick > 1e-3)[0]
                if cols.size < 2:
                    continue
                lo, hi = cols.min(), cols.max() + 1
                zk = stack.surface_k(k)[lo:hi, iy]
                strips.append(np.column_stack([xs[lo:hi], np.full(hi - lo, y), zk]))
                colours.append(lot_colour(stack.info(k).lot_id))
        if strips:
            self.out.log("/site/pile/layers", rr().LineStrips3D(strips, colors=colours,
                                                                radii=0.03))

    def _log_legend(self, analytes) -> None:
        rerun = rr()
        legend = "\n".join(f"| {a} | {self.tracker.colour_range(a)[0]:.2f} | "
                           f"{self.tracker.colour_range(a)[1]:.2f} |" for a in analytes)
        self.out.log("/legend", rerun.TextDocument(
            "### Colours\n\nSurface, voxels and cut footprints: blue = low, red = high, grey = "
            "no grade.\nVoxel radius grows with the voxel's tonnes.\n\n| analyte | blue at % | "
            "red at % |\n|---|---|---|\n" + legend, media_type=rerun.MediaType.MARKDOWN))


def log_machines(out, machines, pile) -> None:
    """Each reclaimer's rail (static, once the pile is known) and, when its pose is newer
    than the one drawn, its tower, boom and wheel (``/site/machines/<id>``)."""
    rerun = rr()
    for m in machines.values():
        if not m.rail_logged and pile is not None:
            g = pile.geometry
            y0 = g.origin_y_m - RAIL_OVERHANG_M
            y1 = g.origin_y_m + g.length_y_m + RAIL_OVERHANG_M
            r = m.reclaimer
            out.log(f"/site/machines/{m.machine_id}/rail_m", rerun.LineStrips3D(
                [[[r.rail_x_m, y0, r.rail_z_m], [r.rail_x_m, y1, r.rail_z_m]]],
                colors=[[120, 120, 120]], radii=0.3), static=True)
            m.rail_logged = True
        if m.pose is None or m.pose[0] == m.logged_pose_ns:
            continue
        t, centre, rot = m.pose
        travel, slew, luff = joints_from_wheel_pose(m.reclaimer, centre, rot)
        strips = machine_strips(m.reclaimer, travel, slew, luff,
                                m.wheel_radius_m or m.reclaimer.cutting_radius_m * 0.7)
        out.at()
        out.log(f"/site/machines/{m.machine_id}", rerun.LineStrips3D(
            strips, colors=[[250, 200, 40]] * len(strips), radii=0.25,
            labels=[m.machine_id] + [""] * (len(strips) - 1)))
        m.logged_pose_ns = t


def log_scan(out, msg, scanner_poses: dict) -> None:
    """A decoded scan georeferenced with its machine's scanner poses (``/site/scan``)."""
    frame = msg.frame_id or ""
    machine_id = frame.split("/", 1)[0] if "/" in frame else next(iter(scanner_poses), "")
    poses = scanner_poses.get(machine_id)
    ranges = np.asarray(msg.ranges, np.float64)
    if not poses or ranges.size < 2:
        return
    position, quaternion = scanner_pose_at(coerce_time_ns(msg.timestamp), poses)
    if not np.isfinite(position).all():
        return
    pts = scan_points(ranges, msg.start_angle, msg.end_angle, position, quaternion)
    out.at()
    out.log("/site/scan", rr().Points3D(pts, colors=[[255, 255, 255]], radii=0.08))


def log_status(out, pile_id: str, state, *, updates: int, rebuilds: int) -> None:
    """The ``/status`` document: V, K, the pile's figures and the fold's counters."""
    rerun = rr()
    tracker = out.tracker
    counters = ", ".join(f"{k} {v:,}" for k, v in sorted(state.counters.items()))
    out.log("/status", rerun.TextDocument(
        f"### Pile {pile_id}\n\n"
        f"- valid time V: {iso(tracker.valid_ns)}\n- known time K: {iso(tracker.known_ns)} "
        f"(ledger seq {tracker.seq:,})\n- volume {state.volume_m3:,.1f} m3, "
        f"{state.tonnes:,.1f} t, assayed fraction {state.assayed_fraction:.2f}\n- grade: "
        + ", ".join(f"{a} {g:.2f} %" for a, g in state.grade.items() if math.isfinite(g))
        + f"\n- deposits {len(state.deposits)}, cuts {len(state.cuts)}, "
        f"updates {updates}, rebuilds {rebuilds}\n- fold: {counters}",
        media_type=rerun.MediaType.MARKDOWN))

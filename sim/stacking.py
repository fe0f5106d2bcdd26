"""How a stacking pass is released: the boom's path per pattern, and each release's share.

:meth:`sim.world.World.stack_pass` releases a pass in small time steps; this module
plans them: :func:`release_segments` gives the boom's path per release for a
:class:`~sim.grid.Pattern` (CHEVRON one run along y, WINDROW parallel runs, CONE_SHELL
stations), :func:`release_shares` each release's fraction of the pass's tonnes, and
:func:`release_times` the moment of each release. :func:`chevron_pile` stacks
consecutive chevron passes. Lengths in metres, times in UTC ns.
"""

from __future__ import annotations

import math
from typing import Iterable

import numpy as np

from sim.grid import DEFAULT_DENSITY_T_M3, Pattern

#: one release's path: (x_start, y_start, x_end, y_end), m
Segment = tuple[float, float, float, float]


def split_run(x: float, y0: float, y1: float, step: float) -> list[Segment]:
    """Split a run along y at fixed x into segments of at most ``step`` (at least one)."""
    length = abs(y1 - y0)
    n = max(1, int(math.ceil(length / step - 1e-9)))
    ys = np.linspace(y0, y1, n + 1)
    return [(x, float(ys[i]), x, float(ys[i + 1])) for i in range(n)]


def release_segments(pattern: Pattern, y0: float, y1: float, xc: float, step: float, *,
                     volume_m3: float, tan_repose: float, n_rows: int = 3,
                     row_spacing_m: float | None = None, row_offset_m: float = 0.0,
                     n_cones: int | None = None, cone_spacing_m: float | None = None,
                     releases_per_cone: int = 4) -> list[Segment]:
    """The boom's path per release of one pass (see :meth:`sim.world.World.stack_pass`).

    ``volume_m3`` is the pass's volume: the default WINDROW spacing puts ridges of its
    cross-section per row at ``tan_repose`` toe to toe.
    """
    segs: list[Segment] = []
    length = abs(y1 - y0)
    if pattern is Pattern.CHEVRON:
        segs = split_run(xc, y0, y1, step)
    elif pattern is Pattern.WINDROW:
        if n_rows < 1:
            raise ValueError("n_rows must be >= 1")
        if row_spacing_m is None:
            a_row = volume_m3 / max(length, step) / n_rows
            row_spacing_m = 2.0 * math.sqrt(max(a_row, 0.0) / tan_repose)
        for j in range(n_rows):
            xr = xc + row_offset_m + (j - (n_rows - 1) / 2.0) * float(row_spacing_m)
            segs += split_run(xr, y0, y1, step) if j % 2 == 0 else split_run(xr, y1, y0, step)
    else:  # CONE_SHELL
        if n_cones is None:
            spacing = float(cone_spacing_m) if cone_spacing_m else 4.0 * step
            n_cones = max(1, int(round(length / spacing)) + 1)
        if n_cones < 1 or releases_per_cone < 1:
            raise ValueError("n_cones and releases_per_cone must be >= 1")
        ys = [y0] if n_cones == 1 else list(np.linspace(y0, y1, n_cones))
        for yy in ys:
            segs += [(xc, float(yy), xc, float(yy))] * int(releases_per_cone)
    return segs


def release_shares(pattern: Pattern, segs: list[Segment],
                   rng: np.random.Generator | None, rate_cv: float) -> np.ndarray:
    """Each release's fraction of the pass's tonnes, shape (n,), summing to 1.

    Uniform tonnes per metre of boom travel (per release at a cone station), times a
    lognormal factor of coefficient of variation ``rate_cv`` drawn from ``rng``.
    """
    n = len(segs)
    w = np.ones(n)
    if rate_cv > 0:
        sig = math.sqrt(math.log(1.0 + rate_cv ** 2))
        w = rng.lognormal(-0.5 * sig * sig, sig, n)
    w_lengths = np.array([max(math.hypot(s[2] - s[0], s[3] - s[1]), 0.0) for s in segs])
    if pattern is not Pattern.CONE_SHELL and w_lengths.sum() > 0:
        w = w * w_lengths  # uniform tonnes per metre of boom travel
    return w / w.sum()


def release_times(shares: np.ndarray, t_start_ns: int, t_end_ns: int) -> list[int]:
    """Each release's time (UTC ns): the middle of its share of the pass's time, in
    ``[t_start_ns, t_end_ns]`` (each release covers time in proportion to its tonnes)."""
    edges = np.concatenate([[0.0], np.cumsum(shares)])
    edges[-1] = 1.0
    mids = 0.5 * (edges[:-1] + edges[1:])
    dur = t_end_ns - t_start_ns
    times = []
    for m in mids:
        tm = t_start_ns + int(round(dur * float(m)))
        times.append(min(max(tm, t_start_ns), t_end_ns))
    return times


def chevron_pile(world, *, x_centre_m: float, y_start_m: float, y_end_m: float,
                 passes: Iterable[dict], t0_ns: int, pass_duration_ns: int,
                 gap_ns: int = 0, **kwargs) -> list[dict]:
    """Convenience: stack consecutive chevron passes on a :class:`~sim.world.World`,
    alternating direction.

    ``passes`` items: {"tonnes", "lot", "grade_fn" (or "grade"), optional "deposit_id",
    "density_t_m3"}. Returns the pass records."""
    out = []
    t = int(t0_ns)
    for i, p in enumerate(passes):
        gf = p.get("grade_fn")
        if gf is None:
            gconst = p["grade"]
            gf = (lambda _t, _g=gconst: _g)
        a, b = (y_start_m, y_end_m) if i % 2 == 0 else (y_end_m, y_start_m)
        out.append(world.stack_pass(Pattern.CHEVRON, a, b, x_centre_m, p["tonnes"], t,
                                    t + int(pass_duration_ns), p.get("deposit_id", i), p["lot"],
                                    gf, p.get("density_t_m3", DEFAULT_DENSITY_T_M3), **kwargs))
        t += int(pass_duration_ns) + int(gap_ns)
    return out

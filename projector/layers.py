"""The pile as a monotone stack of surfaces, one band per deposit.

Every column of the grid holds the surfaces ``S0 (ground) <= S1 <= ... <= Sn``; the band
``(S(k-1), S(k)]`` of a column is the material of deposit ``k`` (1-based: deposit ``k`` is
the ``k``-th one opened).  Deposits only ever open on top, so the order of the bands is the
order of deposition.

- :meth:`LayerStack.open_deposit` adds a band of zero thickness on top;
- :meth:`LayerStack.raise_to` puts the material between the top and a higher observed
  surface into the *top* deposit;
- :meth:`LayerStack.add_material` inserts material of one deposit into its band (slumped
  material landing on a toe, :mod:`projector.slump`);
- :meth:`LayerStack.clamp` lowers every surface above a floor to the floor (a reclaimer cut,
  :func:`projector.envelope.cut_floor`) and reports what it removed per deposit;
- :meth:`LayerStack.fit_boundaries` replaces buried surfaces by a local quadratic fit
  (:mod:`projector.surface_fit`): their per-cell noise, never measured again, would
  otherwise mix deposits wherever a cut's floor passes close to them.

A band is well mixed per column, like the simulator's parcels: material of one deposit that
reaches a column at different times keeps one thickness-weighted mean deposition time, and a
partly removed band keeps that time.

Stacks are immutable values: every operation returns a new stack, which shares the arrays it
did not change with the old one (copy-on-write per array).  The arrays handed out are
read-only; copy them to modify them.  Times are UTC nanoseconds; per-cell deposition times
are returned as float64 (about 256 ns resolution at current epochs); internally they are
kept relative to the first raise's time (about 1 ns resolution over 100 days).  The
deposits and what a clamp removed are value types of :mod:`projector.deposits`.
"""

from __future__ import annotations

import numpy as np

from projector.deposits import DepositInfo, DepositRemoval, Removal, removal_of_drops
from projector.grid import GridGeometry
from projector.surface_fit import check_window, fit_local_quadratic, fit_top_above_floor

__all__ = ["DepositInfo", "DepositRemoval", "Removal", "LayerStack"]


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _mixed_time(t_old, old_m, t_add, add_m):
    """Deposition time (ns) of a band's material after ``add_m`` (m, > 0) arriving at
    ``t_add`` joins ``old_m`` (m, >= 0) deposited at ``t_old``: their thickness-weighted
    mean (``t_add`` where there was none)."""
    return np.where(old_m > 0, (t_old * old_m + t_add * add_m) / (old_m + add_m), t_add)


def _check_layer(geometry: GridGeometry, values, name: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != geometry.shape:
        raise ValueError(f"{name} must have shape {geometry.shape} (nx, ny), got {arr.shape}")
    return arr


class LayerStack:
    """An immutable stack of surfaces ``S0 <= S1 <= ... <= Sn`` on one grid (module docstring).

    Build one with :meth:`empty`; every operation returns a new stack.
    """

    __slots__ = ("_geometry", "_surfaces", "_times", "_infos", "_epoch_ns")

    def __init__(self, geometry: GridGeometry, surfaces: tuple[np.ndarray, ...],
                 times_rel: tuple[np.ndarray, ...], infos: tuple[DepositInfo, ...],
                 epoch_ns: int | None) -> None:
        if len(surfaces) != len(infos) + 1 or len(times_rel) != len(infos):
            raise ValueError("a stack needs n + 1 surfaces and n time layers for n deposits")
        self._geometry = geometry
        self._surfaces = surfaces
        self._times = times_rel
        self._infos = infos
        self._epoch_ns = epoch_ns

    # ------------------------------------------------------------------ construction
    @classmethod
    def empty(cls, geometry: GridGeometry, ground_z_m) -> "LayerStack":
        """A stack with no deposits on the ground ``ground_z_m``.

        Parameters
        ----------
        geometry : GridGeometry
        ground_z_m : float or array_like, shape (nx, ny)
            Ground level (m), finite.
        """
        ground = np.broadcast_to(np.asarray(ground_z_m, dtype=np.float64), geometry.shape).copy()
        if not np.all(np.isfinite(ground)):
            raise ValueError("the ground level must be finite everywhere")
        return cls(geometry, (_frozen(ground),), (), (), None)

    def copy(self) -> "LayerStack":
        """An independent deep copy (stacks are immutable, so this is rarely needed)."""
        return LayerStack(self._geometry, tuple(_frozen(s.copy()) for s in self._surfaces),
                          tuple(_frozen(t.copy()) for t in self._times), self._infos,
                          self._epoch_ns)

    # ------------------------------------------------------------------ accessors
    @property
    def geometry(self) -> GridGeometry:
        return self._geometry

    @property
    def n_deposits(self) -> int:
        """Number of deposits n (bands)."""
        return len(self._infos)

    @property
    def deposits(self) -> tuple[DepositInfo, ...]:
        """The deposits, bottom (index 1) to top (index n)."""
        return self._infos

    def info(self, k: int) -> DepositInfo:
        """The deposit with index ``k`` (1-based)."""
        self._check_k(k)
        return self._infos[k - 1]

    def ground(self) -> np.ndarray:
        """S0, the ground, shape (nx, ny) (m, read-only)."""
        return self._surfaces[0]

    def surface(self) -> np.ndarray:
        """Sn, the top surface, shape (nx, ny) (m, read-only)."""
        return self._surfaces[-1]

    def surface_k(self, k: int) -> np.ndarray:
        """S(k), the top of deposit ``k`` (``k = 0``: the ground), shape (nx, ny) (read-only)."""
        if isinstance(k, bool) or not 0 <= int(k) <= self.n_deposits:
            raise ValueError(f"surface index must be in 0..{self.n_deposits}, got {k!r}")
        return self._surfaces[int(k)]

    def surfaces(self) -> np.ndarray:
        """All surfaces stacked, shape (n + 1, nx, ny) (m, a new array)."""
        return np.stack(self._surfaces)

    def band(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(S(k-1), S(k))``: bottom and top of deposit ``k``, each (nx, ny) (read-only)."""
        self._check_k(k)
        return self._surfaces[k - 1], self._surfaces[k]

    def thickness(self, k: int) -> np.ndarray:
        """Thickness of deposit ``k`` per cell, ``S(k) - S(k-1)``, shape (nx, ny) (m, >= 0)."""
        lo, hi = self.band(k)
        return hi - lo

    def deposition_time_ns(self, k: int) -> np.ndarray:
        """When deposit ``k``'s material in each cell arrived, shape (nx, ny), float64 UTC ns.

        The thickness-weighted mean over the material of the deposit in that cell; NaN where
        the deposit has no material.
        """
        cells, _thick, times = self.deposit_cells(k)
        out = np.full(self._geometry.shape, np.nan)
        out.ravel()[cells] = times
        return out

    def deposit_cells(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Deposit ``k``'s material where it has any: ``(cells, thickness_m, time_ns)``.

        ``cells`` are flat indices into ``(nx, ny)`` (ascending), ``thickness_m`` > 0 their
        band thickness (m) and ``time_ns`` their :meth:`deposition_time_ns` (float64 UTC
        ns): the same figures without forming the full-grid arrays.
        """
        lo, hi = self.band(k)
        thick = (hi - lo).ravel()
        cells = np.flatnonzero(thick > 0)
        epoch = float(self._epoch_ns) if self._epoch_ns is not None else 0.0
        return cells, thick[cells], self._times[k - 1].ravel()[cells] + epoch

    def volume_m3(self, k: int) -> float:
        """Volume of deposit ``k`` (m3)."""
        return float(np.sum(self.thickness(k)) * self._geometry.cell_area_m2)

    def total_volume_m3(self) -> float:
        """Volume of the whole pile, ``sum(Sn - S0) * cell area`` (m3)."""
        return float(np.sum(self._surfaces[-1] - self._surfaces[0]) * self._geometry.cell_area_m2)

    @property
    def epoch_ns(self) -> int | None:
        """The reference time of the internal relative times (the first raise's), or None."""
        return self._epoch_ns

    def _check_k(self, k) -> None:
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) \
                or not 1 <= int(k) <= self.n_deposits:
            raise ValueError(f"deposit index must be an int in 1..{self.n_deposits}, got {k!r}")

    # ------------------------------------------------------------------ operations
    def open_deposit(self, info: DepositInfo) -> "LayerStack":
        """A new deposit on top, of zero thickness everywhere.

        Parameters
        ----------
        info : DepositInfo
            Its ``index`` must be ``n_deposits + 1``.
        """
        if not isinstance(info, DepositInfo):
            raise TypeError(f"info must be a DepositInfo, got {type(info).__name__}")
        if info.index != self.n_deposits + 1:
            raise ValueError(f"the next deposit's index is {self.n_deposits + 1}, "
                             f"got {info.index}")
        zeros = _frozen(np.zeros(self._geometry.shape))
        # the new top surface is the old one: share the (read-only) array
        return LayerStack(self._geometry, self._surfaces + (self._surfaces[-1],),
                          self._times + (zeros,), self._infos + (info,), self._epoch_ns)

    def raise_to(self, surface_m, t_ns) -> tuple["LayerStack", float]:
        """Add the material between the top and a higher observed surface to the top deposit.

        Parameters
        ----------
        surface_m : array_like, shape (nx, ny)
            Observed surface (m); NaN = no observation.  Cells where it is at or below the top
            are left alone (lowering happens only through :meth:`clamp`).
        t_ns : int or ndarray, shape (nx, ny)
            When the material arrived (UTC ns): one integer for every cell, or a float64
            array giving each cell's time (finite where the surface rises).

        Returns
        -------
        stack : LayerStack
        added_m3 : float
            The volume added (m3).

        Raises
        ------
        ValueError
            On a wrong shape, +inf heights, a non-finite time where the surface rises, or
            a stack with no deposit.
        TypeError
            When ``t_ns`` is neither an integer nor an array.
        """
        if isinstance(t_ns, np.ndarray):
            times = _check_layer(self._geometry, t_ns, "t_ns")
        elif isinstance(t_ns, bool) or not isinstance(t_ns, (int, np.integer)):
            raise TypeError(f"t_ns must be an integer (UTC ns) or an (nx, ny) array, "
                            f"got {type(t_ns).__name__}")
        else:
            times = None
        surf = _check_layer(self._geometry, surface_m, "surface_m")
        if np.any(np.isposinf(surf)):
            raise ValueError("surface_m must not contain +inf (NaN = no observation)")
        if self.n_deposits == 0:
            raise ValueError("no deposit is open: open_deposit() before raise_to()")
        top = self._surfaces[-1]
        with np.errstate(invalid="ignore"):
            up = surf > top  # NaN compares False
        if not up.any():
            return self, 0.0
        if times is None:
            epoch = int(t_ns) if self._epoch_ns is None else self._epoch_ns
            t_rel = float(int(t_ns) - epoch)
        else:
            t_up = times[up]
            if not np.isfinite(t_up).all():
                raise ValueError("t_ns must be finite wherever the surface rises")
            epoch = int(t_up.min()) if self._epoch_ns is None else self._epoch_ns
            t_rel = t_up - float(epoch)
        lower = self._surfaces[-2]
        old = (top - lower)[up]
        add = surf[up] - top[up]
        new_top = top.copy()
        new_top[up] = surf[up]
        new_time = self._times[-1].copy()
        t_old = new_time[up]
        new_time[up] = _mixed_time(t_old, old, t_rel, add)
        stack = LayerStack(self._geometry, self._surfaces[:-1] + (_frozen(new_top),),
                           self._times[:-1] + (_frozen(new_time),), self._infos, epoch)
        return stack, float(np.sum(add) * self._geometry.cell_area_m2)

    def raise_deposit(self, k: int, surface_m, t_ns) -> tuple["LayerStack", np.ndarray]:
        """Add material to deposit ``k`` where every band above it is empty.

        In cells where the surface is above the top and deposits ``k+1 .. n`` have no
        material, surfaces ``S(k) .. S(n)`` rise to it together, so the new material
        lies in band ``k`` (material stacked by an earlier pass, seen late).  Other
        cells are left alone.

        Parameters
        ----------
        k : int
            The deposit (1-based).
        surface_m : array_like, shape (nx, ny)
            Observed surface (m); NaN = no observation.
        t_ns : int or array_like, shape (nx, ny)
            When the material arrived (UTC ns), per cell or for all.

        Returns
        -------
        stack : LayerStack
        raised : ndarray of bool, shape (nx, ny)
            The cells that received material.
        """
        self._check_k(k)
        surf = _check_layer(self._geometry, surface_m, "surface_m")
        cells = np.flatnonzero(np.isfinite(surf))
        t = np.broadcast_to(np.asarray(t_ns, dtype=np.float64), self._geometry.shape)
        stack, (raised_cells,) = self.raise_deposits([(k, cells, surf.ravel()[cells],
                                                       t.ravel()[cells])])
        up = np.zeros(self._geometry.shape, bool)
        up.ravel()[cells[raised_cells]] = True
        return stack, up

    def raise_deposits(self, updates) -> tuple["LayerStack", list[np.ndarray]]:
        """:meth:`raise_deposit` for several deposits in turn, each surface copied once.

        Parameters
        ----------
        updates : sequence of ``(k, cells, surface_m, t_ns)``
            Applied in order, each seeing the stack the ones before left: ``k`` the deposit
            (1-based); ``cells`` flat cell indices (into ``(nx, ny)``, distinct);
            ``surface_m`` their observed surface (m, NaN = none); ``t_ns`` when their
            material arrived (UTC ns, float array or one value).

        Returns
        -------
        stack : LayerStack
        raised : list of ndarray of bool
            Per update, which of its ``cells`` received material.
        """
        n = self.n_deposits
        surfaces, times = list(self._surfaces), list(self._times)
        owned_s, owned_t = set(), set()   # arrays copied (writable) in this call
        epoch = self._epoch_ns
        raised_all = []
        for k, cells, surf_c, t_c in updates:
            self._check_k(k)
            cells = np.asarray(cells, dtype=np.int64).ravel()
            surf_c = np.asarray(surf_c, dtype=np.float64).ravel()
            if surf_c.shape != cells.shape or (cells.size and (
                    cells.min() < 0 or cells.max() >= self._geometry.nx * self._geometry.ny)):
                raise ValueError("cells must be flat indices into the grid, one surface each")
            t_c = np.broadcast_to(np.asarray(t_c, dtype=np.float64), cells.shape)
            with np.errstate(invalid="ignore"):
                keep = surf_c > surfaces[-1].ravel()[cells]
            # only where every band above k is empty
            for j in range(k + 1, n + 1):
                if not keep.any():
                    break
                keep &= surfaces[j].ravel()[cells] <= surfaces[j - 1].ravel()[cells]
            raised_all.append(keep)
            if not keep.any():
                continue
            c, z = cells[keep], surf_c[keep]
            if epoch is None:
                epoch = int(np.nanmin(t_c[keep]))
            t_rel = t_c[keep] - float(epoch)
            old = surfaces[k].ravel()[c] - surfaces[k - 1].ravel()[c]
            add = z - surfaces[-1].ravel()[c]
            for j in range(k, n + 1):
                if j not in owned_s:
                    surfaces[j] = surfaces[j].copy()
                    owned_s.add(j)
                surfaces[j].ravel()[c] = z
            if k - 1 not in owned_t:
                times[k - 1] = times[k - 1].copy()
                owned_t.add(k - 1)
            tv = times[k - 1].ravel()
            tv[c] = _mixed_time(tv[c], old, t_rel, add)
        if not owned_s:
            return self, raised_all
        return LayerStack(self._geometry, tuple(_frozen(a) for a in surfaces),
                          tuple(_frozen(a) for a in times), self._infos, epoch), raised_all

    def add_material(self, k: int, thickness_m, t_ns) -> "LayerStack":
        """Insert material of deposit ``k`` into every column: its band grows by ``thickness_m``.

        Surfaces ``S(k) .. S(n)`` rise by the thickness, so bands above ``k`` keep their
        thickness and sit on the new material (material slid down a face lands on a toe
        whose later bands, if any, are thin; the column keeps its composition).

        Parameters
        ----------
        k : int
            The deposit (1-based).
        thickness_m : array_like, shape (nx, ny)
            Added thickness (m, >= 0; NaN or 0 = nothing).
        t_ns : float or array_like, shape (nx, ny)
            When the added material was deposited (UTC ns), per cell or for all.

        Returns
        -------
        LayerStack

        Raises
        ------
        ValueError
            On a wrong shape or a negative thickness.
        """
        self._check_k(k)
        add = np.nan_to_num(_check_layer(self._geometry, thickness_m, "thickness_m"), nan=0.0)
        if np.any(add < 0):
            raise ValueError("thickness_m must be >= 0")
        cells = add > 0
        if not cells.any():
            return self
        t = np.broadcast_to(np.asarray(t_ns, dtype=np.float64), self._geometry.shape)
        epoch = int(np.nanmin(t[cells])) if self._epoch_ns is None else self._epoch_ns
        surfaces = list(self._surfaces)
        old = (self._surfaces[k] - self._surfaces[k - 1])[cells]
        for j in range(k, self.n_deposits + 1):
            surfaces[j] = _frozen(self._surfaces[j] + add)
        times = list(self._times)
        new_time = times[k - 1].copy()
        t_rel = t[cells] - float(epoch)
        a = add[cells]
        new_time[cells] = _mixed_time(new_time[cells], old, t_rel, a)
        times[k - 1] = _frozen(new_time)
        return LayerStack(self._geometry, tuple(surfaces), tuple(times), self._infos, epoch)

    def scaled(self, factor) -> "LayerStack":
        """Every band scaled about the ground by ``factor`` per cell (``(nx, ny)``, finite,
        >= 0; 1 leaves a column as it is): each deposit keeps its share of the column's
        material and its deposition times (a rebase on a survey, :mod:`projector.rebase`).
        """
        f = np.asarray(factor, dtype=np.float64)
        if f.shape != self._geometry.shape:
            raise ValueError(f"factor must have shape {self._geometry.shape}, got {f.shape}")
        if not np.all(np.isfinite(f) & (f >= 0)):
            raise ValueError("factor must be finite and >= 0")
        ground = self._surfaces[0]
        surfaces = (ground,) + tuple(_frozen(ground + (s - ground) * f)
                                     for s in self._surfaces[1:])
        return LayerStack(self._geometry, surfaces, self._times, self._infos, self._epoch_ns)

    def fit_top_above(self, floor_m, window: int = 7) -> "LayerStack":
        """The stack with its top, where it or its fit stands above ``floor_m``, replaced
        by a local quadratic fit: the surface a cut down to that floor is measured on.

        The volume above a floor of a surface with per-cell noise is biased high where
        the surface runs close to the floor: ``E[max(z + e - f, 0)] > max(z - f, 0)``.
        A cut's first slice of a freshly stacked pile is a few cell-noises thick, so the
        bias is a few percent of it.  A local quadratic fit over the top deposit's cells
        takes most of the noise out; the fit replaces the top where it or the top stands
        above the floor, never below the floor or the deposit under the top one (the top
        deposit's material and deposition times stay, its thickness moves;
        :func:`projector.surface_fit.fit_top_above_floor`).

        Parameters
        ----------
        floor_m : array_like, shape (nx, ny)
            The floor (m), NaN outside the cut.
        window : int
            The fit's square, in cells (odd, >= 3).

        Raises
        ------
        ValueError
            On a floor of another shape or a bad window.
        """
        check_window(window)
        floor = np.asarray(floor_m, dtype=np.float64)
        if floor.shape != self._geometry.shape:
            raise ValueError(f"floor_m must have shape {self._geometry.shape}, got {floor.shape}")
        n = self.n_deposits
        if n == 0:
            return self
        top = fit_top_above_floor(self._surfaces[n - 1], self._surfaces[n], floor, window)
        if top is None:
            return self
        surfaces = list(self._surfaces)
        surfaces[n] = _frozen(top)
        return LayerStack(self._geometry, tuple(surfaces), self._times, self._infos,
                          self._epoch_ns)

    def fit_boundaries(self, ks, window: int = 7) -> "LayerStack":
        """The stack with the tops of deposits ``ks`` replaced by a local quadratic fit.

        A deposit's top is the height map as it last saw it, per cell, with each cell's
        noise; once the next deposit covers it, no scan measures it again.  Where a cut's
        floor passes close to it, that noise decides per cell which deposit the cut takes,
        and takes more of the lower one than a smooth boundary would (wherever the noise
        lifted the boundary above the floor).  A local quadratic fit
        (:func:`projector.surface_fit.fit_local_quadratic`) over the cells where both
        deposit ``k`` and deposit ``k + 1`` have material replaces it there, kept between
        ``S(k-1)`` and ``S(k+1)``: material moves between the two deposits only, each
        cell's top and deposition times stay.

        Parameters
        ----------
        ks : iterable of int
            Deposits below the top one (``1 <= k < n_deposits``).
        window : int
            The fit's square, in cells (odd, >= 3).

        Raises
        ------
        ValueError
            On a ``k`` out of range (the top deposit's top is the measured surface) or a
            bad window.
        """
        check_window(window)
        ks = sorted(set(ks))
        for k in ks:
            self._check_k(k)
        surfaces = list(self._surfaces)
        for k in map(int, ks):
            if k == self.n_deposits:
                raise ValueError(f"deposit {k} is the top one: its top is the measured surface")
            lo, z, hi = surfaces[k - 1], surfaces[k], surfaces[k + 1]
            mask = (z > lo) & (hi > z)
            if not mask.any():
                continue
            fitted = np.clip(fit_local_quadratic(z, mask, window), lo, hi)
            surfaces[k] = _frozen(np.where(mask, fitted, z))
        return LayerStack(self._geometry, tuple(surfaces), self._times, self._infos,
                          self._epoch_ns)

    def clamp(self, floor_m) -> tuple["LayerStack", Removal]:
        """Lower every surface above a floor to it: ``S(k) = min(S(k), floor)`` for k >= 1.

        The floor never goes below the ground (material is not removed below S0).

        Parameters
        ----------
        floor_m : array_like, shape (nx, ny)
            Floor (m); +inf = untouched (e.g. :func:`projector.envelope.cut_floor`).

        Returns
        -------
        stack : LayerStack
        removal : Removal
            What was removed, per deposit, with per-cell volumes and deposition times.

        Raises
        ------
        ValueError
            On a wrong shape or NaN in the floor.
        """
        floor = _check_layer(self._geometry, floor_m, "floor_m")
        if np.any(np.isnan(floor)):
            raise ValueError("floor_m must not contain NaN (+inf = untouched)")
        top = self._surfaces[-1]
        cut = np.flatnonzero(floor < top)
        if cut.size == 0 or self.n_deposits == 0:
            return self, Removal()
        f = np.maximum(floor.ravel()[cut], self._surfaces[0].ravel()[cut])
        surfaces = list(self._surfaces)
        lowered = []  # lowered[k] = S(k) - S'(k) at the cut cells, k = n, n-1, ...
        for k in range(self.n_deposits, 0, -1):
            s_k = self._surfaces[k].ravel()[cut]
            drop = s_k - np.minimum(s_k, f)
            if not np.any(drop > 0):
                break  # monotone: no lower surface is above the floor either
            new = self._surfaces[k].copy()
            new.ravel()[cut] = np.minimum(s_k, f)
            surfaces[k] = _frozen(new)
            lowered.append((k, drop))
        if not lowered:
            return self, Removal()
        lowered.reverse()  # bottom-most lowered surface first
        removal = removal_of_drops(cut, lowered, self._geometry, self._infos, self._times,
                                   self._epoch_ns)
        stack = LayerStack(self._geometry, tuple(surfaces), self._times, self._infos,
                           self._epoch_ns)
        return stack, removal

    def __repr__(self) -> str:
        return (f"LayerStack({self._geometry.nx}x{self._geometry.ny} cells, "
                f"{self.n_deposits} deposits, {self.total_volume_m3():.3f} m3)")

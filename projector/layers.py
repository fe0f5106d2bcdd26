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
  (:func:`fit_local_quadratic`): their per-cell noise, never measured again, would
  otherwise mix deposits wherever a cut's floor passes close to them.

A band is well mixed per column, like the simulator's parcels: material of one deposit that
reaches a column at different times keeps one thickness-weighted mean deposition time, and a
partly removed band keeps that time.

Stacks are immutable values: every operation returns a new stack, which shares the arrays it
did not change with the old one (copy-on-write per array).  The arrays handed out are
read-only; copy them to modify them.  Times are UTC nanoseconds; per-cell deposition times
are returned as float64 (about 256 ns resolution at current epochs); internally they are
kept relative to the first raise's time (about 1 ns resolution over 100 days).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from projector.grid import GridGeometry

__all__ = ["DepositInfo", "DepositRemoval", "Removal", "LayerStack", "fit_local_quadratic"]


@dataclass(frozen=True)
class DepositInfo:
    """What a deposit is: one stacking pass (or material that rose outside any pass).

    Attributes
    ----------
    index : int
        1-based position in the stack: the band ``(S(index-1), S(index)]``.
    pass_id : str
        The stacking pass (``""`` when none).
    lot_id : str
        The lot stacked (``""`` when unknown).
    opened_ns : int
        When the deposit was opened (UTC ns).
    flagged : bool
        True for material that rose outside any stacking pass.
    """

    index: int
    pass_id: str
    lot_id: str
    opened_ns: int
    flagged: bool = False


@dataclass(frozen=True, eq=False)
class DepositRemoval:
    """What one clamp removed from one deposit.

    Attributes
    ----------
    index : int
        The deposit (1-based).
    info : DepositInfo
    volume_m3 : float
        Total removed volume (m3).
    ix, iy : ndarray, shape (m,), int64
        The cells some of the deposit was removed from.
    cell_volume_m3 : ndarray, shape (m,)
        Removed volume per cell (m3, > 0).
    deposition_time_ns : ndarray, shape (m,), float64
        When the removed material arrived in that cell (UTC ns): the band's
        thickness-weighted mean deposition time.
    """

    index: int
    info: DepositInfo
    volume_m3: float
    ix: np.ndarray
    iy: np.ndarray
    cell_volume_m3: np.ndarray
    deposition_time_ns: np.ndarray

    @property
    def mean_deposition_time_ns(self) -> float:
        """Volume-weighted mean deposition time of the removed material (UTC ns)."""
        if self.volume_m3 <= 0:
            return math.nan
        return float(np.sum(self.cell_volume_m3 * self.deposition_time_ns) / self.volume_m3)


@dataclass(frozen=True, eq=False)
class Removal:
    """What one :meth:`LayerStack.clamp` removed, per deposit (only deposits that lost material).

    Attributes
    ----------
    deposits : tuple of DepositRemoval
        In deposit order (bottom to top).
    """

    deposits: tuple[DepositRemoval, ...] = ()

    @property
    def volume_m3(self) -> float:
        """Total removed volume (m3)."""
        return float(sum(d.volume_m3 for d in self.deposits))

    def by_index(self) -> dict[int, DepositRemoval]:
        """The removals keyed by deposit index."""
        return {d.index: d for d in self.deposits}

    def within(self, mask) -> "Removal":
        """The part of this removal in the cells where ``mask`` (bool, (nx, ny)) is True."""
        mask = np.asarray(mask, dtype=bool)
        parts = []
        for d in self.deposits:
            sel = mask[d.ix, d.iy]
            if sel.any():
                vol = d.cell_volume_m3[sel]
                parts.append(DepositRemoval(d.index, d.info, float(np.sum(vol)), d.ix[sel],
                                            d.iy[sel], vol, d.deposition_time_ns[sel]))
        return Removal(tuple(parts))

    def removed_m(self, geometry: GridGeometry) -> np.ndarray:
        """Removed thickness per cell, all deposits, shape (nx, ny) (m)."""
        out = np.zeros(geometry.shape)
        for d in self.deposits:
            np.add.at(out, (d.ix, d.iy), d.cell_volume_m3 / geometry.cell_area_m2)
        return out


def _quadratic_basis(window: int) -> np.ndarray:
    """The terms ``1, dx, dy, dx^2, dx dy, dy^2`` at each offset of a square window,
    shape (window * window, 6), offsets in cells, row-major over (dx, dy)."""
    half = window // 2
    dx, dy = np.meshgrid(np.arange(-half, half + 1, dtype=np.float64),
                         np.arange(-half, half + 1, dtype=np.float64), indexing="ij")
    dx, dy = dx.ravel(), dy.ravel()
    return np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=1)


def _check_window(window) -> None:
    if isinstance(window, bool) or not isinstance(window, (int, np.integer)) \
            or window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd int >= 3, got {window!r}")


def fit_local_quadratic(z_m, mask, window: int = 7) -> np.ndarray:
    """Each masked cell's value on the least-squares quadratic surface through the masked
    cells of the ``window`` x ``window`` square around it.

    A surface estimated per cell carries each cell's own noise.  The fit takes it down
    (the standard deviation times 0.39, 0.27 and 0.21 for full 5, 7 and 9 cell windows)
    and, unlike a mean, returns any surface that is quadratic over the window unchanged:
    a plane, a rounded crest, a toe, also where the mask cuts the window short.

    Parameters
    ----------
    z_m : array_like, shape (nx, ny)
        The surface (m).
    mask : array_like of bool, shape (nx, ny)
        The cells to fit and to fit from (NaN cells never count).
    window : int
        The square's edge in cells: odd, >= 3.

    Returns
    -------
    ndarray, shape (nx, ny), float64
        The fit on the masked cells.  Elsewhere ``z_m``; also where a window's masked cells
        do not determine a quadratic (fewer than six, or all on two lines).

    Raises
    ------
    ValueError
        On shapes that differ or are not 2-D, or a window that is even or below 3.
    """
    z = np.asarray(z_m, dtype=np.float64)
    m = np.asarray(mask, dtype=bool)
    if z.ndim != 2 or m.shape != z.shape:
        raise ValueError(f"z_m and mask must be 2-D of one shape, got {z.shape} and {m.shape}")
    _check_window(window)
    m = m & np.isfinite(z)
    out = z.copy()
    if not m.any():
        return out
    window, half = int(window), int(window) // 2
    basis = _quadratic_basis(window)
    # a full window: one fixed kernel, the least-squares weights of the centre value
    # (Savitzky-Golay)
    centre = np.linalg.pinv(basis)[0].reshape(window, window)
    zm = np.where(m, z, 0.0)
    counts = ndimage.correlate(m.astype(np.float64), np.ones((window, window)), mode="constant")
    full = m & (counts > window * window - 0.5)
    out[full] = ndimage.correlate(zm, centre, mode="constant")[full]
    # a window the mask cuts short: its own least squares, from the cells it holds
    part = np.flatnonzero(m & ~full)
    if part.size:
        ny = z.shape[1]
        zp, mp = np.pad(zm, half), np.pad(m, half)
        ix, iy = np.unravel_index(part, z.shape)
        offsets = (np.arange(window)[:, None] * (ny + 2 * half)
                   + np.arange(window)[None, :]).ravel()
        flat = (ix * (ny + 2 * half) + iy)[:, None] + offsets[None, :]   # window's top-left
        w = mp.ravel()[flat].astype(np.float64)                           # (p, window^2)
        products = (basis[:, :, None] * basis[:, None, :]).reshape(len(basis), 36)
        a = (w @ products).reshape(-1, 6, 6)                      # the normal equations
        b = (w * zp.ravel()[flat]) @ basis
        # singular where the cells do not determine a quadratic: the determinant against
        # the product of the diagonal (1 for orthogonal terms, 0 for dependent ones)
        sign, logdet = np.linalg.slogdet(a)
        diagonal = np.einsum("pii->pi", a)
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = (sign > 0) & (logdet - np.sum(np.log(diagonal), axis=1) > math.log(1e-10))
        if ok.any():
            sol = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
            out.ravel()[part[ok]] = sol[:, 0]
    return out


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


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
        new_time[up] = np.where(old > 0, (t_old * old + t_rel * add) / (old + add), t_rel)
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
            tv[c] = np.where(old > 0, (tv[c] * old + t_rel * add) / (old + add), t_rel)
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
        new_time[cells] = np.where(old > 0, (new_time[cells] * old + t_rel * a) / (old + a), t_rel)
        times[k - 1] = _frozen(new_time)
        return LayerStack(self._geometry, tuple(surfaces), tuple(times), self._infos, epoch)

    def fit_top_above(self, floor_m, window: int = 7) -> "LayerStack":
        """The stack with its top, where it or its fit stands above ``floor_m``, replaced
        by a local quadratic fit: the surface a cut down to that floor is measured on.

        The volume above a floor of a surface with per-cell noise is biased high where
        the surface runs close to the floor: ``E[max(z + e - f, 0)] > max(z - f, 0)``.
        A cut's first slice of a freshly stacked pile is a few cell-noises thick, so the
        bias is a few percent of it.  :func:`fit_local_quadratic` over the top deposit's
        cells takes most of the noise out; the fit replaces the top where it or the top
        stands above the floor, never below the floor or the deposit under the top one
        (the top deposit's material and deposition times stay, its thickness moves).

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
        _check_window(window)
        floor = np.asarray(floor_m, dtype=np.float64)
        if floor.shape != self._geometry.shape:
            raise ValueError(f"floor_m must have shape {self._geometry.shape}, got {floor.shape}")
        n = self.n_deposits
        if n == 0:
            return self
        ix, iy = np.nonzero(np.isfinite(floor))
        if ix.size == 0:
            return self
        # the fit at a cell sees the window around it: the floor's block, padded by half
        # a window, gives the same values there as the whole grid would
        pad = window // 2
        block = (slice(max(0, ix.min() - pad), ix.max() + pad + 1),
                 slice(max(0, iy.min() - pad), iy.max() + pad + 1))
        lo, z, f = self._surfaces[n - 1][block], self._surfaces[n][block], floor[block]
        mask = z > lo
        if not mask.any():
            return self
        fitted = fit_local_quadratic(z, mask, window)
        with np.errstate(invalid="ignore"):
            near = mask & np.isfinite(f) & ((z > f) | (fitted > f))
        if not near.any():
            return self
        top = np.array(self._surfaces[n])
        top[block] = np.where(near, np.maximum(np.fmax(fitted, f), lo), z)
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
        lifted the boundary above the floor).  :func:`fit_local_quadratic` over the cells
        where both deposit ``k`` and deposit ``k + 1`` have material replaces it there, kept
        between ``S(k-1)`` and ``S(k+1)``: material moves between the two deposits only,
        each cell's top and deposition times stay.

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
        _check_window(window)
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
        shape = self._geometry.shape
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
        area = self._geometry.cell_area_m2
        epoch = float(self._epoch_ns) if self._epoch_ns is not None else 0.0
        removals = []
        lowered.reverse()  # bottom-most lowered surface first
        below = np.zeros(cut.size)
        for k, drop in lowered:
            removed = drop - below  # (S(k) - S'(k)) - (S(k-1) - S'(k-1)) >= 0
            below = drop
            sel = removed > 0
            if not sel.any():
                continue
            cells = cut[sel]
            ix, iy = np.unravel_index(cells, shape)
            vol = removed[sel] * area
            removals.append(DepositRemoval(
                index=k, info=self._infos[k - 1], volume_m3=float(np.sum(vol)),
                ix=ix.astype(np.int64), iy=iy.astype(np.int64), cell_volume_m3=vol,
                deposition_time_ns=self._times[k - 1].ravel()[cells] + epoch))
        stack = LayerStack(self._geometry, tuple(surfaces), self._times, self._infos,
                           self._epoch_ns)
        return stack, Removal(tuple(removals))

    def __repr__(self) -> str:
        return (f"LayerStack({self._geometry.nx}x{self._geometry.ny} cells, "
                f"{self.n_deposits} deposits, {self.total_volume_m3():.3f} m3)")

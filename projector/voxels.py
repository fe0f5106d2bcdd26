"""Exact voxel integration of deposit bands: quality-volumetric objects (thesis §5.2.2.1).

A voxel grid of edge ``voxel_m`` lies over the layer grid: ``voxel_m`` is an integer
multiple ``m`` of the cell edge, voxel column ``(vx, vy)`` holds the ``m x m`` cells
``ix // m == vx, iy // m == vy`` (the last voxel row or column may hold fewer cells when
``nx`` or ``ny`` is not a multiple of ``m``) and z bin ``iz`` spans
``[z0 + iz * voxel_m, z0 + (iz + 1) * voxel_m)`` with ``z0`` the lowest ground level.

For every cell and every deposit band ``(lo, hi]`` the part of the band in z bin
``[z_a, z_b)`` has exactly the volume ``max(0, min(hi, z_b) - max(lo, z_a)) * cell area``;
these pieces summed over the cells of a voxel column are the QVOs (the part of a voxel that
lies in one deposit).  Nothing is sampled: the total of all voxels equals the stack's volume
to rounding.

Weights turn volumes into tonnes and grades: pass, per deposit, per-cell weights such as
``density`` (t/m3) and ``density * grade / 100`` per analyte; ``weighted[..., a]`` is then the
sum over the voxel's pieces of volume x weight (tonnes, tonnes of analyte), and a voxel's
grade is ``100 * weighted[..., 1 + a] / weighted[..., 0]``.

Cost: per deposit a few vectorised passes over the cells with material (into buffers
reused by every deposit) and, for the weights, one bincount of the pieces per (grade
class, QVO) (:class:`ClassWeights`, the form the query uses) or one sparse-dense product
(per-cell weight arrays); no cells x deposits x bins cube is formed, and the QVO table is
written once into buffers reserved with ``np.empty`` (measured times: see
docs/design-notes.md).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import sparse

from projector.layers import LayerStack

__all__ = ["ClassWeights", "QVOTable", "VoxelGrid", "integrate", "cells_per_voxel"]


@dataclass(frozen=True, eq=False)
class ClassWeights:
    """Per-cell weights of one deposit as a class per cell and one weight row per class.

    A deposit's material takes a few grades (the lot's planned grade and the grades of the
    assays whose sampling windows cover its deposition times,
    :func:`projector.grades.grade_classes`), so its per-cell weights are a small
    table indexed by a class map; :func:`integrate` then sums volumes per (QVO, class) and
    multiplies by the table once, instead of reading A weights per cell.

    Attributes
    ----------
    index : ndarray, shape (nx, ny), integer
        Class of each cell, in ``0 .. C - 1`` (any class where the deposit has no material).
    table : ndarray, shape (C, A)
        Weights of each class.  A class no piece of the deposit uses is ignored (NaN is
        fine there); a used class's NaN propagates to the voxels it reaches.
    """

    index: np.ndarray
    table: np.ndarray

    def __post_init__(self) -> None:
        index, table = np.asarray(self.index), np.asarray(self.table, dtype=np.float64)
        if index.ndim != 2 or index.dtype.kind not in "iu":
            raise ValueError(f"index must be an (nx, ny) integer array, got "
                             f"{index.dtype} {index.shape}")
        if table.ndim != 2 or table.shape[0] < 1:
            raise ValueError(f"table must have shape (C, A) with C >= 1, got {table.shape}")
        if index.size and (int(index.min()) < 0 or int(index.max()) >= table.shape[0]):
            raise ValueError(f"index must lie in 0 .. {table.shape[0] - 1}, got "
                             f"{int(index.min())} .. {int(index.max())}")
        object.__setattr__(self, "index", index)
        object.__setattr__(self, "table", table)


@dataclass(frozen=True, eq=False)
class QVOTable:
    """The non-empty QVOs, sparse: one row per (voxel, deposit) with material.

    Attributes
    ----------
    flat : ndarray, shape (m,), int64
        Flat voxel index into ``grid_shape`` (C order).
    grid_shape : tuple of int
        ``(nvx, nvy, nvz)``.
    deposit : ndarray, shape (m,), int64
        Deposit index (1-based, :class:`projector.layers.LayerStack`).
    volume_m3 : ndarray, shape (m,)
        Volume of the deposit in the voxel (m3, > 0).
    weighted : ndarray, shape (m, A)
        Sum over the QVO's pieces of volume x per-cell weight (e.g. tonnes, tonnes of an
        analyte); A = 0 without weights.
    ix, iy, iz : ndarray, shape (m,), int64
        Voxel indices (computed from ``flat`` on first use).

    Rows are ordered by deposit, then by voxel (ix, iy, iz) lexicographically.
    """

    flat: np.ndarray
    grid_shape: tuple[int, int, int]
    deposit: np.ndarray
    volume_m3: np.ndarray
    weighted: np.ndarray

    def __len__(self) -> int:
        return int(self.volume_m3.size)

    @functools.cached_property
    def _indices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return tuple(i.astype(np.int64, copy=False)  # type: ignore[return-value]
                     for i in np.unravel_index(self.flat, self.grid_shape))

    @property
    def ix(self) -> np.ndarray:
        return self._indices[0]

    @property
    def iy(self) -> np.ndarray:
        return self._indices[1]

    @property
    def iz(self) -> np.ndarray:
        return self._indices[2]


class _QVOColumns:
    """The QVO table's columns, appended deposit by deposit into buffers that grow rarely.

    Capacity is reserved with ``np.empty``, whose pages the kernel maps only when written,
    so reserving generously costs nothing; copying per-deposit pieces into lists and
    concatenating them at the end would touch the table's memory twice.
    """

    def __init__(self, n_weights: int) -> None:
        self.n_w = n_weights
        self.size = 0
        self.flat = np.empty(0, np.int64)
        self.deposit = np.empty(0, np.int64)
        self.volume = np.empty(0)
        self.weighted_t = np.empty((n_weights, 0))   # (A, capacity): columns contiguous

    def append(self, flat, volume, weighted_t, deposit: int, deposits_left: int) -> None:
        """Append one deposit's QVOs; ``weighted_t`` is their weighted sums transposed,
        shape (A, n)."""
        n, end = flat.size, self.size + flat.size
        if end > self.flat.size:   # reserve room for the deposits left at this one's size
            cap = max(end + n * deposits_left, (3 * self.flat.size) // 2)
            for name in ("flat", "deposit", "volume"):
                old = getattr(self, name)
                new = np.empty(cap, old.dtype)
                new[:self.size] = old[:self.size]
                setattr(self, name, new)
            new = np.empty((self.n_w, cap))
            new[:, :self.size] = self.weighted_t[:, :self.size]
            self.weighted_t = new
        self.flat[self.size:end] = flat
        self.deposit[self.size:end] = deposit
        self.volume[self.size:end] = volume
        if self.n_w:
            self.weighted_t[:, self.size:end] = weighted_t
        self.size = end

    def table(self, grid_shape: tuple[int, int, int]) -> QVOTable:
        m = self.size
        return QVOTable(self.flat[:m], grid_shape, self.deposit[:m], self.volume[:m],
                        self.weighted_t[:, :m].T)


@dataclass(frozen=True, eq=False)
class VoxelGrid:
    """Voxel volumes, weighted sums and QVOs of one layer stack.

    Attributes
    ----------
    voxel_m : float
        Voxel edge (m).
    origin_x_m, origin_y_m : float
        Corner of voxel (0, 0) = the layer grid's corner (m).
    z0_m : float
        Bottom of z bin 0: the lowest ground level (m).
    cells_per_voxel : int
        Cells per voxel edge (``voxel_m / cell_m``).
    volume_m3 : ndarray, shape (nvx, nvy, nvz)
        Material volume per voxel (m3).
    weighted : ndarray, shape (nvx, nvy, nvz, A)
        Sum over the voxel's pieces of volume x per-cell weight (A = 0 without weights).
    qvo : QVOTable
    """

    voxel_m: float
    origin_x_m: float
    origin_y_m: float
    z0_m: float
    cells_per_voxel: int
    volume_m3: np.ndarray
    weighted: np.ndarray
    qvo: QVOTable

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(nvx, nvy, nvz)``."""
        return tuple(self.volume_m3.shape)  # type: ignore[return-value]

    @property
    def voxel_origin(self) -> tuple[float, float, float]:
        """Corner ``(x, y, z)`` of voxel (0, 0, 0) (m)."""
        return (self.origin_x_m, self.origin_y_m, self.z0_m)

    @property
    def voxel_volume_m3(self) -> float:
        return self.voxel_m ** 3

    def z_edges_m(self) -> np.ndarray:
        """Bin edges ``z0 + iz * voxel_m``, shape (nvz + 1,) (m)."""
        return self.z0_m + np.arange(self.shape[2] + 1) * self.voxel_m

    def total_volume_m3(self) -> float:
        return float(self.volume_m3.sum())


def cells_per_voxel(cell_m: float, voxel_m: float) -> int:
    """``voxel_m / cell_m`` as an int; ValueError unless it is a positive integer."""
    if not (math.isfinite(voxel_m) and voxel_m > 0):
        raise ValueError(f"voxel_m must be finite and > 0, got {voxel_m!r}")
    ratio = voxel_m / cell_m
    m = int(round(ratio))
    if m < 1 or abs(ratio - m) > 1e-9 * max(ratio, 1.0):
        raise ValueError(f"voxel_m ({voxel_m}) must be an integer multiple of the cell "
                         f"({cell_m})")
    return m


def _weights_for(weights, k: int, shape: tuple[int, int],
                 n_weights: int | None) -> "np.ndarray | ClassWeights":
    w = weights[k - 1]
    if isinstance(w, ClassWeights):
        if w.index.shape != shape:
            raise ValueError(f"weights[{k - 1}].index must have shape {shape}, got "
                             f"{w.index.shape}")
        if n_weights is not None and w.table.shape[1] != n_weights:
            raise ValueError(f"weights[{k - 1}] has {w.table.shape[1]} weights, expected "
                             f"{n_weights}")
        return w
    w = np.asarray(w, dtype=np.float64)
    if w.ndim == 1:
        w = w[None, None, :]
    if w.ndim != 3 or w.shape[:2] not in (shape, (1, 1)):
        raise ValueError(f"weights[{k - 1}] must have shape (nx, ny, A) = {shape + ('A',)} "
                         f"or (A,), got {np.shape(weights[k - 1])}")
    if n_weights is not None and w.shape[2] != n_weights:
        raise ValueError(f"weights[{k - 1}] has {w.shape[2]} weights, expected {n_weights}")
    return w


def _nonzero(flat: np.ndarray, volume: np.ndarray, weighted_t: np.ndarray | None):
    """``(flat, volume, weighted_t)`` without the QVOs of zero volume (a band ending exactly
    on a bin edge leaves an empty last piece); ``weighted_t`` has shape (A, n)."""
    keep = volume > 0
    if keep.all():
        return flat, volume, weighted_t
    return flat[keep], volume[keep], None if weighted_t is None else weighted_t[:, keep]


def integrate(stack: LayerStack, voxel_m: float,
              weights: Sequence[np.ndarray] | None = None) -> VoxelGrid:
    """Integrate every deposit band of a layer stack exactly over a voxel grid.

    Parameters
    ----------
    stack : LayerStack
        The layer stack (n deposits on a grid of ``nx x ny`` cells of ``cell_m``).
    voxel_m : float
        Voxel edge (m), an integer multiple of ``cell_m``.
    weights : sequence of ndarray or ClassWeights, optional
        One entry per deposit (``weights[k - 1]`` for deposit k): an array of shape
        ``(nx, ny, A)`` (per-cell weights) or ``(A,)`` (one weight vector for the whole
        deposit), or a :class:`ClassWeights` (a class per cell, a (C, A) table; the
        cheapest form when a deposit takes a few grades), with the same ``A`` for all.
        Read one at a time, so a lazy sequence works.  Weights of cells where the deposit
        has no material are ignored (NaN is fine there).

    Returns
    -------
    VoxelGrid
        ``volume_m3`` (nvx, nvy, nvz), ``weighted`` (nvx, nvy, nvz, A), the QVO table.
        ``nvx = ceil(nx / m)``, ``nvy = ceil(ny / m)``, ``nvz`` = bins up to the highest
        material (at least 1).

    Raises
    ------
    ValueError
        If ``voxel_m`` is not a positive integer multiple of the cell, or the weights do not
        match the stack (count, shapes).

    Notes
    -----
    Heights are measured in bins, ``u = (z - z0) / voxel_m``; a band ``(u_lo, u_hi]`` lies
    in bins ``floor(u_lo) .. ceil(u_hi) - 1`` and its piece in bin ``j`` is
    ``min(u_hi, j + 1) - max(u_lo, j)`` (the overlap formula of the module docstring in
    units of ``voxel_m``), times ``voxel_m * cell area``: the first bin gets
    ``min(u_hi, floor(u_lo) + 1) - u_lo``, the last ``u_hi - (ceil(u_hi) - 1)``, the bins in
    between 1.  Per deposit the pieces form a sparse (QVO x cell) matrix, built in CSC form
    (column = cell, so no sorting), and one sparse-dense product with the (cell x A) weights
    gives the weighted sums of every QVO; voxels are sums of their QVOs.
    """
    geometry = stack.geometry
    m = cells_per_voxel(geometry.cell_m, float(voxel_m))
    v = float(voxel_m)
    nx, ny = geometry.shape
    n = stack.n_deposits
    if weights is not None and len(weights) != n:
        raise ValueError(f"weights must have one entry per deposit ({n}), got {len(weights)}")
    nvx, nvy = -(-nx // m), -(-ny // m)
    ncell = nx * ny
    z0 = float(stack.ground().min())
    nvz = _bins_to_top(stack, z0, v)
    nvox = nvx * nvy * nvz
    if nvox >= 2**31 or ncell >= 2**31:
        raise ValueError(f"voxel grid too large: {nvox} voxels, {ncell} cells")
    piece_m3 = v * geometry.cell_area_m2  # one whole bin of one cell

    # flat voxel index of bin 0 of every cell's voxel column, (nx * ny,), C order
    base_of_cell = ((np.arange(nx, dtype=np.int32) // m)[:, None] * (nvy * nvz)
                    + (np.arange(ny, dtype=np.int32) // m)[None, :] * nvz).ravel()
    w_first, n_w = _first_weights(weights, n, (nx, ny))
    bands = _BandPieces(stack.surface_k(0), z0, v, base_of_cell)
    rows_of = _QVORows(nvox, 2 * ncell)
    out = _QVOColumns(n_w)
    for k in range(1, n + 1):
        band = bands.next_band(stack.surface_k(k))
        w = None
        if weights is not None:
            w = w_first if k == 1 else _weights_for(weights, k, (nx, ny), n_w)
        if band is None:
            continue
        data, vox, col, fresh = band
        nz, rows = rows_of.rows(vox, fresh)
        q_k = np.bincount(rows, weights=data, minlength=nz.size)
        q_k *= piece_m3
        if w is None or n_w == 0:
            out.append(*_nonzero(nz, q_k, None), k, n - k)
            continue
        q_wt = _weighted_sums(w, data, rows, col, q_k, piece_m3, ncell)
        out.append(*_nonzero(nz, q_k, q_wt), k, n - k)
    return _voxel_grid(out.table((nvx, nvy, nvz)), geometry, v, z0, m)


def _bins_to_top(stack: LayerStack, z0: float, v: float) -> int:
    """Bins of ``v`` (m) from ``z0`` (m) up to the highest material, at least 1."""
    ground = stack.ground()
    top = stack.surface()
    material = top > ground
    nvz = 1
    if material.any():
        nvz = max(1, int(math.ceil((float(top[material].max()) - z0) / v)))
    return nvz


def _first_weights(weights, n: int, shape: tuple[int, int]):
    """Deposit 1's weights (checked) and the number A of weights (``(None, 0)`` without)."""
    if weights is None or n == 0:
        return None, 0
    w_first = _weights_for(weights, 1, shape, None)
    n_w = (w_first.table.shape[1] if isinstance(w_first, ClassWeights)
           else w_first.shape[2])
    return w_first, n_w


class _BandPieces:
    """The pieces of deposit bands in z bins, band after band from the ground up.

    Every surface is taken in bins, ``u = (z - z0) / voxel_m``, with its bin ``floor(u)``
    (as float); a surface's u and floor serve the band below it and the band above it.
    Two buffers each, swapped per band, and piece buffers reused by every band: fresh
    memory costs page faults, which on a sandboxed machine cost more than the arithmetic.

    A band's pieces are of three kinds, each at most one per cell and bin:

    - first: bin ``fl_lo``, ``min(u_hi, fl_lo + 1) - u_lo`` (cells with material);
    - last: bin ``fl_hi > fl_lo``, ``u_hi - fl_hi`` (possibly 0: dropped with the zero
      QVOs);
    - whole: bins ``fl_lo + 1 .. fl_hi - 1``, 1 each;

    together a sparse (QVO x cell) matrix in COO form (bin units; x the volume of one
    whole bin of one cell gives m3).
    """

    def __init__(self, ground_m: np.ndarray, z0: float, v: float,
                 base_of_cell: np.ndarray) -> None:
        ncell = base_of_cell.size
        self.z0, self.v = z0, v
        self.base_of_cell = base_of_cell
        self.base_less_1 = base_of_cell - 1
        self.u_lo, self.u_hi = np.empty(ncell), np.empty(ncell)
        self.fl_lo, self.fl_hi = np.empty(ncell), np.empty(ncell)
        self.span = np.empty(ncell)
        np.divide(np.subtract(ground_m.ravel(), z0, out=self.u_lo), v, out=self.u_lo)
        np.floor(self.u_lo, out=self.fl_lo)
        cap = 2 * ncell  # first and last pieces; whole bins beyond that get their own arrays
        self.data_buf, self.tmp_buf = np.empty(cap), np.empty(ncell)
        self.vox_buf, self.col_buf = (np.empty(cap, dtype=np.int32) for _ in range(2))

    def next_band(self, top_m: np.ndarray):
        """The pieces of the band from the last surface up to ``top_m`` ((nx, ny), m).

        Returns ``(data, vox, col, fresh)``: the piece heights (bins), their flat voxel
        indices and cells; ``fresh`` when the arrays are new rather than views of the
        buffers (valid until the next call).  None when no cell has material.
        """
        np.subtract(top_m.ravel(), self.z0, out=self.u_hi)
        np.divide(self.u_hi, self.v, out=self.u_hi)
        np.floor(self.u_hi, out=self.fl_hi)
        band = self._pieces()
        self.u_lo, self.u_hi = self.u_hi, self.u_lo
        self.fl_lo, self.fl_hi = self.fl_hi, self.fl_lo
        return band

    def _pieces(self):
        """:meth:`next_band`'s pieces, before the surfaces' buffers are swapped."""
        u_lo_all, u_hi_all, fl_lo_all, fl_hi_all = self.u_lo, self.u_hi, self.fl_lo, self.fl_hi
        data_buf, tmp_buf = self.data_buf, self.tmp_buf
        vox_buf, col_buf = self.vox_buf, self.col_buf
        cells = np.flatnonzero(u_hi_all > u_lo_all)  # a band < 1 ulp of u is dropped
        n1 = cells.size
        if n1 == 0:
            return None
        data, vox, col = data_buf[:n1], vox_buf[:n1], col_buf[:n1]
        next_bin = np.take(fl_lo_all, cells, out=tmp_buf[:n1], mode="clip")
        next_bin += 1.0                                # fl_lo + 1
        np.minimum(np.take(u_hi_all, cells, out=data, mode="clip"), next_bin, out=data)
        data -= np.take(u_lo_all, cells)
        np.add(np.take(self.base_less_1, cells, out=vox, mode="clip"), next_bin, out=vox,
               casting="unsafe")
        col[:] = cells
        np.subtract(fl_hi_all, fl_lo_all, out=self.span)  # 0 where there is no material
        last_cells = np.flatnonzero(self.span > 0)
        n2 = n1 + last_cells.size
        extra = []
        if n2 > n1:
            fl_hi = np.take(fl_hi_all, last_cells, out=tmp_buf[:n2 - n1], mode="clip")
            last_data, last_vox = data_buf[n1:n2], vox_buf[n1:n2]
            np.subtract(np.take(u_hi_all, last_cells, out=last_data, mode="clip"), fl_hi,
                        out=last_data)
            np.add(np.take(self.base_of_cell, last_cells, out=last_vox, mode="clip"), fl_hi,
                   out=last_vox, casting="unsafe")
            col_buf[n1:n2] = last_cells
            mid_cells = np.flatnonzero(self.span > 1)
            if mid_cells.size:
                extra = self._whole_bins(mid_cells)
        data, vox, col = data_buf[:n2], vox_buf[:n2], col_buf[:n2]
        if extra:
            data, vox, col = (np.concatenate((a, b)) for a, b in zip((data, vox, col), extra))
        return data, vox, col, bool(extra)

    def _whole_bins(self, mid_cells: np.ndarray) -> list[np.ndarray]:
        """``[data, vox, col]`` of the whole-bin pieces of the cells ``mid_cells``."""
        n_whole = np.take(self.span, mid_cells).astype(np.int64) - 1
        first_of = np.cumsum(n_whole) - n_whole  # where each cell's run starts
        offset = (np.arange(int(first_of[-1] + n_whole[-1]), dtype=np.int32)
                  - np.repeat(first_of.astype(np.int32), n_whole) + 1)
        bottom = (np.take(self.base_of_cell, mid_cells)
                  + np.take(self.fl_lo, mid_cells).astype(np.int32))
        return [np.ones(offset.size), np.repeat(bottom, n_whole) + offset,
                np.repeat(mid_cells, n_whole)]


class _QVORows:
    """Each piece's row among one band's QVOs: the voxels the band reaches, in order.

    Scratch arrays over all voxels, reused by every band (and left clear after each)."""

    def __init__(self, nvox: int, cap: int) -> None:
        self.touched = np.zeros(nvox, dtype=bool)      # voxels one deposit reaches
        self.compact = np.zeros(nvox, dtype=np.int32)  # voxel -> row of the deposit's QVOs
        self.rows_buf = np.empty(cap, dtype=np.int32)

    def rows(self, vox: np.ndarray, fresh: bool) -> tuple[np.ndarray, np.ndarray]:
        """``(nz, rows)``: the flat voxel indices reached (ascending) and each piece's
        row among them; ``rows`` is a view of a buffer unless ``fresh``."""
        touched, compact = self.touched, self.compact
        touched[vox] = True
        nz = np.flatnonzero(touched)
        touched[nz] = False
        compact[nz] = np.arange(nz.size, dtype=np.int32)
        rows = (np.take(compact, vox) if fresh
                else np.take(compact, vox, out=self.rows_buf[:vox.size], mode="clip"))
        return nz, rows


def _weighted_sums(w, data: np.ndarray, rows: np.ndarray, col: np.ndarray, q_k: np.ndarray,
                   piece_m3: float, ncell: int) -> np.ndarray:
    """Each QVO's weighted sums, shape (A, n_qvo): the pieces (``data`` in bins, QVO
    ``rows``, cells ``col``) times the deposit's weights ``w``, with ``q_k`` the QVOs'
    volumes (m3) and ``piece_m3`` the volume of one whole bin of one cell."""
    n_qvo = q_k.size
    if isinstance(w, ClassWeights):
        n_c = w.table.shape[0]
        if n_c == 1:
            return w.table[0][:, None] * q_k[None, :]
        # volume per (class, QVO), then the class table: one bincount, no per-cell weight
        # rows
        key = np.multiply(np.take(w.index.ravel(), col), n_qvo, dtype=np.int64)
        key += rows
        per_class = np.bincount(key, weights=data, minlength=n_qvo * n_c)
        per_class = per_class.reshape(n_c, n_qvo)
        used = np.flatnonzero(per_class.any(axis=1))
        q_wt = w.table[used].T @ per_class[used]
        q_wt *= piece_m3
        return q_wt
    if w.shape[:2] == (1, 1):
        return w[0, 0][:, None] * q_k[None, :]  # one weight vector for the deposit
    pieces = sparse.coo_array((data, (rows, col)), shape=(n_qvo, ncell))
    q_wt = (pieces @ w.reshape(ncell, w.shape[2])).T
    q_wt *= piece_m3
    return q_wt


def _voxel_grid(qvo: QVOTable, geometry, v: float, z0: float, m: int) -> VoxelGrid:
    """The voxel grid of a QVO table: a voxel's volume and weighted sums are the sums of
    its QVOs'."""
    nvx, nvy, nvz = qvo.grid_shape
    nvox = nvx * nvy * nvz
    n_w = qvo.weighted.shape[1]
    volume = np.bincount(qvo.flat, weights=qvo.volume_m3, minlength=nvox)
    weighted = np.empty((nvox, n_w))
    for a in range(n_w):   # qvo.weighted's columns are contiguous
        weighted[:, a] = np.bincount(qvo.flat, weights=qvo.weighted[:, a], minlength=nvox)
    return VoxelGrid(
        voxel_m=v, origin_x_m=geometry.origin_x_m, origin_y_m=geometry.origin_y_m, z0_m=z0,
        cells_per_voxel=m, volume_m3=volume.reshape(nvx, nvy, nvz),
        weighted=weighted.reshape(nvx, nvy, nvz, n_w), qvo=qvo)

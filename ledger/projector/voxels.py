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

Cost: per deposit a few vectorised passes over the cells with material and one
sparse-dense product (pieces x weights); no cells x deposits x bins cube is formed.  The
full-scale case (220 m x 60 m pile, 0.25 m cells, 1 m voxels, 60 chevron deposits, 6 weights)
takes about 0.5 s on one core.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import sparse

from ledger.projector.layers import LayerStack

__all__ = ["QVOTable", "VoxelGrid", "integrate", "cells_per_voxel"]


@dataclass(frozen=True, eq=False)
class QVOTable:
    """The non-empty QVOs, sparse: one row per (voxel, deposit) with material.

    Attributes
    ----------
    ix, iy, iz : ndarray, shape (m,), int64
        Voxel indices.
    deposit : ndarray, shape (m,), int64
        Deposit index (1-based, :class:`ledger.projector.layers.LayerStack`).
    volume_m3 : ndarray, shape (m,)
        Volume of the deposit in the voxel (m3, > 0).
    weighted : ndarray, shape (m, A)
        Sum over the QVO's pieces of volume x per-cell weight (e.g. tonnes, tonnes of an
        analyte); A = 0 without weights.

    Rows are ordered by deposit, then by voxel (ix, iy, iz) lexicographically.
    """

    ix: np.ndarray
    iy: np.ndarray
    iz: np.ndarray
    deposit: np.ndarray
    volume_m3: np.ndarray
    weighted: np.ndarray

    def __len__(self) -> int:
        return int(self.volume_m3.size)


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


def _weights_for(weights, k: int, shape: tuple[int, int], n_weights: int | None) -> np.ndarray:
    w = np.asarray(weights[k - 1], dtype=np.float64)
    if w.ndim == 1:
        w = w[None, None, :]
    if w.ndim != 3 or w.shape[:2] not in (shape, (1, 1)):
        raise ValueError(f"weights[{k - 1}] must have shape (nx, ny, A) = {shape + ('A',)} "
                         f"or (A,), got {np.shape(weights[k - 1])}")
    if n_weights is not None and w.shape[2] != n_weights:
        raise ValueError(f"weights[{k - 1}] has {w.shape[2]} weights, expected {n_weights}")
    return w


def integrate(stack: LayerStack, voxel_m: float,
              weights: Sequence[np.ndarray] | None = None) -> VoxelGrid:
    """Integrate every deposit band of a layer stack exactly over a voxel grid.

    Parameters
    ----------
    stack : LayerStack
        The layer stack (n deposits on a grid of ``nx x ny`` cells of ``cell_m``).
    voxel_m : float
        Voxel edge (m), an integer multiple of ``cell_m``.
    weights : sequence of ndarray, optional
        One array per deposit (``weights[k - 1]`` for deposit k), each of shape
        ``(nx, ny, A)`` (per-cell weights) or ``(A,)`` (one weight vector for the whole
        deposit), with the same ``A`` for all.  Read one at a time, so a lazy sequence
        works.  Weights of cells where the deposit has no material are ignored (NaN is
        fine there).

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
    ground = stack.ground()
    z0 = float(ground.min())
    top = stack.surface()
    material = top > ground
    nvz = 1
    if material.any():
        nvz = max(1, int(math.ceil((float(top[material].max()) - z0) / v)))
    nvox = nvx * nvy * nvz
    piece_m3 = v * geometry.cell_area_m2  # one whole bin of one cell

    # flat voxel index of bin 0 of every cell's voxel column, (nx * ny,), C order
    base_of_cell = ((np.arange(nx) // m)[:, None] * (nvy * nvz)
                    + (np.arange(ny) // m)[None, :] * nvz).ravel()

    w_first = None
    n_w = 0
    if weights is not None and n > 0:
        w_first = _weights_for(weights, 1, (nx, ny), None)
        n_w = w_first.shape[2]
    touched = np.zeros(nvox, dtype=bool)       # scratch: voxels one deposit reaches
    compact = np.zeros(nvox, dtype=np.int64)   # scratch: voxel -> row of the deposit's QVOs
    q_flat, q_dep, q_vol, q_w = [], [], [], []

    u_lo_all = (stack.surface_k(0).ravel() - z0) / v
    for k in range(1, n + 1):
        u_hi_all = (stack.surface_k(k).ravel() - z0) / v
        w = None
        if weights is not None:
            w = w_first if k == 1 else _weights_for(weights, k, (nx, ny), n_w)
        # cells with material (a band thinner than the rounding of u, <= 1 ulp, is dropped)
        cells = np.flatnonzero(u_hi_all > u_lo_all)
        u_lo = np.take(u_lo_all, cells)
        u_hi = np.take(u_hi_all, cells)
        u_lo_all = u_hi_all
        if cells.size == 0:
            continue
        b_lo = np.floor(u_lo)
        b_hi = np.ceil(u_hi) - 1.0  # >= b_lo because u_hi > u_lo
        span = (b_hi - b_lo).astype(np.int64)  # bins after the first
        # CSC layout: per cell its pieces [first, whole bins ..., last] contiguously
        counts = np.zeros(ncell + 1, dtype=np.int64)
        counts[cells + 1] = span + 1
        indptr = np.cumsum(counts)
        n_pieces = int(indptr[-1])
        at_first = np.take(indptr, cells)
        voxel = np.empty(n_pieces, dtype=np.int64)
        data = np.empty(n_pieces)
        base = np.take(base_of_cell, cells) + b_lo.astype(np.int64)
        voxel[at_first] = base
        data[at_first] = (np.minimum(u_hi, b_lo + 1.0) - u_lo) * piece_m3
        two = np.flatnonzero(span > 0)
        if two.size:
            at_last = np.take(at_first, two) + np.take(span, two)
            voxel[at_last] = np.take(base, two) + np.take(span, two)
            data[at_last] = (np.take(u_hi, two) - np.take(b_hi, two)) * piece_m3
            mid = np.flatnonzero(span > 1)
            if mid.size:
                # whole bins: (span - 1) per cell, at offsets 1 .. span - 1 from the first
                n_mid = np.take(span, mid) - 1
                first_of = np.cumsum(n_mid) - n_mid  # where each cell's run starts
                offset = np.arange(int(n_mid.sum())) - np.repeat(first_of, n_mid) + 1
                at_mid = np.repeat(np.take(at_first, mid), n_mid) + offset
                voxel[at_mid] = np.repeat(np.take(base, mid), n_mid) + offset
                data[at_mid] = piece_m3
        touched[voxel] = True
        nz = np.flatnonzero(touched)
        touched[nz] = False
        compact[nz] = np.arange(nz.size)
        rows = np.take(compact, voxel)
        q_k = np.bincount(rows, weights=data, minlength=nz.size)
        q_flat.append(nz)
        q_dep.append(np.full(nz.size, k, dtype=np.int64))
        q_vol.append(q_k)
        if w is None or n_w == 0:
            continue
        if w.shape[:2] == (1, 1):
            q_w.append(q_k[:, None] * w[0, 0][None, :])  # one weight vector for the deposit
        else:
            pieces = sparse.csc_array((data, rows, indptr), shape=(nz.size, ncell))
            q_w.append(pieces @ w.reshape(ncell, n_w))

    if q_flat:
        flat = np.concatenate(q_flat)
        deposit = np.concatenate(q_dep)
        qvol = np.concatenate(q_vol)
        qw = np.concatenate(q_w) if n_w else np.zeros((flat.size, 0))
        keep = np.flatnonzero(qvol > 0)
        if keep.size < flat.size:
            flat, deposit, qvol, qw = flat[keep], deposit[keep], qvol[keep], qw[keep]
    else:
        flat = np.zeros(0, dtype=np.int64)
        deposit = np.zeros(0, dtype=np.int64)
        qvol = np.zeros(0)
        qw = np.zeros((0, n_w))
    volume = np.bincount(flat, weights=qvol, minlength=nvox)
    weighted = np.empty((nvox, n_w))
    for a in range(n_w):
        weighted[:, a] = np.bincount(flat, weights=qw[:, a], minlength=nvox)
    vx, vy, vz = np.unravel_index(flat, (nvx, nvy, nvz))
    qvo = QVOTable(vx.astype(np.int64, copy=False), vy.astype(np.int64, copy=False),
                   vz.astype(np.int64, copy=False), deposit, qvol, qw)
    return VoxelGrid(
        voxel_m=v, origin_x_m=geometry.origin_x_m, origin_y_m=geometry.origin_y_m, z0_m=z0,
        cells_per_voxel=m, volume_m3=volume.reshape(nvx, nvy, nvz),
        weighted=weighted.reshape(nvx, nvy, nvz, n_w), qvo=qvo)

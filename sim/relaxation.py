"""Slope failure on the deposition grid: the avalanche relaxation and slump routing.

:func:`relax` is the explicit avalanche relaxation (Jacobi sweeps on the 8-neighbour
stencil: each column steeper than the angle of repose toward a neighbour sends half its
largest excess, split among its lower neighbours in proportion to their excess, never
more than its mobile material) until no column is steeper than the tolerance; it is
exactly volume conserving. :func:`unstable_mask` finds the columns it would move.
After a cut the walls may fail (:meth:`sim.world.World.settle`): the relaxation then
records the flux through every cell edge, and :func:`slump_flow`, :func:`flow_matrix`
and :func:`route` carry the composition of the moving material through that flux network,
assuming each cell mixes what passes through it (a sparse linear solve,
``(E_i + In_i) c_i - sum_j F_ji c_j = s_i``). All arrays are over the padded grid
``(ny + 2, nx + 2)`` (one ring of ground cells, the border sink) unless said otherwise;
heights and thicknesses in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import linalg as sparse_linalg

#: 8-neighbour stencil (dy, dx), and the distance to each neighbour in cells.
DIRS: tuple[tuple[int, int], ...] = ((-1, 0), (1, 0), (0, -1), (0, 1),
                                     (-1, -1), (-1, 1), (1, -1), (1, 1))
DIST = np.array([1.0, 1.0, 1.0, 1.0, math.sqrt(2), math.sqrt(2), math.sqrt(2), math.sqrt(2)])


def relax(base: np.ndarray, mob: np.ndarray, bbox, crit: np.ndarray, tol_m: float,
          max_iterations: int, flux: np.ndarray | None = None):
    """Jacobi avalanche relaxation of the mobile layer ``mob`` on ``base``.

    Parameters
    ----------
    base, mob : ndarray (ny + 2, nx + 2)
        Immobile surface (m, read only) and mobile thickness on it (m, modified in place).
    bbox : tuple of int
        (r0, r1, c0, c1) in padded indices, covering every column that may be unstable.
    crit : ndarray (8,)
        Critical drop to each neighbour of :data:`DIRS` (m): ``tan(repose) * cell * DIST``.
    tol_m : float
        A column is stable when no drop exceeds the critical one by more than this (m).
    max_iterations : int
        RuntimeError beyond this many sweeps.
    flux : ndarray (8, ny + 2, nx + 2), optional
        Accumulates the thickness (m) sent from each cell to each neighbour.

    Returns
    -------
    iterations : int
    lost : float
        Thickness (m, summed over cells) pushed into the pad (the border) and removed.
    touched : tuple of int
        (r0, r1, c0, c1) padded bbox of every cell that sent or received material.
    """
    nyp, nxp = mob.shape
    r0, r1, c0, c1 = (max(1, bbox[0]), min(nyp - 1, bbox[1]), max(1, bbox[2]),
                      min(nxp - 1, bbox[3]))
    t0, t1, u0, u1 = r0 - 1, r1 + 1, c0 - 1, c1 + 1
    tol = tol_m
    lost = 0.0
    it = 0
    while r1 > r0 and c1 > c0:
        if it >= max_iterations:
            raise RuntimeError(f"avalanche relaxation did not settle in {it} sweeps")
        hblk = base[r0 - 1:r1 + 1, c0 - 1:c1 + 1] + mob[r0 - 1:r1 + 1, c0 - 1:c1 + 1]
        excess, emax, esum = _excess(hblk, crit)
        mc = mob[r0:r1, c0:c1]
        send = (emax > tol) & (mc > 0)
        if not send.any():
            break
        out = np.minimum(mc, 0.5 * emax)
        out *= send
        wgt = np.zeros_like(out)
        np.divide(out, esum, out=wgt, where=send)
        mc -= out
        for k, (dy, dx) in enumerate(DIRS):
            f = excess[k]
            f *= wgt
            mob[r0 + dy:r1 + dy, c0 + dx:c1 + dx] += f
            if flux is not None:
                flux[k, r0:r1, c0:c1] += f
        if r0 == 1 or c0 == 1 or r1 == nyp - 1 or c1 == nxp - 1:
            lost += (mob[0, :].sum() + mob[-1, :].sum() + mob[1:-1, 0].sum()
                     + mob[1:-1, -1].sum())
            mob[0, :] = 0.0
            mob[-1, :] = 0.0
            mob[:, 0] = 0.0
            mob[:, -1] = 0.0
        rows = np.flatnonzero(send.any(axis=1))
        cols = np.flatnonzero(send.any(axis=0))
        nr0, nr1 = r0 + rows[0] - 1, r0 + rows[-1] + 2
        nc0, nc1 = c0 + cols[0] - 1, c0 + cols[-1] + 2
        t0, t1 = min(t0, nr0 - 1), max(t1, nr1 + 1)
        u0, u1 = min(u0, nc0 - 1), max(u1, nc1 + 1)
        r0, r1 = max(1, nr0), min(nyp - 1, nr1)
        c0, c1 = max(1, nc0), min(nxp - 1, nc1)
        it += 1
    touched = (max(1, t0), min(nyp - 1, t1), max(1, u0), min(nxp - 1, u1))
    return it, float(lost), touched


def _excess(hblk: np.ndarray, crit: np.ndarray):
    """Per neighbour, the drop beyond the critical one (>= 0) of the block's inner cells.

    ``hblk`` is a (h + 2, w + 2) surface block; returns the list of 8 (h, w) excesses
    (order of :data:`DIRS`), their maximum and their sum.
    """
    h, w = hblk.shape[0] - 2, hblk.shape[1] - 2
    centre = hblk[1:-1, 1:-1]
    excess = []
    emax = None
    esum = None
    for k, (dy, dx) in enumerate(DIRS):
        e = centre - hblk[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        e -= crit[k]
        np.maximum(e, 0.0, out=e)
        excess.append(e)
        if emax is None:
            emax = e.copy()
            esum = e.copy()
        else:
            np.maximum(emax, e, out=emax)
            esum += e
    return excess, emax, esum


def unstable_mask(surf: np.ndarray, crit: np.ndarray, tol_m: float,
                  ground_z_m: float) -> np.ndarray:
    """Bool (ny, nx): columns of the padded surface ``surf`` (ny + 2, nx + 2) steeper than
    repose (beyond ``tol_m``) toward a neighbour and holding material."""
    ny, nx = surf.shape[0] - 2, surf.shape[1] - 2
    centre = surf[1:-1, 1:-1]
    emax = np.zeros((ny, nx))
    for k, (dy, dx) in enumerate(DIRS):
        np.maximum(emax, centre - surf[1 + dy:1 + dy + ny, 1 + dx:1 + dx + nx] - crit[k],
                   out=emax)
    return (emax > tol_m) & (centre > ground_z_m)


@dataclass
class SlumpFlow:
    """The flux network of one relaxation on the window around the cells it touched.

    The window is the touched block plus the pad ring around it; ``gy0, gx0`` is the grid
    index of its cell (0, 0) (-1 on the pad). Arrays are (hh, ww) over the window (``fw``
    (8, hh, ww)), thicknesses in metres.

    Attributes
    ----------
    fw : ndarray
        Thickness sent from each cell to each neighbour of :data:`DIRS`.
    inflow, ero, dep : ndarray
        Thickness received from neighbours; eroded from; deposited on each cell (on the
        pad, whose material was removed as lost, the deposit is the inflow).
    pad : ndarray of bool
        Cells of the pad ring (the border sink).
    node : ndarray of bool
        Cells material passed through (inflow or erosion): the network's nodes.
    idx : ndarray of int64
        Node number of each cell, -1 off the network.
    """

    fw: np.ndarray
    inflow: np.ndarray
    ero: np.ndarray
    dep: np.ndarray
    pad: np.ndarray
    node: np.ndarray
    idx: np.ndarray
    gy0: int
    gx0: int

    @property
    def n_nodes(self) -> int:
        return int(self.node.sum())


def slump_flow(flux: np.ndarray, mob: np.ndarray, mob0: np.ndarray, touched,
               ny: int, nx: int) -> SlumpFlow:
    """The network of a relaxation that started from ``mob0`` and ended at ``mob``.

    ``flux`` (8, ny + 2, nx + 2) as accumulated by :func:`relax`; ``touched`` its touched
    bbox; ``ny, nx`` the grid's shape (without the pad).
    """
    r0, r1, c0, c1 = touched
    # window including the pad ring around the touched block (sinks)
    w0, w1, v0, v1 = r0 - 1, r1 + 1, c0 - 1, c1 + 1
    fw = flux[:, w0:w1, v0:v1]
    dlt = (mob - mob0)[w0:w1, v0:v1]
    # border cells received lost material (mob was zeroed there): their "deposit" is
    # their inflow; reconstruct it from the fluxes
    hh, ww = dlt.shape
    inflow = np.zeros((hh, ww))
    for k, (dy, dx) in enumerate(DIRS):
        src = fw[k]
        ys0, ys1 = max(0, -dy), hh - max(0, dy)
        xs0, xs1 = max(0, -dx), ww - max(0, dx)
        inflow[ys0 + dy:ys1 + dy, xs0 + dx:xs1 + dx] += src[ys0:ys1, xs0:xs1]
    pad = np.zeros((hh, ww), bool)
    gy = np.arange(w0, w1)
    gx = np.arange(v0, v1)
    pad[(gy == 0) | (gy == ny + 1), :] = True
    pad[:, (gx == 0) | (gx == nx + 1)] = True
    dlt = np.where(pad, inflow, dlt)
    ero = np.maximum(-dlt, 0.0)
    dep = np.maximum(dlt, 0.0)
    node = (inflow + ero) > 0
    nn = int(node.sum())
    idx = -np.ones((hh, ww), np.int64)
    idx[node] = np.arange(nn)
    return SlumpFlow(fw, inflow, ero, dep, pad, node, idx, w0 - 1, v0 - 1)


def flow_matrix(flow: SlumpFlow) -> sparse.csc_matrix:
    """The mixing system's matrix (n_nodes, n_nodes): ``(E_i + In_i)`` on the diagonal,
    ``-F_ji`` (the flux from node j into node i) off it."""
    fw, idx = flow.fw, flow.idx
    hh, ww = idx.shape
    nn = flow.n_nodes
    diag = (flow.inflow + flow.ero)[flow.node]
    ri, ci, vv = [np.arange(nn)], [np.arange(nn)], [diag]
    for k, (dy, dx) in enumerate(DIRS):
        fk = fw[k]
        sy, sx = np.nonzero(fk > 0)
        ty, tx = sy + dy, sx + dx
        ok = (ty >= 0) & (ty < hh) & (tx >= 0) & (tx < ww)
        sy, sx, ty, tx = sy[ok], sx[ok], ty[ok], tx[ok]
        ok = (idx[ty, tx] >= 0) & (idx[sy, sx] >= 0)
        sy, sx, ty, tx = sy[ok], sx[ok], ty[ok], tx[ok]
        ri.append(idx[ty, tx])
        ci.append(idx[sy, sx])
        vv.append(-fk[sy, sx])
    return sparse.csc_matrix((np.concatenate(vv), (np.concatenate(ri), np.concatenate(ci))),
                             shape=(nn, nn))


def route(amat: sparse.csc_matrix, rhs: np.ndarray) -> np.ndarray:
    """Solve ``amat @ conc = rhs`` for every column of ``rhs`` (n_nodes, n_components):
    the mixed concentration of each component in each node."""
    lu = sparse_linalg.splu(amat)
    # one right-hand side at a time: faster than SuperLU's 2-D solve here
    return np.column_stack([lu.solve(np.ascontiguousarray(rhs[:, j]))
                            for j in range(rhs.shape[1])])


def routed_deposits(flow: SlumpFlow, rhs: np.ndarray, eroded_by_slot: np.ndarray,
                    ncomp: int) -> np.ndarray:
    """What each node of the network keeps of the routed material.

    Parameters
    ----------
    flow : SlumpFlow
    rhs : ndarray (n_nodes, n_slots * ncomp)
        Per node and eroding slot, the eroded thickness (m), thickness x time and
        thickness x grade (``ncomp`` = 2 + analytes columns per slot).
    eroded_by_slot : ndarray (n_slots,)
        Eroded thickness per slot, summed over the cells (m).

    Returns
    -------
    ndarray (n_nodes, n_slots * ncomp)
        Deposited thickness, thickness x time and thickness x grade per node, scaled per
        slot so that the deposits add up to exactly what that slot lost.
    """
    conc = rhs
    if eroded_by_slot.size:
        conc = route(flow_matrix(flow), rhs)
    dep_n = flow.dep[flow.node]
    add = conc * dep_n[:, None]  # per node: deposited volume(-weighted) components
    # exact per-slot conservation: scale deposits to the eroded volumes
    for j in range(eroded_by_slot.size):
        tot = add[:, j * ncomp].sum()
        if tot > 0:
            add[:, j * ncomp:(j + 1) * ncomp] *= eroded_by_slot[j] / tot
    return add

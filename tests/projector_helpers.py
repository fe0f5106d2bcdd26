"""Helpers the projector tests share: their time constants, their seeded random inputs (a
layer stack for the material tests, generators for the geometry tests) and a ray caster
that makes scanner profiles of a known surface for the profile and height-map tests.
"""

from __future__ import annotations


import numpy as np

from seeding import session_seed

from projector.grid import GridGeometry
from projector.layers import DepositInfo, LayerStack
from schemas.times import NS_PER_H, NS_PER_S


# --- the material tests (envelope, layers, voxels and grades) ----------------------------

T0 = 1_700_000_000 * NS_PER_S  # an arbitrary UTC epoch (ns)
H = NS_PER_H                   # one hour (ns)


def random_stack(seed, nx=7, ny=9, cell=0.5, n=5, quantum=None, ground_sd=0.3):
    """A seeded random stack of ``n`` deposits (thicknesses from a few fixed values) on a
    rough ground, cut after the third deposit so that not every band is full; ``quantum``
    (m) rounds the ground and the surfaces to its multiples."""
    rng = np.random.default_rng(seed)
    geometry = GridGeometry(10.0, -4.0, cell, nx, ny)
    ground = 2.0 + rng.uniform(-ground_sd, ground_sd, geometry.shape)
    if quantum:
        ground = np.round(ground / quantum) * quantum
    stack = LayerStack.empty(geometry, ground)
    for k in range(1, n + 1):
        stack = stack.open_deposit(DepositInfo(k, f"P{k}", f"L{k % 2}", T0 + k * H))
        thick = rng.choice([0.0, 0.05, 0.3, 1.2, 2.7], size=geometry.shape) \
            * rng.uniform(0.5, 1.5, geometry.shape)
        surf = stack.surface() + thick
        if quantum:
            surf = np.maximum(np.round(surf / quantum) * quantum, stack.surface())
        stack, _ = stack.raise_to(surf, T0 + k * H)
        if k == 3:  # a cut in the middle, so bands are not all full
            floor = np.where(rng.random(geometry.shape) < 0.4,
                             stack.surface() - rng.uniform(0, 2, geometry.shape), np.inf)
            stack, _ = stack.clamp(floor)
    return stack


# --- the geometry tests (georef, profile, height map) ------------------------------------

#: base seed of :func:`make_rng`: the run's seed (``--seed`` / ``STOCKPILE_TEST_SEED``,
#: tests/seeding.py)
BASE_SEED = session_seed()
T0_NS = 1_793_491_200_000_000_000
NS = NS_PER_S
#: scanner x -> site -z, y -> site +x, z -> site -y (the simulator's LOOK_DOWN)
LOOK_DOWN = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])


def make_rng(offset: int = 0) -> np.random.Generator:
    seed = BASE_SEED + offset
    print(f"seed={seed}")
    return np.random.default_rng(seed)


def cast_profile(surface, x0: float, z0: float, angles_rad: np.ndarray,
                 t_max: float = 200.0) -> np.ndarray:
    """Ranges from (x0, z0) along (sin a, -cos a) to the first crossing of z = surface(x).

    Dense march + bisection (a different method from the bench's closed form).
    """
    u, v = np.sin(angles_rad), np.cos(angles_rad)
    ts = np.linspace(0.0, t_max, 40_001)
    h = (z0 - ts[None, :] * v[:, None]) - surface(x0 + ts[None, :] * u[:, None])
    below = h <= 0
    first = np.argmax(below, axis=1)
    if not below.any(axis=1).all():
        raise AssertionError("a ray misses the surface")
    lo, hi = ts[first - 1], ts[first]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        under = (z0 - mid * v) - surface(x0 + mid * u) <= 0
        hi = np.where(under, mid, hi)
        lo = np.where(under, lo, mid)
    return 0.5 * (lo + hi)

"""The simulated SICK LMS200 on the reclaimer's boom, and the scan geometry.

:class:`ScannerModel` reproduces the LMS200 (thesis §3.4, App. A, docs/domain.md §5): ray
casting on the true heightmap (:func:`sim.raycast.raycast_heightmap`), range noise
(14.5 mm measured), mixed pixels at depth discontinuities, dropouts, error codes, and 10 mm
/ 1 mm quantisation. It takes a :class:`numpy.random.Generator` (never the global RNG).

Scan geometry convention (shared with the georeferencing code, see
:func:`beam_directions_scanner_frame`): the Foxglove ``LaserScan`` / ROS convention that
the ledger stores scans in.  The scan plane is the scanner frame's **x-y plane**; beam
``k`` has bearing ``a_k = -fov/2 + k * step`` (radians, counter-clockwise about the
scanner's +z axis, 0 = +x) and direction ``(cos a_k, sin a_k, 0)`` in the scanner frame.
A pose rotation ``R`` maps scanner-frame vectors to the site frame
(``d_site = R @ d_scanner``; site frame: ENU metres, x across the pile, y along the rail,
z up, docs/domain.md §2); a downward-looking scanner therefore has its +x axis pointing
down: ``R = [[0, 1, 0], [0, 0, -1], [-1, 0, 0]]`` (columns: scanner x -> site -z, scanner
y -> site +x, scanner z -> site -y) looks straight down and sweeps across the pile (site
x-z plane), the first beam (-fov/2) toward -x.
"""

from __future__ import annotations

import math

import numpy as np

from sim.raycast import raycast_heightmap
from sim.rng import check_rng

__all__ = [
    "scan_count", "beam_angles_rad", "beam_directions_scanner_frame", "rotation_matrix",
    "ScannerModel", "BEAM_OK", "BEAM_NO_HIT", "BEAM_DROPOUT", "BEAM_ERROR_CODE", "BEAM_MIXED",
]

#: (field of view deg, step deg) -> values per scan; the LMS200's modes (thesis App. A,
#: docs/domain.md §5)
_SCAN_MODES = {(100.0, 0.25): 401, (100.0, 0.5): 201, (100.0, 1.0): 101,
               (180.0, 0.5): 361, (180.0, 1.0): 181}

#: beam status codes returned by :meth:`ScannerModel.scan_with_status`
BEAM_OK = 0          # a range
BEAM_NO_HIT = 1      # nothing within the maximum range: NaN
BEAM_DROPOUT = 2     # a surface was there but no echo came back: NaN
BEAM_ERROR_CODE = 3  # the scanner sent an error code (top of the 13-bit scale): NaN
BEAM_MIXED = 4       # a range, but a mixed pixel (phantom) between two surfaces (truth only)


def scan_count(fov_deg: float, step_deg: float, *, any_step: bool = False) -> int:
    """Values per LMS200 scan: 100/0.25 -> 401, 100/0.5 -> 201, 100/1 -> 101, 180/0.5 -> 361,
    180/1 -> 181.  With ``any_step`` (another scanner: an LMS1xx/5xx, TiM), any step > 0
    and field in (0, 360] deg: the whole steps that fit the field, ``floor(fov / step) + 1``
    values (the last beam at or just before +fov/2).

    Raises
    ------
    ValueError
        For any other combination (180 deg at 0.25 deg is not an LMS200 mode).
    """
    if any_step:
        if not (math.isfinite(step_deg) and step_deg > 0 and 0 < fov_deg <= 360):
            raise ValueError(f"need a step > 0 and a field in (0, 360] deg, got fov "
                             f"{fov_deg} deg, step {step_deg} deg")
        return int(math.floor(fov_deg / step_deg + 1e-9)) + 1
    try:
        return _SCAN_MODES[(float(fov_deg), float(step_deg))]
    except KeyError:
        raise ValueError(f"not an LMS200 mode: fov {fov_deg} deg, step {step_deg} deg; "
                         "choose one of " + ", ".join(f"{f:g}/{s:g}" for f, s in _SCAN_MODES)) from None


def beam_angles_rad(fov_deg: float, step_deg: float, *, any_step: bool = False) -> np.ndarray:
    """Beam bearings ``a_k = -fov/2 + k * step`` (rad), k = 0 .. scan_count - 1, shape (n,)."""
    count = scan_count(fov_deg, step_deg, any_step=any_step)
    return np.radians(-0.5 * fov_deg + step_deg * np.arange(count))


def beam_directions_scanner_frame(fov_deg: float, step_deg: float, *,
                                  any_step: bool = False) -> np.ndarray:
    """Unit beam directions in the scanner frame, shape (n, 3).

    The single definition of the scan geometry (Foxglove ``LaserScan`` / ROS convention):
    the scan plane is the scanner's x-y plane, bearing ``a`` counter-clockwise about +z
    from +x, ``a_k = -fov/2 + k * step`` (first value at -fov/2), direction
    ``(cos a, sin a, 0)``.  A point is ``position + R @ (range * direction)`` in the site
    frame for a pose (position, R).
    """
    a = beam_angles_rad(fov_deg, step_deg, any_step=any_step)
    return np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)


def rotation_matrix(rotation) -> np.ndarray:
    """A (3, 3) rotation matrix from a matrix or a quaternion.

    Parameters
    ----------
    rotation : array_like, shape (3, 3) or (4,)
        Rotation matrix (columns = scanner axes in the site frame), or a quaternion in
        Foxglove/ROS order ``(x, y, z, w)`` (normalised here).

    Raises
    ------
    ValueError
        On another shape, a zero quaternion or a matrix that is not a proper rotation.
    """
    r = np.asarray(rotation, float)
    if r.shape == (4,):
        nq = np.linalg.norm(r)
        if not nq > 0:
            raise ValueError("zero quaternion")
        x, y, z, w = r / nq
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    if r.shape == (3, 3):
        if not (np.allclose(r.T @ r, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0):
            raise ValueError("rotation matrix must be orthonormal with determinant +1")
        return r
    raise ValueError(f"rotation must be a (3, 3) matrix or an (x, y, z, w) quaternion, "
                     f"got {r.shape}")


class ScannerModel:
    """A SICK LMS200 on the boom, scanning a heightmap.

    Per beam: the true range by :func:`raycast_heightmap`; at depth discontinuities
    (a neighbouring beam's true range differs by more than ``mixed_pixel_jump_m``) with
    probability ``mixed_pixel_prob`` a mixed pixel ``r + w (r_neighbour - r)``, w ~ U(0, 1)
    (the footprint straddles the edge, thesis §3.4); Gaussian noise with sd
    ``sqrt(range_noise_m^2 + (range_noise_frac r)^2)``; ranges beyond the maximum become
    no-hit; quantisation to the unit (10 mm, or 1 mm in mm mode); dropouts (NaN) with
    probability ``dropout_prob``; error codes (NaN) with probability ``error_code_prob``.
    All parameters are keyword-only.

    Parameters
    ----------
    fov_deg, step_deg : float
        An LMS200 mode (see :func:`scan_count`), or with ``any_step`` any step and field.
    range_noise_m : float
        Constant part of the range noise sd (14.5 mm measured on a flat table).
    range_noise_frac : float
        Range-proportional part of the sd (fraction of range).
    max_range_m : float
        Maximum range (80 m in cm mode).  In mm mode the 13-bit scale caps it at 8.18 m.
    unit_mm : bool
        mm mode: 1 mm resolution (else 10 mm, the cm mode).
    mixed_pixel_prob, mixed_pixel_jump_m : float
        Mixed-pixel probability per beam next to a range jump, and the jump threshold.
    dropout_prob, error_code_prob : float
        Per-beam probabilities.
    rng : numpy.random.Generator
        Required.
    any_step : bool
        Cast any step and field (:func:`scan_count`), not only the LMS200's modes.
    """

    MM_MODE_MAX_RANGE_M = 8.18

    def __init__(self, *, fov_deg: float = 100.0, step_deg: float = 0.25,
                 range_noise_m: float = 0.0145, range_noise_frac: float = 2.0e-4,
                 max_range_m: float = 80.0, unit_mm: bool = False,
                 mixed_pixel_prob: float = 0.5, mixed_pixel_jump_m: float = 0.3,
                 dropout_prob: float = 0.002, error_code_prob: float = 0.0005,
                 rng: np.random.Generator, any_step: bool = False) -> None:
        self.fov_deg, self.step_deg = float(fov_deg), float(step_deg)
        self.n_beams = scan_count(fov_deg, step_deg, any_step=any_step)
        for name, p in (("mixed_pixel_prob", mixed_pixel_prob), ("dropout_prob", dropout_prob),
                        ("error_code_prob", error_code_prob)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {p}")
        if range_noise_m < 0 or range_noise_frac < 0 or not max_range_m > 0:
            raise ValueError("noise must be >= 0 and max_range_m > 0")
        self.range_noise_m = float(range_noise_m)
        self.range_noise_frac = float(range_noise_frac)
        self.unit_mm = bool(unit_mm)
        self.resolution_m = 0.001 if unit_mm else 0.01
        self.max_range_m = min(float(max_range_m), self.MM_MODE_MAX_RANGE_M) if unit_mm \
            else float(max_range_m)
        self.mixed_pixel_prob = float(mixed_pixel_prob)
        self.mixed_pixel_jump_m = float(mixed_pixel_jump_m)
        self.dropout_prob = float(dropout_prob)
        self.error_code_prob = float(error_code_prob)
        self.rng = check_rng(rng)
        self.angles_rad = beam_angles_rad(fov_deg, step_deg, any_step=any_step)
        self.directions = beam_directions_scanner_frame(fov_deg, step_deg, any_step=any_step)

    def beam_directions_site(self, rotation) -> np.ndarray:
        """Beam directions (n, 3) in the site frame for a scanner rotation (see pose)."""
        return self.directions @ rotation_matrix(rotation).T

    def true_ranges(self, height_m, origin_x_m: float, origin_y_m: float, cell_m: float,
                    position_m, rotation) -> np.ndarray:
        """Noise-free ranges (n,) (NaN = no hit within the maximum range)."""
        p = np.asarray(position_m, float)
        if p.shape != (3,):
            raise ValueError(f"position_m must have shape (3,), got {p.shape}")
        return raycast_heightmap(height_m, origin_x_m, origin_y_m, cell_m, p,
                                 self.beam_directions_site(rotation), self.max_range_m)

    def scan_with_status(self, height_m, origin_x_m: float, origin_y_m: float, cell_m: float,
                         position_m, rotation) -> tuple[np.ndarray, np.ndarray]:
        """One scan with per-beam status.

        Parameters
        ----------
        height_m : ndarray (ny, nx)
            Heightmap (see :func:`raycast_heightmap` for the grid convention).
        origin_x_m, origin_y_m, cell_m : float
            Grid corner and cell size (m).
        position_m : array_like (3,)
            Scanner origin in the site frame (m).
        rotation : array_like (3, 3) or (4,)
            Scanner orientation: matrix mapping scanner-frame vectors to the site frame,
            or quaternion (x, y, z, w).

        Returns
        -------
        ranges_m : ndarray (n,)
            Measured ranges (m), quantised; NaN where status is not OK/MIXED.
        status : ndarray (n,) int8
            :data:`BEAM_OK`, :data:`BEAM_NO_HIT`, :data:`BEAM_DROPOUT`,
            :data:`BEAM_ERROR_CODE` or :data:`BEAM_MIXED`.
        """
        r_true = self.true_ranges(height_m, origin_x_m, origin_y_m, cell_m, position_m, rotation)
        rng, n = self.rng, self.n_beams
        status = np.where(np.isnan(r_true), BEAM_NO_HIT, BEAM_OK).astype(np.int8)
        r = r_true.copy()
        # mixed pixels: next to a depth jump, pick the neighbour with the larger jump
        if self.mixed_pixel_prob > 0 and n > 1:
            left = np.full(n, np.nan)
            right = np.full(n, np.nan)
            left[1:] = r_true[:-1]
            right[:-1] = r_true[1:]
            with np.errstate(invalid="ignore"):
                jl = np.abs(left - r_true)
                jr = np.abs(right - r_true)
            jl = np.where(np.isnan(jl), -1.0, jl)
            jr = np.where(np.isnan(jr), -1.0, jr)
            other = np.where(jl >= jr, left, right)
            jump = np.maximum(jl, jr)
            mixed = (jump > self.mixed_pixel_jump_m) & (status == BEAM_OK) \
                & (rng.random(n) < self.mixed_pixel_prob)
            w = rng.random(n)
            r = np.where(mixed, r_true + w * (other - r_true), r)
            status[mixed] = BEAM_MIXED
        sd = np.sqrt(self.range_noise_m ** 2 + (self.range_noise_frac * np.nan_to_num(r)) ** 2)
        r = np.maximum(r + sd * rng.standard_normal(n), 0.0)
        beyond = r > self.max_range_m
        status[beyond] = BEAM_NO_HIT
        r = np.round(r / self.resolution_m) * self.resolution_m
        hit = (status == BEAM_OK) | (status == BEAM_MIXED)
        status[hit & (rng.random(n) < self.dropout_prob)] = BEAM_DROPOUT
        status[rng.random(n) < self.error_code_prob] = BEAM_ERROR_CODE
        r[(status != BEAM_OK) & (status != BEAM_MIXED)] = np.nan
        return r, status

    def scan(self, height_m, origin_x_m: float, origin_y_m: float, cell_m: float,
             position_m, rotation) -> np.ndarray:
        """One scan: measured ranges (n,) in metres, NaN = no return / dropout / error code.

        See :meth:`scan_with_status` for the parameters and the per-beam status.
        """
        return self.scan_with_status(height_m, origin_x_m, origin_y_m, cell_m, position_m,
                                     rotation)[0]

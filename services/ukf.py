"""Localisation of a bucket-wheel reclaimer: an unscented Kalman filter over its joints.

Pure numerics, no I/O: the localizer service (:mod:`services.localizer`), the benchmark
(``bench/localizer.py``) and the tests drive it.  Thesis §3.1-§3.3 (Zhao 2016) fuses
GNSS and joint encoders with a UKF; DOMAIN.md §3 is the kinematic contract.

Frames and units
----------------
Site frame: ENU metres, x across the pile, y along the rail, z up.  Joints: travel
``d1`` (m, along +y), slew ``theta2`` (rad, boom azimuth from +y toward +x), luff
``theta3`` (rad, boom elevation).  Times are UTC nanoseconds.

The filter
----------
State (9): ``x = [travel_m, slew_rad, luff_rad, travel_bias_m, slew_bias_rad,
luff_bias_rad, gnss_err_e_m, gnss_err_n_m, gnss_err_u_m]``.

- *Joints* follow a random walk whose step over ``dt`` has sd ``joint_rate_sd * dt``
  (the machine moves at bounded rates; the encoders pin the joints at every reading).
- *Encoder biases* (drift: slip, scale error, slop; thesis §3.1 "degrade without
  boundary") are random walks in sqrt(time) and in sqrt(distance moved).  The motion
  part is added at each reading from the change since the previous reading.
- *GNSS error* has a time-correlated part (the DGPS residual, a first-order
  Gauss-Markov process, thesis §3.2.2 / eq. 3.17) carried in the state, so a slowly
  wandering fix is not mistaken for encoder drift; the fix's own covariance is the white
  part.  ``gnss_markov_sd_m = 0`` turns it off (the last three states stay 0).
- An encoder reading measures ``joint + bias`` (``R`` from the resolution and noise).
- A GNSS fix measures the antenna's site position: forward kinematics of the joints
  (the antenna on the boom, DOMAIN.md §3) plus the correlated error.  Fixes whose
  squared Mahalanobis distance exceeds the chi-square quantile (3 dof, ``gate_probability``)
  are rejected (counted), so the heavy-tailed yard noise (impulses, Cauchy, ignition,
  UWB bursts, correction outages) does not pull the estimate.  When every fix for
  ``regate_after_s`` has been rejected the filter assumes it is the one that is wrong (an encoder slipped or was re-zeroed): it re-opens the bias covariance by
  the joint change that explains the rejected fixes' mean innovation, so the next fixes
  pull it back (counted as ``regates``).
- Fixes coarser than ``max_fix_sd_m`` (no differential corrections: metres of error
  correlated over minutes) are not fused at all (``"skipped"``).

Numerical care: ``P`` is symmetrised after every step and its matrix square root is a
Cholesky factor with escalating diagonal jitter (then an eigenvalue clip) when the
factorisation fails, so it never raises on a nearly singular ``P``; measurement
covariances are floored (never ``R = 0``).

Sigma points: :class:`filterpy.kalman.MerweScaledSigmaPoints` (alpha 0.5, beta 2,
kappa 0); filter: :class:`filterpy.kalman.UnscentedKalmanFilter`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from filterpy.kalman import unscented_transform
from scipy.linalg import cholesky
from scipy.stats import chi2

__all__ = [
    "MachineGeometry", "FilterTuning", "Estimate", "LocalizerFilter", "GnssOutcome",
    "wheel_centre_m", "antenna_position_m", "wheel_rotation", "wheel_quaternion_xyzw",
    "quaternion_multiply", "quaternion_to_matrix", "scanner_pose", "gnss_covariance_m2",
    "robust_sqrt", "filter_sequence", "FilterCounters", "SequenceResult",
]

NS_PER_S = 1_000_000_000
N_STATE = 9
_JOINTS = slice(0, 3)
_BIAS = slice(3, 6)
_GNSS = slice(6, 9)

GnssOutcome = Literal["accepted", "gated", "skipped"]


# --------------------------------------------------------------------------------------
# Geometry (DOMAIN.md §3), from the machine_declared event's fields
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class MachineGeometry:
    """Kinematic constants of a reclaimer, its GNSS antenna and its scanner mount.

    Attributes
    ----------
    rail_x_m, rail_z_m : float
        Rail position across the pile and rail height (site frame, m).
    l2_m, l3_m : float
        ``L2 + L3`` = height of the boom pivot above the rail (m).
    l4_m : float
        Horizontal offset of the pivot from the slew axis (m).
    l5_m : float
        Boom length, pivot -> wheel centre (m).
    antenna_along_boom_m : float
        GNSS antenna beyond the wheel centre along the boom (negative = toward the pivot);
        0 = at the wheel centre (the simulator's default).
    antenna_up_m : float
        Antenna mast height above that boom point (site +z, m).
    scanner_translation_m : tuple of 3 float
        Scanner origin in the wheel frame (m); ``MachineDeclared.scanner.translation``.
    scanner_rotation_xyzw : tuple of 4 float
        Scanner orientation in the wheel frame, unit quaternion (x, y, z, w);
        ``MachineDeclared.scanner.rotation``.
    """

    rail_x_m: float
    rail_z_m: float
    l2_m: float
    l3_m: float
    l4_m: float
    l5_m: float
    antenna_along_boom_m: float = 0.0
    antenna_up_m: float = 0.0
    scanner_translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scanner_rotation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        values = (self.rail_x_m, self.rail_z_m, self.l2_m, self.l3_m, self.l4_m, self.l5_m,
                  self.antenna_along_boom_m, self.antenna_up_m, *self.scanner_translation_m,
                  *self.scanner_rotation_xyzw)
        if len(self.scanner_translation_m) != 3 or len(self.scanner_rotation_xyzw) != 4:
            raise ValueError("scanner_translation_m needs 3 values and scanner_rotation_xyzw 4")
        if not all(math.isfinite(v) for v in values):
            raise ValueError("machine geometry must be finite")
        if not self.l5_m > 0:
            raise ValueError(f"l5_m (boom length) must be > 0, got {self.l5_m}")
        if not math.isclose(float(np.linalg.norm(self.scanner_rotation_xyzw)), 1.0,
                            abs_tol=1e-3):
            raise ValueError("scanner_rotation_xyzw must be a unit quaternion")

    @property
    def pivot_height_m(self) -> float:
        """Height of the boom pivot above the rail, ``L2 + L3`` (m)."""
        return self.l2_m + self.l3_m

    @classmethod
    def from_machine_declared(cls, message: Any, *, antenna_along_boom_m: float = 0.0,
                              antenna_up_m: float = 0.0) -> MachineGeometry:
        """Geometry from a ``stockpile.v1.MachineDeclared`` message.

        The schema has no antenna mount yet, so the antenna offsets are parameters
        (default: antenna at the wheel centre, as in the simulator).  A declaration
        without a scanner mount gets the identity mount.

        Raises
        ------
        ValueError
            On non-finite or impossible values.
        """
        scanner = message.scanner
        if message.HasField("scanner"):
            t = (scanner.translation.x, scanner.translation.y, scanner.translation.z)
            q = (scanner.rotation.x, scanner.rotation.y, scanner.rotation.z, scanner.rotation.w)
        else:
            t, q = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)
        return cls(rail_x_m=message.rail_x_m, rail_z_m=message.rail_z_m, l2_m=message.l2_m,
                   l3_m=message.l3_m, l4_m=message.l4_m, l5_m=message.l5_m,
                   antenna_along_boom_m=float(antenna_along_boom_m),
                   antenna_up_m=float(antenna_up_m), scanner_translation_m=tuple(map(float, t)),
                   scanner_rotation_xyzw=tuple(map(float, q)))


def _joint_columns(joints) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    j = np.asarray(joints, float)
    if j.ndim < 1 or j.shape[-1] != 3:
        raise ValueError(f"joints must have shape (..., 3), got {j.shape}")
    return j[..., 0], j[..., 1], j[..., 2]


def wheel_centre_m(geometry: MachineGeometry, joints) -> np.ndarray:
    """Forward kinematics of DOMAIN.md §3: the wheel centre in the site frame.

    Parameters
    ----------
    geometry : MachineGeometry
    joints : array_like, shape (..., 3)
        (travel m, slew rad, luff rad).

    Returns
    -------
    ndarray, shape (..., 3)
        (x, y, z) in metres.

    Raises
    ------
    ValueError
        If the last axis of ``joints`` is not 3.
    """
    return _boom_point_m(geometry, joints, 0.0, 0.0)


def antenna_position_m(geometry: MachineGeometry, joints) -> np.ndarray:
    """The GNSS antenna in the site frame: a point on the boom, shape (..., 3) (m).

    ``antenna_along_boom_m`` beyond the wheel centre along the (luffed) boom, then
    ``antenna_up_m`` straight up.  See :func:`wheel_centre_m` for ``joints``.
    """
    return _boom_point_m(geometry, joints, geometry.antenna_along_boom_m, geometry.antenna_up_m)


def _boom_point_m(g: MachineGeometry, joints, along_m: float, up_m: float) -> np.ndarray:
    travel, slew, luff = _joint_columns(joints)
    boom = g.l5_m + along_m
    rho = g.l4_m + boom * np.cos(luff)
    x = g.rail_x_m + rho * np.sin(slew)
    y = travel + rho * np.cos(slew)
    z = g.rail_z_m + g.pivot_height_m + boom * np.sin(luff) + up_m
    return np.stack([x, y, z], axis=-1)


def _boom_point_scalar(g: MachineGeometry, travel: float, slew: float, luff: float,
                       along_m: float, up_m: float) -> np.ndarray:
    """The same as :func:`_boom_point_m` for one joint triple (fast path for sigma points)."""
    boom = g.l5_m + along_m
    rho = g.l4_m + boom * math.cos(luff)
    return np.array([g.rail_x_m + rho * math.sin(slew), travel + rho * math.cos(slew),
                     g.rail_z_m + g.pivot_height_m + boom * math.sin(luff) + up_m])


def wheel_rotation(slew_rad: float) -> np.ndarray:
    """Rotation (3, 3) of the wheel frame in the site frame.

    The wheel frame is level: x along the boom's horizontal direction
    ``(sin slew, cos slew, 0)``, z up, y = z x x.  The luff does not tilt it (the
    scanner hangs level below the wheel, as in the simulator's scanner pose).
    """
    s, c = math.sin(slew_rad), math.cos(slew_rad)
    return np.array([[s, -c, 0.0], [c, s, 0.0], [0.0, 0.0, 1.0]])


def wheel_quaternion_xyzw(slew_rad: float) -> np.ndarray:
    """:func:`wheel_rotation` as a unit quaternion (x, y, z, w): a yaw of pi/2 - slew."""
    half = 0.5 * (0.5 * math.pi - slew_rad)
    return np.array([0.0, 0.0, math.sin(half), math.cos(half)])


def quaternion_multiply(a, b) -> np.ndarray:
    """Hamilton product ``a * b`` of quaternions in (x, y, z, w) order (rotate by b, then a)."""
    ax, ay, az, aw = (float(v) for v in a)
    bx, by, bz, bw = (float(v) for v in b)
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def quaternion_to_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion (x, y, z, w) (normalised here).

    Raises
    ------
    ValueError
        On a shape other than (4,) or a zero quaternion.
    """
    q = np.asarray(q, float)
    if q.shape != (4,):
        raise ValueError(f"quaternion must have shape (4,), got {q.shape}")
    n = float(np.linalg.norm(q))
    if not n > 0:
        raise ValueError("zero quaternion")
    x, y, z, w = q / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def scanner_pose(geometry: MachineGeometry, joints) -> tuple[np.ndarray, np.ndarray]:
    """Scanner pose in the site frame: the wheel pose composed with the scanner mount.

    ``position = wheel_centre + R_wheel @ t_mount``; ``q = q_wheel * q_mount``.

    Parameters
    ----------
    geometry : MachineGeometry
    joints : array_like, shape (3,)
        (travel m, slew rad, luff rad).

    Returns
    -------
    position_m : ndarray (3,)
    rotation_xyzw : ndarray (4,)
        Unit quaternion, w >= 0.
    """
    j = np.asarray(joints, float)
    if j.shape != (3,):
        raise ValueError(f"joints must have shape (3,), got {j.shape}")
    centre = wheel_centre_m(geometry, j)
    position = centre + wheel_rotation(j[1]) @ np.asarray(geometry.scanner_translation_m)
    q = quaternion_multiply(wheel_quaternion_xyzw(j[1]), geometry.scanner_rotation_xyzw)
    q /= np.linalg.norm(q)
    return position, (q if q[3] >= 0 else -q)


# --------------------------------------------------------------------------------------
# Noise model
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class FilterTuning:
    """Process and measurement noise of :class:`LocalizerFilter` (SI units, radians).

    Each 3-tuple is over (travel, slew, luff).  The defaults suit the thesis' encoder
    sets (§3.3) and a DGPS receiver with a ~31 km baseline (eq. 3.17).

    Attributes
    ----------
    encoder_sd : 3-tuple
        White reading noise (m, rad, rad), including quantisation; floored at
        ``1e-4 m`` / ``1e-6 rad`` so ``R`` is never 0.
    joint_rate_sd : 3-tuple
        Sd of the joint rate (m/s, rad/s, rad/s): a joint's predicted step over ``dt``
        has sd ``joint_rate_sd * dt``.
    bias_walk_per_sqrt_s : 3-tuple
        Encoder drift with time: bias random walk, sd per sqrt(second).
    bias_walk_per_sqrt_moved : 3-tuple
        Encoder drift with motion: sd per sqrt(metre) for travel, per sqrt(radian) for
        slew and luff.
    travel_scale_sd : float
        Travel scale-factor uncertainty: bias sd grows by this fraction of each move.
    initial_joint_sd, initial_bias_sd : 3-tuple
        Initial uncertainty of the joints (around the first reading) and the biases
        (around 0).
    gnss_markov_sd_m : 3-tuple
        Stationary sd (east, north, up) of the time-correlated GNSS error state;
        0 = no correlated error modelled.
    gnss_markov_tau_s : float
        Its correlation time (s).
    gnss_min_sd_m : float
        Floor of a fix's white sd (m): ``R`` is never below ``gnss_min_sd_m**2``.
    max_fix_sd_m : float
        Fixes whose horizontal sd (largest eigenvalue of the covariance's east-north
        block) exceeds this are not fused (``"skipped"``): without differential
        corrections a receiver's error is metres and correlated over minutes (thesis
        Table 3.2), which a white measurement model would average as if independent and
        be pulled by.  ``inf`` fuses every fix.
    gate_probability : float
        Chi-square (3 dof) probability of the Mahalanobis gate, in (0, 1).
    regate_after_s : float
        When every fix for this long (and at least ``regate_min_fixes`` fixes) has been
        rejected, the bias covariance is re-opened (0 = never).  Longer than the usual
        loss of differential corrections, whose autonomous fixes a front end may not
        mark as coarse: re-opening then would pull the estimate onto their metres of
        error.
    regate_min_fixes : int
        Fewest rejected fixes in such a run.
    alpha, beta, kappa : float
        Merwe scaled sigma point parameters.
    """

    encoder_sd: tuple[float, float, float] = (0.001, math.radians(0.005), math.radians(0.01))
    joint_rate_sd: tuple[float, float, float] = (0.5, math.radians(1.0), math.radians(0.5))
    bias_walk_per_sqrt_s: tuple[float, float, float] = (1e-4, math.radians(0.015),
                                                        math.radians(0.012))
    bias_walk_per_sqrt_moved: tuple[float, float, float] = (0.01, math.radians(0.0068)
                                                            / math.sqrt(math.radians(1.0)),
                                                            math.radians(0.016)
                                                            / math.sqrt(math.radians(1.0)))
    travel_scale_sd: float = 0.002
    initial_joint_sd: tuple[float, float, float] = (0.01, math.radians(0.01), math.radians(0.01))
    initial_bias_sd: tuple[float, float, float] = (0.3, math.radians(0.3), math.radians(0.3))
    gnss_markov_sd_m: tuple[float, float, float] = (0.19, 0.19, 0.33)
    gnss_markov_tau_s: float = 60.0
    gnss_min_sd_m: float = 0.02
    max_fix_sd_m: float = 1.5
    gate_probability: float = 0.999
    regate_after_s: float = 120.0
    regate_min_fixes: int = 10
    alpha: float = 0.5
    beta: float = 2.0
    kappa: float = 0.0

    def __post_init__(self) -> None:
        for name in ("encoder_sd", "joint_rate_sd", "bias_walk_per_sqrt_s",
                     "bias_walk_per_sqrt_moved", "initial_joint_sd", "initial_bias_sd",
                     "gnss_markov_sd_m"):
            v = getattr(self, name)
            if len(v) != 3 or not all(math.isfinite(x) and x >= 0 for x in v):
                raise ValueError(f"{name} must be 3 finite values >= 0, got {v!r}")
        if not 0.0 < self.gate_probability < 1.0:
            raise ValueError(f"gate_probability must be in (0, 1), got {self.gate_probability}")
        if not (self.gnss_markov_tau_s > 0 and self.gnss_min_sd_m > 0 and 0 < self.alpha <= 1
                and self.max_fix_sd_m > self.gnss_min_sd_m
                and self.travel_scale_sd >= 0 and self.regate_after_s >= 0
                and self.regate_min_fixes >= 1):
            raise ValueError("gnss_markov_tau_s, gnss_min_sd_m must be > 0, alpha in (0, 1], "
                             "max_fix_sd_m > gnss_min_sd_m, travel_scale_sd and regate_after_s "
                             ">= 0, regate_min_fixes >= 1")

    @property
    def gate_d2(self) -> float:
        """Squared Mahalanobis distance above which a fix is rejected."""
        return float(chi2.ppf(self.gate_probability, 3))


def gnss_covariance_m2(hdop: float, *, dgps: bool = True, dgps_sd_m: float = 0.45,
                       autonomous_sd_m: float = 2.5, hdop_nominal: float = 4.0 / 3.0,
                       vertical_factor: float = 1.7) -> np.ndarray:
    """A diagonal ENU covariance (3, 3) in m^2 for a GNSS fix from its quality and HDOP.

    What a GNSS front end can put in ``LocationFix.position_covariance`` when the
    receiver reports no covariance of its own: per horizontal axis ``dgps_sd_m`` with
    differential corrections (eq. 3.17's residual plus the core of the yard's
    heavy-tailed noise), ``autonomous_sd_m`` without (Table 3.2), both scaled by
    ``hdop / hdop_nominal``; the vertical sd is ``vertical_factor`` times larger.

    Raises
    ------
    ValueError
        If ``hdop`` is not finite and > 0.
    """
    if not (math.isfinite(hdop) and hdop > 0):
        raise ValueError(f"hdop must be finite and > 0, got {hdop}")
    sd = (dgps_sd_m if dgps else autonomous_sd_m) * max(hdop / hdop_nominal, 0.5)
    return np.diag([sd * sd, sd * sd, (vertical_factor * sd) ** 2])


# --------------------------------------------------------------------------------------
# Matrix helpers
# --------------------------------------------------------------------------------------

def _symmetrise(p: np.ndarray) -> np.ndarray:
    return 0.5 * (p + p.T)


def robust_sqrt(p: np.ndarray) -> np.ndarray:
    """Upper-triangular square root ``U`` (``U.T @ U = P``) that never raises on a bad P.

    Tries :func:`scipy.linalg.cholesky` on the symmetrised matrix, then with diagonal
    jitter growing from ``1e-12`` to ``1e-3`` times the mean diagonal, then falls back
    to an eigen-decomposition with negative eigenvalues clipped (returned as the upper
    factor of a QR of ``diag(sqrt(w)) V.T``).

    Parameters
    ----------
    p : ndarray (n, n)
        A covariance-like matrix (already scaled as the sigma points need it).

    Raises
    ------
    ValueError
        If ``p`` is not square or contains non-finite values.
    """
    p = np.asarray(p, float)
    if p.ndim != 2 or p.shape[0] != p.shape[1]:
        raise ValueError(f"matrix must be square, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("matrix has non-finite values")
    p = _symmetrise(p)
    try:
        return cholesky(p, lower=False, check_finite=False)
    except np.linalg.LinAlgError:
        pass
    scale = max(float(np.mean(np.abs(np.diag(p)))), 1e-300)
    eye = np.eye(p.shape[0])
    for k in range(-12, -2):
        try:
            return cholesky(p + (10.0 ** k) * scale * eye, lower=False, check_finite=False)
        except np.linalg.LinAlgError:
            continue
    w, v = np.linalg.eigh(p)
    half = np.sqrt(np.clip(w, 1e-12 * scale, None))[:, None] * v.T
    r = np.linalg.qr(half, mode="r")
    return r


def _make_pd(p: np.ndarray) -> np.ndarray:
    """Symmetrise; if a Cholesky factorisation fails, clip the eigenvalues to be > 0."""
    p = _symmetrise(p)
    try:
        np.linalg.cholesky(p)
        return p
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(p)
        floor = 1e-12 * max(float(np.max(np.abs(w))), 1e-300)
        return _symmetrise((v * np.clip(w, floor, None)) @ v.T)


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


# --------------------------------------------------------------------------------------
# The filter
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Estimate:
    """The filter's current belief.

    Attributes
    ----------
    t_ns : int
        Time of the estimate (UTC ns).
    joints : ndarray (3,)
        (travel m, slew rad, luff rad): the true joints' estimate (reading minus bias).
    joint_covariance : ndarray (3, 3)
        Covariance over (travel, slew, luff) in m^2, m rad, rad^2.
    bias : ndarray (3,)
        Estimated encoder bias (m, rad, rad).
    wheel_centre_m : ndarray (3,)
        Wheel centre in the site frame: forward kinematics of ``joints`` (m).
    wheel_covariance_m2 : ndarray (3, 3)
        Its covariance (m^2), by the unscented transform of the joint belief.
    """

    t_ns: int
    joints: np.ndarray
    joint_covariance: np.ndarray
    bias: np.ndarray
    wheel_centre_m: np.ndarray
    wheel_covariance_m2: np.ndarray


@dataclass
class FilterCounters:
    """What the filter did: updates per sensor, gated fixes, re-inflations, undone steps."""

    joint_updates: int = 0
    gnss_accepted: int = 0
    gnss_gated: int = 0
    gnss_skipped: int = 0
    regates: int = 0
    consecutive_gated: int = 0
    numeric_rejects: int = 0
    sqrt_repairs: int = 0


class _SigmaPoints(MerweScaledSigmaPoints):
    """filterpy's Merwe scaled sigma points, generated without a Python loop.

    Same points and weights as the base class: ``x``, ``x + U[k]``, ``x - U[k]`` with
    ``U = sqrt((n + lambda) P)`` (upper-triangular factor, rows as directions).
    """

    def sigma_points(self, x, P):  # noqa: N803 - filterpy's signature
        n = self.n
        x = np.asarray(x, float)
        if x.size != n:
            raise ValueError(f"expected size(x) {n}, but size is {x.size}")
        lambda_ = self.alpha ** 2 * (n + self.kappa) - n
        u = self.sqrt((lambda_ + n) * np.asarray(P, float))
        return np.vstack([x[None, :], x + u, x - u])


class _UKF(UnscentedKalmanFilter):
    """filterpy's UKF with the per-sigma-point Python loops of two steps vectorised.

    ``fx`` must accept the whole (2n+1, n) sigma array (the transition here is linear
    per state); the cross covariance is one matrix product.  Results are identical to
    the base class.
    """

    def compute_process_sigmas(self, dt, fx=None, **fx_args):
        fx = self.fx if fx is None else fx
        sigmas = self.points_fn.sigma_points(self.x, self.P)
        self.sigmas_f = fx(sigmas, dt, **fx_args)

    def cross_variance(self, x, z, sigmas_f, sigmas_h):
        dx = sigmas_f - x
        dz = sigmas_h - z
        return (dx * self.Wc[:, None]).T @ dz


class LocalizerFilter:
    """UKF over the joints, encoder biases and the correlated GNSS error of a reclaimer.

    See the module docstring for the model.  Usage::

        f = LocalizerFilter(geometry)
        f.predict_to(t_ns); f.update_joints([travel_m, slew_rad, luff_rad])
        f.predict_to(t_fix_ns); f.update_gnss(enu_m, cov_m2)   # -> "accepted" | "gated"
        f.estimate()

    The first :meth:`update_joints` initialises the joints at the reading (biases 0);
    fixes before it are ``"skipped"``.  Times must not go backwards.

    Parameters
    ----------
    geometry : MachineGeometry
        The machine (from its ``machine_declared`` event).
    tuning : FilterTuning, optional
        Noise model; default :class:`FilterTuning()`.
    """

    def __init__(self, geometry: MachineGeometry, tuning: FilterTuning | None = None) -> None:
        if not isinstance(geometry, MachineGeometry):
            raise TypeError("geometry must be a MachineGeometry")
        self.geometry = geometry
        self.tuning = tuning if tuning is not None else FilterTuning()
        tn = self.tuning
        self._points = _SigmaPoints(N_STATE, alpha=tn.alpha, beta=tn.beta,
                                              kappa=tn.kappa, sqrt_method=self._sqrt)
        self._ukf = _UKF(dim_x=N_STATE, dim_z=3, dt=1.0, hx=self._hx_joints,
                                          fx=self._fx, points=self._points,
                                          sqrt_fn=self._sqrt)
        self._points3 = MerweScaledSigmaPoints(3, alpha=tn.alpha, beta=tn.beta, kappa=tn.kappa,
                                               sqrt_method=robust_sqrt)
        self._gate_d2 = tn.gate_d2
        self._enc_r = np.diag(np.maximum(np.asarray(tn.encoder_sd), [1e-4, 1e-6, 1e-6]) ** 2)
        self._gm_sd = np.asarray(tn.gnss_markov_sd_m, float)
        self._use_gm = bool(np.any(self._gm_sd > 0))
        self.t_ns: int | None = None
        #: squared Mahalanobis distance of the last fix's innovation (inf if unusable)
        self.last_gnss_d2 = math.nan
        self._gated_innovation_sum = np.zeros(3)
        self._gated_since_ns = 0
        self._last_reading: np.ndarray | None = None
        self.counters = FilterCounters()

    # -- state access -----------------------------------------------------------------

    @property
    def initialised(self) -> bool:
        """Whether a joint reading has initialised the filter."""
        return self._last_reading is not None

    @property
    def x(self) -> np.ndarray:
        """A copy of the state vector (9,)."""
        return self._ukf.x.copy()

    @property
    def P(self) -> np.ndarray:  # noqa: N802 - the filter's conventional name
        """A copy of the state covariance (9, 9)."""
        return self._ukf.P.copy()

    def set_geometry(self, geometry: MachineGeometry) -> None:
        """Replace the machine geometry (a re-declared machine); the state is kept."""
        if not isinstance(geometry, MachineGeometry):
            raise TypeError("geometry must be a MachineGeometry")
        self.geometry = geometry

    # -- model ------------------------------------------------------------------------

    def _sqrt(self, p: np.ndarray) -> np.ndarray:
        try:
            return np.linalg.cholesky(p).T     # upper factor, as scipy's cholesky gives
        except np.linalg.LinAlgError:
            self.counters.sqrt_repairs += 1
            return robust_sqrt(p)

    def _fx(self, sigmas: np.ndarray, dt: float) -> np.ndarray:
        """State transition of all sigma points (2n+1, n): joints and biases are random
        walks (identity), the correlated GNSS error decays by ``exp(-dt / tau)``."""
        out = np.array(sigmas, float, copy=True)
        if self._use_gm:
            out[..., _GNSS] *= math.exp(-dt / self.tuning.gnss_markov_tau_s)
        return out

    @staticmethod
    def _hx_joints(x: np.ndarray) -> np.ndarray:
        return x[_JOINTS] + x[_BIAS]

    def _hx_gnss(self, x: np.ndarray) -> np.ndarray:
        g = self.geometry
        return _boom_point_scalar(g, x[0], x[1], x[2], g.antenna_along_boom_m,
                                  g.antenna_up_m) + x[_GNSS]

    @staticmethod
    def _joint_delta(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``a - b`` over (travel, slew, luff) with the slew difference wrapped to [-pi, pi)."""
        d = np.subtract(a, b)
        d[1] = _wrap_pi(float(d[1]))
        return d

    def _process_noise(self, dt: float) -> np.ndarray:
        tn = self.tuning
        q = np.zeros(N_STATE)
        q[_JOINTS] = (np.asarray(tn.joint_rate_sd) * dt) ** 2
        q[_BIAS] = np.asarray(tn.bias_walk_per_sqrt_s) ** 2 * dt
        if self._use_gm:
            a = math.exp(-dt / tn.gnss_markov_tau_s)
            q[_GNSS] = self._gm_sd ** 2 * (1.0 - a * a)
        return np.diag(q)

    def _set_state(self, x: np.ndarray, p: np.ndarray) -> None:
        self._ukf.x = np.asarray(x, float)
        self._ukf.P = _make_pd(p)

    def _snapshot(self) -> tuple[np.ndarray, np.ndarray, int | None]:
        return self._ukf.x.copy(), self._ukf.P.copy(), self.t_ns

    def _check_finite(self, snapshot) -> None:
        """Undo the step and raise if it made x or P non-finite (never keep a broken state)."""
        if np.all(np.isfinite(self._ukf.x)) and np.all(np.isfinite(self._ukf.P)):
            return
        self._ukf.x, self._ukf.P, self.t_ns = snapshot[0], snapshot[1], snapshot[2]
        self.counters.numeric_rejects += 1
        raise FloatingPointError("the filter step made the state non-finite; it was undone")

    def _refresh_sigmas(self) -> None:
        """Sigma points of the current (x, P) for the next update (P may have changed)."""
        self._ukf.P = _make_pd(self._ukf.P)
        self._ukf.sigmas_f = self._points.sigma_points(self._ukf.x, self._ukf.P)

    # -- steps ------------------------------------------------------------------------

    def predict_to(self, t_ns: int) -> None:
        """Propagate the belief to ``t_ns`` (UTC ns).  No-op before initialisation.

        Raises
        ------
        ValueError
            If ``t_ns`` is earlier than the filter's time.
        FloatingPointError
            If the step made the state non-finite (it is undone).
        """
        t_ns = int(t_ns)
        if self.t_ns is None:
            return
        if t_ns < self.t_ns:
            raise ValueError(f"time goes backwards: {t_ns} < {self.t_ns}")
        if t_ns == self.t_ns:
            return
        dt = (t_ns - self.t_ns) / NS_PER_S
        snapshot = self._snapshot()
        self._ukf.Q = self._process_noise(dt)
        self._ukf.predict(dt=dt)
        self._ukf.P = _make_pd(self._ukf.P)
        self._check_finite(snapshot)
        self.t_ns = t_ns

    def update_joints(self, reading, t_ns: int | None = None) -> None:
        """Fuse one encoder reading (travel m, slew rad, luff rad).

        Parameters
        ----------
        reading : array_like, shape (3,)
            Finite encoder values.
        t_ns : int, optional
            Reading time; if given the filter is first predicted to it (and the first
            reading sets the filter's time).

        Raises
        ------
        ValueError
            On a wrong shape, non-finite values or a time going backwards.
        FloatingPointError
            If the step made the state non-finite (it is undone).
        """
        z = np.asarray(reading, float)
        if z.shape != (3,):
            raise ValueError(f"reading must have shape (3,), got {z.shape}")
        if not np.all(np.isfinite(z)):
            raise ValueError("reading must be finite")
        tn = self.tuning
        if self._last_reading is None:
            if t_ns is None:
                raise ValueError("the first reading needs its time t_ns")
            x = np.zeros(N_STATE)
            x[_JOINTS] = z
            var = np.zeros(N_STATE)
            var[_JOINTS] = np.asarray(tn.initial_joint_sd) ** 2 + np.diag(self._enc_r)
            var[_BIAS] = np.maximum(np.asarray(tn.initial_bias_sd), 1e-9) ** 2
            var[_GNSS] = np.maximum(self._gm_sd, 1e-6) ** 2
            self._set_state(x, np.diag(var))
            self.t_ns = int(t_ns)
            self._last_reading = z.copy()
            self.counters.joint_updates += 1
            return
        if t_ns is not None:
            self.predict_to(t_ns)
        snapshot = self._snapshot()
        # motion-driven drift since the previous reading
        moved = np.abs(self._joint_delta(z, self._last_reading))
        qm = np.asarray(tn.bias_walk_per_sqrt_moved) ** 2 * moved
        qm[0] += (tn.travel_scale_sd * moved[0]) ** 2
        p = self._ukf.P.copy()
        p[_BIAS, _BIAS] += np.diag(qm)
        self._ukf.P = p
        self._refresh_sigmas()
        # unwrap the slew reading next to the prediction (a reading may wrap at +-pi)
        predicted = self._hx_joints(self._ukf.x)
        z_near = predicted + self._joint_delta(z, predicted)
        self._ukf.update(z_near, R=self._enc_r, hx=self._hx_joints)
        self._ukf.P = _make_pd(self._ukf.P)
        self._check_finite(snapshot)
        self._last_reading = z.copy()
        self.counters.joint_updates += 1

    def update_gnss(self, enu_m, cov_m2, t_ns: int | None = None) -> GnssOutcome:
        """Fuse one GNSS fix of the antenna, unless the Mahalanobis gate rejects it.

        Parameters
        ----------
        enu_m : array_like, shape (3,)
            Antenna position in the site ENU frame (m), finite.
        cov_m2 : array_like, shape (3, 3)
            Fix covariance (m^2), finite; symmetrised and its eigenvalues floored at
            ``tuning.gnss_min_sd_m**2``.
        t_ns : int, optional
            Fix time; if given the filter is first predicted to it.

        Returns
        -------
        {"accepted", "gated", "skipped"}
            ``"skipped"`` before the first joint reading or when the fix is coarser than
            ``tuning.max_fix_sd_m``.

        Raises
        ------
        ValueError
            On wrong shapes, non-finite values or a time going backwards.
        FloatingPointError
            If the step made the state non-finite (it is undone).
        """
        z = np.asarray(enu_m, float)
        r = np.asarray(cov_m2, float)
        if z.shape != (3,) or r.shape != (3, 3):
            raise ValueError(f"enu_m must have shape (3,) and cov_m2 (3, 3); got {z.shape}, "
                             f"{r.shape}")
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(r))):
            raise ValueError("enu_m and cov_m2 must be finite")
        r = _symmetrise(r)
        coarse = float(np.linalg.eigvalsh(r[:2, :2])[-1]) > self.tuning.max_fix_sd_m ** 2
        if self._last_reading is None or coarse:
            self.counters.gnss_skipped += 1
            return "skipped"
        if t_ns is not None:
            self.predict_to(t_ns)
        w, v = np.linalg.eigh(r)
        r = _symmetrise((v * np.maximum(w, self.tuning.gnss_min_sd_m ** 2)) @ v.T)
        self._refresh_sigmas()
        # update, then gate on the innovation's squared Mahalanobis distance
        # y' S^-1 y (S and y from the same unscented transform); a gated fix is undone
        x_prior, p_prior = self._ukf.x.copy(), self._ukf.P.copy()
        try:
            self._ukf.update(z, R=r, hx=self._hx_gnss)
            y, si = self._ukf.y, self._ukf.SI
            d2 = float(y @ si @ y)
        except np.linalg.LinAlgError:
            d2 = math.inf
        c = self.counters
        self.last_gnss_d2 = d2
        if not d2 <= self._gate_d2:
            self._set_state(x_prior, p_prior)
            c.gnss_gated += 1
            c.consecutive_gated += 1
            if c.consecutive_gated == 1:
                self._gated_since_ns = self.t_ns
            if np.all(np.isfinite(self._ukf.y)):
                self._gated_innovation_sum += self._ukf.y
            tn = self.tuning
            if (tn.regate_after_s > 0 and c.consecutive_gated >= tn.regate_min_fixes
                    and self.t_ns - self._gated_since_ns >= tn.regate_after_s * NS_PER_S):
                self._reinflate(self._gated_innovation_sum / c.consecutive_gated)
            return "gated"
        self._ukf.P = _make_pd(self._ukf.P)
        self._check_finite((x_prior, p_prior, self.t_ns))
        c.consecutive_gated = 0
        self._gated_innovation_sum = np.zeros(3)
        c.gnss_accepted += 1
        return "accepted"

    def _antenna_jacobian(self, joints: np.ndarray) -> np.ndarray:
        """d(antenna position) / d(travel, slew, luff), shape (3, 3)."""
        g = self.geometry
        boom = g.l5_m + g.antenna_along_boom_m
        _t, slew, luff = (float(v) for v in joints)
        rho = g.l4_m + boom * math.cos(luff)
        ss, cs, sl, cl = math.sin(slew), math.cos(slew), math.sin(luff), math.cos(luff)
        return np.array([[0.0, rho * cs, -boom * sl * ss],
                         [1.0, -rho * ss, -boom * sl * cs],
                         [0.0, 0.0, boom * cl]])

    def _reinflate(self, mean_innovation_m: np.ndarray) -> None:
        """Re-open the bias uncertainty after a long run of rejected fixes.

        The fixes have disagreed with the estimate by ``mean_innovation_m`` on average
        for ``regate_after_s``: the encoders have probably jumped (slip,
        re-zeroing).  The bias variance grows by the initial bias variance plus the
        square of the joint change that explains the mean innovation (least squares
        through the antenna Jacobian), so the next such fix passes the gate and pulls
        the estimate back.  ``joint + bias`` (what the encoders measure) stays as
        certain as it was; the GNSS-error block is reset to its stationary variance.
        """
        tn = self.tuning
        x = self._ukf.x
        explain = np.zeros(3)
        if np.all(np.isfinite(mean_innovation_m)):
            explain = np.linalg.lstsq(self._antenna_jacobian(x[_JOINTS]),
                                      np.asarray(mean_innovation_m, float), rcond=None)[0]
        bias_var = np.maximum(np.asarray(tn.initial_bias_sd), 1e-9) ** 2 + explain ** 2
        p = self._ukf.P.copy()
        add = np.zeros((N_STATE, N_STATE))
        add[_BIAS, _BIAS] = np.diag(bias_var)
        add[_JOINTS, _JOINTS] = np.diag(bias_var)
        add[_JOINTS, _BIAS] = -np.diag(bias_var)
        add[_BIAS, _JOINTS] = -np.diag(bias_var)
        p[_GNSS, :] = 0.0
        p[:, _GNSS] = 0.0
        p[_GNSS, _GNSS] = np.diag(np.maximum(self._gm_sd, 1e-6) ** 2)
        self._ukf.P = _make_pd(p + add)
        self.counters.regates += 1
        self.counters.consecutive_gated = 0
        self._gated_innovation_sum = np.zeros(3)

    # -- output -----------------------------------------------------------------------

    def estimate(self) -> Estimate:
        """The current belief: joints, their covariance, and the wheel centre.

        The wheel centre is the forward kinematics of the estimated joints (so the pose
        published with them is exactly consistent); its covariance is the unscented
        transform of the joint belief through the forward kinematics.

        Raises
        ------
        LookupError
            Before the first joint reading.
        """
        if self._last_reading is None or self.t_ns is None:
            raise LookupError("no joint reading yet")
        x = self._ukf.x
        pj = _make_pd(self._ukf.P[_JOINTS, _JOINTS])
        pts = self._points3
        centres = wheel_centre_m(self.geometry, pts.sigma_points(x[_JOINTS], pj))
        _mean, cov = unscented_transform(centres, pts.Wm, pts.Wc)
        return Estimate(t_ns=int(self.t_ns), joints=x[_JOINTS].copy(), joint_covariance=pj,
                        bias=x[_BIAS].copy(),
                        wheel_centre_m=wheel_centre_m(self.geometry, x[_JOINTS]),
                        wheel_covariance_m2=_make_pd(np.asarray(cov, float)))


# --------------------------------------------------------------------------------------
# Batch helper (benchmark, tests)
# --------------------------------------------------------------------------------------

@dataclass
class SequenceResult:
    """Output of :func:`filter_sequence`, one row per joint reading.

    Attributes
    ----------
    t_ns : ndarray (N,) int64
    wheel_centre_m : ndarray (N, 3)
    wheel_covariance_m2 : ndarray (N, 3, 3)
    joints : ndarray (N, 3)
    outcomes : dict
        Counts of GNSS outcomes (accepted, gated, skipped).
    update_s : ndarray (M,)
        Wall time of each filter step (predict + update), seconds.
    counters : FilterCounters
    """

    t_ns: np.ndarray
    wheel_centre_m: np.ndarray
    wheel_covariance_m2: np.ndarray
    joints: np.ndarray
    outcomes: dict
    update_s: np.ndarray
    counters: FilterCounters = field(default_factory=FilterCounters)


def filter_sequence(geometry: MachineGeometry, reading_t_ns, readings, fix_t_ns, fix_enu_m,
                    fix_cov_m2, tuning: FilterTuning | None = None) -> SequenceResult:
    """Run :class:`LocalizerFilter` over time-stamped readings and fixes in time order.

    At equal times a joint reading is fused before a fix.  Fixes with a non-finite
    position (no fix) are skipped.  The estimate is taken after each reading's time
    has been fully processed (its reading and any fix at the same time).

    Parameters
    ----------
    geometry : MachineGeometry
    reading_t_ns : array_like (N,) int
        Reading times, non-decreasing.
    readings : array_like (N, 3)
        Encoder readings (travel m, slew rad, luff rad).
    fix_t_ns : array_like (M,) int
        Fix times, non-decreasing.
    fix_enu_m : array_like (M, 3)
        Fixes in the site ENU frame (NaN rows = no fix).
    fix_cov_m2 : array_like (M, 3, 3)
        Fix covariances.
    tuning : FilterTuning, optional

    Returns
    -------
    SequenceResult

    Raises
    ------
    ValueError
        On inconsistent shapes.
    """
    import time as _time

    rt = np.asarray(reading_t_ns, np.int64)
    rd = np.asarray(readings, float)
    ft = np.asarray(fix_t_ns, np.int64)
    fe = np.asarray(fix_enu_m, float)
    fc = np.asarray(fix_cov_m2, float)
    if rt.ndim != 1 or rd.shape != (rt.size, 3):
        raise ValueError(f"reading_t_ns must be (N,) and readings (N, 3); got {rt.shape}, "
                         f"{rd.shape}")
    if ft.ndim != 1 or fe.shape != (ft.size, 3) or fc.shape != (ft.size, 3, 3):
        raise ValueError(f"fix_t_ns must be (M,), fix_enu_m (M, 3), fix_cov_m2 (M, 3, 3); "
                         f"got {ft.shape}, {fe.shape}, {fc.shape}")
    f = LocalizerFilter(geometry, tuning)
    n = rt.size
    out_c = np.full((n, 3), np.nan)
    out_p = np.full((n, 3, 3), np.nan)
    out_j = np.full((n, 3), np.nan)
    outcomes = {"accepted": 0, "gated": 0, "skipped": 0}
    times: list[float] = []
    i = k = 0
    clock = _time.perf_counter
    while i < n:
        # fixes strictly before this reading
        while k < ft.size and ft[k] < rt[i]:
            if np.all(np.isfinite(fe[k])):
                t0 = clock()
                outcomes[f.update_gnss(fe[k], fc[k], t_ns=int(ft[k]))] += 1
                times.append(clock() - t0)
            k += 1
        t0 = clock()
        f.update_joints(rd[i], t_ns=int(rt[i]))
        times.append(clock() - t0)
        while k < ft.size and ft[k] == rt[i]:
            if np.all(np.isfinite(fe[k])):
                t0 = clock()
                outcomes[f.update_gnss(fe[k], fc[k], t_ns=int(ft[k]))] += 1
                times.append(clock() - t0)
            k += 1
        e = f.estimate()
        out_c[i], out_p[i], out_j[i] = e.wheel_centre_m, e.wheel_covariance_m2, e.joints
        i += 1
    return SequenceResult(t_ns=rt.copy(), wheel_centre_m=out_c, wheel_covariance_m2=out_p,
                          joints=out_j, outcomes=outcomes, update_s=np.asarray(times),
                          counters=f.counters)

"""Localisation of a bucket-wheel reclaimer: an unscented Kalman filter over its joints.

Pure numerics, no I/O: the localizer service (:mod:`services.localizer`), the benchmark
(``bench/localizer.py``, through :func:`services.localizer_batch.filter_sequence`) and the
tests drive it.  Thesis §3.1-§3.3 (Zhao 2016) fuses GNSS and joint encoders with a UKF;
docs/domain.md §3 is the kinematic contract (:mod:`projector.kinematics`).  The noise
model is :mod:`services.localizer_tuning`, the covariance repair
:mod:`services.localizer_covariance`.

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
  (the antenna on the boom, docs/domain.md §3) plus the correlated error.  Fixes whose
  squared Mahalanobis distance exceeds the chi-square quantile (3 dof, ``gate_probability``)
  are rejected (counted), so the heavy-tailed yard noise (impulses, Cauchy, ignition,
  UWB bursts, correction outages) does not pull the estimate.  When every fix for
  ``regate_after_s`` has been rejected the filter assumes it is the one that is wrong
  (an encoder slipped or was re-zeroed): it re-opens the bias covariance by the joint
  change that explains the rejected fixes' mean innovation, so the next fixes pull it
  back (counted as ``regates``).
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
from dataclasses import dataclass
from typing import Literal

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from filterpy.kalman import unscented_transform

from schemas.times import NS_PER_S
from projector.kinematics import (MachineGeometry, antenna_jacobian, boom_point_scalar_m,
                                  wheel_centre_m)
from services.localizer_covariance import make_pd, robust_sqrt, symmetrise
from services.localizer_tuning import FilterTuning

__all__ = ["LocalizerFilter", "Estimate", "FilterCounters", "GnssOutcome", "N_STATE",
           "GNSS_ERROR_STATES"]

N_STATE = 9
_JOINTS = slice(0, 3)
_BIAS = slice(3, 6)
_GNSS = slice(6, 9)
#: the state vector's correlated GNSS error (the states the transition decays)
GNSS_ERROR_STATES = _GNSS

GnssOutcome = Literal["accepted", "gated", "skipped"]


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


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
        self._points = _SigmaPoints(N_STATE, alpha=tn.alpha, beta=tn.beta, kappa=tn.kappa,
                                    sqrt_method=self._sqrt)
        self._ukf = _UKF(dim_x=N_STATE, dim_z=3, dt=1.0, hx=self._hx_joints, fx=self._fx,
                         points=self._points, sqrt_fn=self._sqrt)
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
        #: a :class:`services.localizer_smoother.FixedLagSmoother` (or None): told of
        #: every prediction and accepted update, for smoothing the estimates
        self.recorder = None

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
        return boom_point_scalar_m(g, x[0], x[1], x[2], g.antenna_along_boom_m,
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
        self._ukf.P = make_pd(p)

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
        self._ukf.P = make_pd(self._ukf.P)
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
        self._ukf.P = make_pd(self._ukf.P)
        self._check_finite(snapshot)
        self.t_ns = t_ns
        if self.recorder is not None and self._use_gm:
            self.recorder.transition(math.exp(-dt / self.tuning.gnss_markov_tau_s))

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
        if self._last_reading is None:
            if t_ns is None:
                raise ValueError("the first reading needs its time t_ns")
            self._initialise(z, int(t_ns))
            return
        tn = self.tuning
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
        prior = (self._ukf.x.copy(), self._ukf.P.copy())
        self._ukf.update(z_near, R=self._enc_r, hx=self._hx_joints)
        self._ukf.P = make_pd(self._ukf.P)
        self._check_finite(snapshot)
        self._record(*prior)
        self._last_reading = z.copy()
        self.counters.joint_updates += 1

    def _initialise(self, z: np.ndarray, t_ns: int) -> None:
        """Start at the first reading: joints there, biases 0, the initial covariances."""
        tn = self.tuning
        x = np.zeros(N_STATE)
        x[_JOINTS] = z
        var = np.zeros(N_STATE)
        var[_JOINTS] = np.asarray(tn.initial_joint_sd) ** 2 + np.diag(self._enc_r)
        var[_BIAS] = np.maximum(np.asarray(tn.initial_bias_sd), 1e-9) ** 2
        var[_GNSS] = np.maximum(self._gm_sd, 1e-6) ** 2
        self._set_state(x, np.diag(var))
        self.t_ns = t_ns
        self._last_reading = z.copy()
        self.counters.joint_updates += 1
        self._record(self._ukf.x, self._ukf.P)

    def _record(self, x_prior: np.ndarray, p_prior: np.ndarray) -> None:
        """Tell the recorder (if any) of an update: the prior given, the current state."""
        if self.recorder is not None:
            self.recorder.update(self.t_ns, x_prior, p_prior, self._ukf.x, self._ukf.P)

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
        r = symmetrise(r)
        coarse = float(np.linalg.eigvalsh(r[:2, :2])[-1]) > self.tuning.max_fix_sd_m ** 2
        if self._last_reading is None or coarse:
            self.counters.gnss_skipped += 1
            return "skipped"
        if t_ns is not None:
            self.predict_to(t_ns)
        w, v = np.linalg.eigh(r)
        r = symmetrise((v * np.maximum(w, self.tuning.gnss_min_sd_m ** 2)) @ v.T)
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
            self._count_gated()
            return "gated"
        self._ukf.P = make_pd(self._ukf.P)
        self._check_finite((x_prior, p_prior, self.t_ns))
        c.consecutive_gated = 0
        self._gated_innovation_sum = np.zeros(3)
        c.gnss_accepted += 1
        self._record(x_prior, p_prior)
        return "accepted"

    def _count_gated(self) -> None:
        """Count a gated fix (undone); after ``regate_after_s`` of only such fixes, re-open
        the bias uncertainty (:meth:`_reinflate`)."""
        c, tn = self.counters, self.tuning
        c.gnss_gated += 1
        c.consecutive_gated += 1
        if c.consecutive_gated == 1:
            self._gated_since_ns = self.t_ns
        if np.all(np.isfinite(self._ukf.y)):
            self._gated_innovation_sum += self._ukf.y
        if (tn.regate_after_s > 0 and c.consecutive_gated >= tn.regate_min_fixes
                and self.t_ns - self._gated_since_ns >= tn.regate_after_s * NS_PER_S):
            self._reinflate(self._gated_innovation_sum / c.consecutive_gated)

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
            explain = np.linalg.lstsq(antenna_jacobian(self.geometry, x[_JOINTS]),
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
        self._ukf.P = make_pd(p + add)
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
        pj = make_pd(self._ukf.P[_JOINTS, _JOINTS])
        pts = self._points3
        centres = wheel_centre_m(self.geometry, pts.sigma_points(x[_JOINTS], pj))
        _mean, cov = unscented_transform(centres, pts.Wm, pts.Wc)
        return Estimate(t_ns=int(self.t_ns), joints=x[_JOINTS].copy(), joint_covariance=pj,
                        bias=x[_BIAS].copy(),
                        wheel_centre_m=wheel_centre_m(self.geometry, x[_JOINTS]),
                        wheel_covariance_m2=make_pd(np.asarray(cov, float)))

"""The GNSS receiver on the simulated reclaimer's boom, with the errors of thesis §3.2.2.

:class:`GnssModel` turns the antenna's true site-frame position (ENU metres, docs/domain.md
§2; :func:`antenna_position` by the simulator's own forward kinematics) into fixes as a
receiver's GGA sentences carry them (:class:`GnssFix`): the DGPS error of eq. 3.17, loss
of corrections (a two-state Markov process), the autonomous error (Table 3.2), and the
heavy-tailed yard noise: Middleton class-A impulses, Cauchy, ignition and UWB bursts.
Gaussian parts are first-order Gauss-Markov in time; the vertical error is larger than the
horizontal. :class:`GnssConfig` holds the error model. Times are UTC nanoseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pymap3d

from schemas.times import NS_PER_S
from sim.kinematics import Machine, wheel_centre
from sim.rng import check_rng

__all__ = ["GnssConfig", "GnssFix", "GnssModel", "antenna_position", "hdop_from_satellites"]

_R95_FACTOR = math.sqrt(-2.0 * math.log(0.05))  # 95 % radius of a 2-D Gaussian / sigma


@dataclass(frozen=True)
class GnssConfig:
    """Error model of a DGPS receiver on the boom tip (thesis §3.2.2, Table 3.2).

    All sigmas are per horizontal axis (east, north) in metres; the vertical axis gets
    ``vertical_factor`` times the horizontal error of every component.

    Attributes
    ----------
    dgps : bool
        Receiver uses differential corrections when available (False = autonomous only).
    baseline_km : float
        Distance to the reference station (thesis: Karratha, 31 km from Cape Lambert).
    dgps_r95_m_at_0km, dgps_r95_m_per_100km : float
        Eq. 3.17: 95 % horizontal error = 0.41 m + 0.2 m per 100 km of baseline,
        interpreted as the radius containing 95 % of horizontal fixes (R95).
    dgps_tau_s : float
        Correlation time of the first-order Gauss-Markov DGPS residual.
    autonomous_sigma_m, autonomous_tau_s : float
        Gaussian error without corrections (Table 3.2 configuration 1, sigma_Gaussian
        2.5 m) at the nominal satellite count, scaled by HDOP / HDOP(nominal); a
        Gauss-Markov process (ephemeris, ionosphere, troposphere vary slowly).
    outage_mean_interval_s, outage_mean_duration_s : float
        Two-state Markov process of correction loss: mean time with corrections, mean
        outage length.  ``math.inf`` interval = corrections never lost.
    nofix_mean_interval_s, nofix_mean_duration_s : float
        Two-state Markov process of lost fixes (quality 0, position NaN).
    middleton_index_a, middleton_sigma_m, impulse_sigma_m : float
        Middleton class-A-like impulsive noise: per epoch the number of impulses is
        Poisson(A) (A = impulsive index); the error is Gaussian with variance
        ``middleton_sigma_m**2 + m * impulse_sigma_m**2`` (background of Table 3.2
        plus rare big spikes).
    cauchy_scale_m, cauchy_clip_m : float
        White Cauchy noise (scale per Table 3.2, 0.25 m), truncated at +-clip (the
        receiver's outlier rejection; an untruncated Cauchy has no RMSE).
    ignition_sigma_m, ignition_on_mean_s, ignition_off_mean_s : float
        Motor ignition noise (Table 3.2 sigma 0.293 m): white Gaussian while a machine
        runs near the antenna, bursts from a two-state Markov process.
    uwb_sigma_m, uwb_on_mean_s, uwb_off_mean_s : float
        Ultra-wideband interference (Table 3.2 sigma 0.4 m), bursty like ignition.
    satellites_nominal, satellites_min, satellites_max, satellites_change_mean_s
        Satellites tracked: a mean-reverting +-1 jump process.
    """

    dgps: bool = True
    baseline_km: float = 31.0
    dgps_r95_m_at_0km: float = 0.41
    dgps_r95_m_per_100km: float = 0.2
    dgps_tau_s: float = 60.0
    autonomous_sigma_m: float = 2.5
    autonomous_tau_s: float = 300.0
    vertical_factor: float = 1.7
    outage_mean_interval_s: float = 900.0
    outage_mean_duration_s: float = 30.0
    nofix_mean_interval_s: float = 7200.0
    nofix_mean_duration_s: float = 4.0
    middleton_index_a: float = 0.003
    middleton_sigma_m: float = 9.99e-6
    impulse_sigma_m: float = 4.0
    cauchy_scale_m: float = 0.25
    cauchy_clip_m: float = 2.0
    ignition_sigma_m: float = 0.293
    ignition_on_mean_s: float = 60.0
    ignition_off_mean_s: float = 240.0
    uwb_sigma_m: float = 0.4
    uwb_on_mean_s: float = 120.0
    uwb_off_mean_s: float = 360.0
    satellites_nominal: int = 8
    satellites_min: int = 4
    satellites_max: int = 12
    satellites_change_mean_s: float = 120.0

    @property
    def dgps_r95_m(self) -> float:
        """Eq. 3.17: 95 % horizontal error radius with corrections (m)."""
        return self.dgps_r95_m_at_0km + self.dgps_r95_m_per_100km * self.baseline_km / 100.0

    @property
    def dgps_sigma_m(self) -> float:
        """Per-axis horizontal sigma of the DGPS residual: R95 / sqrt(-2 ln 0.05)."""
        return self.dgps_r95_m / _R95_FACTOR

    def without_outages(self) -> GnssConfig:
        """Corrections never lost and fixes never lost."""
        return replace(self, outage_mean_interval_s=math.inf, nofix_mean_interval_s=math.inf)

    def gaussian_only(self) -> GnssConfig:
        """No non-Gaussian components (impulsive, Cauchy, ignition, UWB)."""
        return replace(self, middleton_index_a=0.0, middleton_sigma_m=0.0, cauchy_scale_m=0.0,
                       ignition_sigma_m=0.0, uwb_sigma_m=0.0)


def hdop_from_satellites(satellites) -> np.ndarray:
    """A typical HDOP for a satellite count: ``0.5 + 5 / (n - 2)`` (4 -> 3.0, 8 -> 1.33, 12 -> 1.0).

    Parameters
    ----------
    satellites : array_like of int
        Satellites used (>= 3).
    """
    n = np.asarray(satellites, float)
    return 0.5 + 5.0 / np.maximum(n - 2.0, 1.0)


def antenna_position(machine: Machine, joints, offset_along_boom_m: float = 0.0,
                     offset_up_m: float = 0.0) -> np.ndarray:
    """Site-frame position of a point on the boom (the GNSS antenna) by forward kinematics.

    Parameters
    ----------
    machine : Machine
        Kinematic constants.
    joints : array_like, shape (..., 3)
        (travel m, slew rad, luff rad).
    offset_along_boom_m : float
        Distance of the antenna beyond the wheel centre along the boom (negative = toward
        the pivot); 0 = at the wheel centre.
    offset_up_m : float
        Vertical mast height above that boom point (site +z).

    Returns
    -------
    ndarray, shape (..., 3)
        (x, y, z) in metres.
    """
    joints = np.asarray(joints, float)
    if joints.ndim < 1 or joints.shape[-1] != 3:
        raise ValueError(f"joints must have shape (..., 3), got {joints.shape}")
    m = machine if offset_along_boom_m == 0.0 else replace(
        machine, l5_m=machine.l5_m + offset_along_boom_m)
    p = wheel_centre(m, joints[..., 0], joints[..., 1], joints[..., 2])
    if offset_up_m:
        p[..., 2] += offset_up_m
    return p


@dataclass(frozen=True)
class GnssFix:
    """A batch of GNSS fixes (one row per epoch), as a receiver's GGA sentences carry them.

    Attributes
    ----------
    t_ns : ndarray (N,) int64
        Epoch times, UTC ns.
    enu_m : ndarray (N, 3)
        Measured antenna position in the site ENU frame (NaN when quality is 0).
    quality : ndarray (N,) int8
        GGA fix quality: 0 = no fix, 1 = GPS (autonomous), 2 = DGPS.
    satellites : ndarray (N,) int16
        Satellites used.
    hdop : ndarray (N,)
        Horizontal dilution of precision (99.9 when there is no fix).
    lat_deg, lon_deg, alt_m : ndarray (N,)
        Geodetic WGS84 position of ``enu_m`` (pymap3d.enu2geodetic from the site datum).
    """

    t_ns: np.ndarray
    enu_m: np.ndarray
    quality: np.ndarray
    satellites: np.ndarray
    hdop: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.size)


class GnssModel:
    """A DGPS receiver whose antenna is on the BWR boom, with the errors of thesis §3.2.2.

    Per epoch the error is ``G + I + C + Ig + U`` per axis, the vertical axis scaled by
    ``vertical_factor``:

    - ``G`` Gaussian, first-order Gauss-Markov: the DGPS residual (sigma from eq. 3.17,
      tau ``dgps_tau_s``) while corrections are received (quality 2), the autonomous
      error (Table 3.2, scaled by HDOP; tau ``autonomous_tau_s``) during correction
      outages (quality 1).  Both processes always evolve, so a receiver that loses its
      corrections jumps by the correction's size, as real ones do.
    - ``I`` Middleton class-A-like impulsive noise, ``C`` truncated Cauchy,
      ``Ig`` ignition bursts, ``U`` UWB bursts (all white).

    Occasionally (a two-state Markov process) there is no fix at all: quality 0,
    position NaN, fewer than 4 satellites, HDOP 99.9.

    Parameters
    ----------
    lat0_deg, lon0_deg, alt0_m : float
        Geodetic datum of the site frame's origin (WGS84).
    config : GnssConfig
        Error model; the default is DGPS from a 31 km baseline with outages.
    antenna_offset_along_boom_m, antenna_offset_up_m : float
        Antenna mount relative to the wheel centre (see :func:`antenna_position`).
    rng : numpy.random.Generator
        Keyword-only, required.
    """

    def __init__(self, lat0_deg: float, lon0_deg: float, alt0_m: float, *,
                 config: GnssConfig | None = None, antenna_offset_along_boom_m: float = 0.0,
                 antenna_offset_up_m: float = 0.0, rng: np.random.Generator) -> None:
        self.lat0_deg, self.lon0_deg, self.alt0_m = float(lat0_deg), float(lon0_deg), float(alt0_m)
        self.config = config if config is not None else GnssConfig()
        self.antenna_offset_along_boom_m = float(antenna_offset_along_boom_m)
        self.antenna_offset_up_m = float(antenna_offset_up_m)
        self.rng = check_rng(rng)
        c = self.config
        self._t_ns: int | None = None
        self._dgps_err = np.zeros(3)
        self._auto_err = np.zeros(3)
        self._corrections = bool(c.dgps)
        self._nofix = False
        self._ignition = False
        self._uwb = False
        self._sats = int(c.satellites_nominal)

    def antenna_position(self, machine: Machine, joints) -> np.ndarray:
        """True antenna position (..., 3) for joints (..., 3) = (travel, slew, luff)."""
        return antenna_position(machine, joints, self.antenna_offset_along_boom_m,
                                self.antenna_offset_up_m)

    @staticmethod
    def _switch(p_leave: float, u: float, state: bool) -> bool:
        return (not state) if u < p_leave else state

    def fix(self, t_ns, true_enu_m) -> GnssFix:
        """Simulated fixes of the antenna at its true positions.

        Stateful: error processes continue from the previous call.

        Parameters
        ----------
        t_ns : int or array_like of int, shape () or (N,)
            Epoch times (UTC ns), non-decreasing and not before the previous call.
        true_enu_m : array_like, shape (3,) or (N, 3)
            True antenna position in the site ENU frame (m).

        Returns
        -------
        GnssFix
            Always batch-shaped (N = 1 for a single epoch).
        """
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        truth = np.asarray(true_enu_m, float)
        if truth.ndim == 1:
            truth = truth[None, :]
        if t.ndim != 1 or truth.shape != (t.size, 3):
            raise ValueError(f"t_ns must be (N,) and true_enu_m (N, 3); got {t.shape}, "
                             f"{truth.shape}")
        if np.any(np.diff(t) < 0) or (self._t_ns is not None and t.size and t[0] < self._t_ns):
            raise ValueError("t_ns must be non-decreasing across fixes")
        c, rng = self.config, self.rng
        n = t.size
        u = rng.random((n, 6))                   # Markov switches + satellite moves
        w = rng.standard_normal((n, 2, 3))       # Gauss-Markov innovations
        gauss, quality, sats, ignition, uwb = self._correlated(t, u, w)
        impulsive, cauchy, burst = self._white(n, ignition, uwb)
        axis_scale = np.array([1.0, 1.0, c.vertical_factor])
        err = (gauss + impulsive + cauchy + burst) * axis_scale
        enu = truth + err
        nofix = quality == 0
        enu[nofix] = np.nan
        sats = np.where(nofix, rng.integers(0, 4, n), sats).astype(np.int16)
        hdop = np.round(hdop_from_satellites(sats) + 0.05 * rng.standard_normal(n), 1)
        hdop = np.where(nofix, 99.9, np.maximum(hdop, 0.5))
        lat, lon, alt = pymap3d.enu2geodetic(enu[:, 0], enu[:, 1], enu[:, 2],
                                             self.lat0_deg, self.lon0_deg, self.alt0_m)
        return GnssFix(t_ns=t.copy(), enu_m=enu, quality=quality, satellites=sats, hdop=hdop,
                       lat_deg=np.asarray(lat, float), lon_deg=np.asarray(lon, float),
                       alt_m=np.asarray(alt, float))

    def _correlated(self, t: np.ndarray, u: np.ndarray, w: np.ndarray):
        """Run the error processes over the epochs ``t`` (N,) with the uniforms ``u``
        (N, 6) and innovations ``w`` (N, 2, 3): per epoch the Gaussian error (N, 3) m of
        the state the receiver is in, the fix quality (N,) int8, satellites (N,) int16
        and whether ignition and UWB bursts are on (N,) bool."""
        c = self.config
        n = t.size
        sig_d = c.dgps_sigma_m
        hdop_nom = float(hdop_from_satellites(c.satellites_nominal))
        gauss = np.empty((n, 3))
        quality = np.empty(n, np.int8)
        sats = np.empty(n, np.int16)
        ignition = np.empty(n, bool)
        uwb = np.empty(n, bool)
        for k in range(n):
            tk = int(t[k])
            if self._t_ns is None:               # stationary start
                self._dgps_err = sig_d * w[k, 0]
                self._auto_err = c.autonomous_sigma_m * w[k, 1]
            else:
                self._advance((tk - self._t_ns) / NS_PER_S, u[k], w[k], sig_d)
            self._t_ns = tk
            sats[k] = self._sats
            ignition[k], uwb[k] = self._ignition, self._uwb
            if self._nofix:
                quality[k] = 0
            elif self._corrections:
                quality[k] = 2
            else:
                quality[k] = 1
            if quality[k] == 2:
                gauss[k] = self._dgps_err
            else:
                gauss[k] = self._auto_err * (float(hdop_from_satellites(self._sats)) / hdop_nom)
        return gauss, quality, sats, ignition, uwb

    def _advance(self, dt: float, u: np.ndarray, w: np.ndarray, sig_d: float) -> None:
        """Move every error process on by ``dt`` seconds: the Gauss-Markov errors with the
        innovations ``w`` (2, 3), the Markov switches and satellite moves with the
        uniforms ``u`` (6,)."""
        c = self.config
        # first-order Gauss-Markov, exact for any dt: x <- a x + sigma sqrt(1 - a^2) w
        a = math.exp(-dt / c.dgps_tau_s)
        self._dgps_err = a * self._dgps_err + sig_d * math.sqrt(1.0 - a * a) * w[0]
        a = math.exp(-dt / c.autonomous_tau_s)
        self._auto_err = (a * self._auto_err
                          + c.autonomous_sigma_m * math.sqrt(1.0 - a * a) * w[1])
        if c.dgps:
            mean = (c.outage_mean_interval_s if self._corrections
                    else c.outage_mean_duration_s)
            self._corrections = self._switch(-math.expm1(-dt / mean), u[0], self._corrections)
        mean = c.nofix_mean_duration_s if self._nofix else c.nofix_mean_interval_s
        self._nofix = self._switch(-math.expm1(-dt / mean), u[1], self._nofix)
        mean = c.ignition_on_mean_s if self._ignition else c.ignition_off_mean_s
        self._ignition = self._switch(-math.expm1(-dt / mean), u[2], self._ignition)
        mean = c.uwb_on_mean_s if self._uwb else c.uwb_off_mean_s
        self._uwb = self._switch(-math.expm1(-dt / mean), u[3], self._uwb)
        if u[4] < -math.expm1(-dt / c.satellites_change_mean_s):
            p_up = 0.5 + 0.1 * (c.satellites_nominal - self._sats)
            self._sats += 1 if u[5] < p_up else -1
            self._sats = min(max(self._sats, c.satellites_min), c.satellites_max)

    def _white(self, n: int, ignition: np.ndarray, uwb: np.ndarray):
        """The white, heavy-tailed errors of ``n`` epochs, each (n, 3) m per axis:
        impulsive (Middleton class A), truncated Cauchy, and the ignition and UWB bursts
        where they are on."""
        c, rng = self.config, self.rng
        m = rng.poisson(c.middleton_index_a, n) if c.middleton_index_a > 0 else np.zeros(n)
        impulsive = rng.standard_normal((n, 3)) * np.sqrt(
            c.middleton_sigma_m ** 2 + m * c.impulse_sigma_m ** 2)[:, None]
        if c.cauchy_scale_m > 0:
            half = math.atan(c.cauchy_clip_m / c.cauchy_scale_m)
            cauchy = c.cauchy_scale_m * np.tan(rng.uniform(-half, half, (n, 3)))
        else:
            cauchy = np.zeros((n, 3))
        burst = (rng.standard_normal((n, 3)) * (c.ignition_sigma_m * ignition)[:, None]
                 + rng.standard_normal((n, 3)) * (c.uwb_sigma_m * uwb)[:, None])
        return impulsive, cauchy, burst

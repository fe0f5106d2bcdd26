"""Sensor models of the yard simulator: joint encoders, GNSS and the SICK LMS200.

Every model takes a :class:`numpy.random.Generator` (never the global RNG) and works on
numpy arrays.  Site frame: ENU metres (DOMAIN.md §2): x across the pile, y along the
rail, z up.  Joints: travel ``d1`` (m), slew ``theta2`` (rad, from +y toward +x), luff
``theta3`` (rad, elevation) as in :mod:`sim.kinematics`.  Times are UTC
nanoseconds.

=====================  ==================================================================
model                  what it reproduces
=====================  ==================================================================
:class:`EncoderModel`  thesis §3.2.1 (quantise, add Gaussian noise, quantise again) plus
                       the unbounded drift of §3.1 ("degrade without boundary over time"):
                       travel slip and scale error, slew/luff bias random walks and slop
                       (backlash) in the linkages
:class:`GnssModel`     thesis §3.2.2: DGPS error from eq. 3.17, loss of corrections (a
                       two-state Markov process), autonomous error (Table 3.2), and the
                       heavy-tailed yard noise: Middleton class-A impulses, Cauchy,
                       ignition and UWB bursts; Gaussian parts are first-order
                       Gauss-Markov in time; vertical error larger than horizontal
:class:`ScannerModel`  the LMS200 (thesis §3.4, App. A, DOMAIN.md §5): ray casting on a
                       heightmap, range noise (14.5 mm measured), mixed pixels at depth
                       discontinuities, dropouts, error codes, 10 mm / 1 mm quantisation
=====================  ==================================================================

Scan geometry convention (shared with the georeferencing code, see
:func:`beam_directions_scanner_frame`): the Foxglove ``LaserScan`` / ROS convention that
the ledger stores scans in.  The scan plane is the scanner frame's **x-y plane**; beam
``k`` has bearing ``a_k = -fov/2 + k * step`` (radians, counter-clockwise about the
scanner's +z axis, 0 = +x) and direction ``(cos a_k, sin a_k, 0)`` in the scanner frame.
A pose rotation ``R`` maps scanner-frame vectors to the site frame
(``d_site = R @ d_scanner``); a downward-looking scanner therefore has its +x axis
pointing down: ``R = [[0, 1, 0], [0, 0, -1], [-1, 0, 0]]`` (columns: scanner x -> site -z,
scanner y -> site +x, scanner z -> site -y) looks straight down and sweeps across the pile
(site x-z plane), the first beam (-fov/2) toward -x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pymap3d

from sim.kinematics import Machine, wheel_centre

NS_PER_S = 1_000_000_000

__all__ = [
    "EncoderSpec", "ENCODER_SET_1", "ENCODER_SET_2", "EncoderModel", "quantise_down",
    "GnssConfig", "GnssFix", "GnssModel", "antenna_position", "hdop_from_satellites",
    "raycast_heightmap", "scan_count", "beam_angles_rad", "beam_directions_scanner_frame",
    "rotation_matrix", "ScannerModel",
    "BEAM_OK", "BEAM_NO_HIT", "BEAM_DROPOUT", "BEAM_ERROR_CODE", "BEAM_MIXED",
]


def _check_rng(rng) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise TypeError("rng must be a numpy.random.Generator, e.g. numpy.random.default_rng(seed)")
    return rng


# --------------------------------------------------------------------------------------
# Joint encoders
# --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class EncoderSpec:
    """Resolution, noise and drift of the three joint encoders of a BWR.

    Resolutions and noise follow thesis §3.2.1 / §3.3 (Gaussian noise sd, applied between
    the two quantisations).  The drift terms model "encoders degrade without boundary
    over time" (§3.1): they are random walks and are what makes encoders-alone positions
    tens of centimetres wrong after an hour (thesis Table 3.3: 66 cm set 1, 122 cm set 2).

    Attributes
    ----------
    travel_resolution_m, slew_resolution_deg, luff_resolution_deg : float
        Encoder resolution (one count).
    travel_noise_m, slew_noise_deg, luff_noise_deg : float
        Sd of the Gaussian read noise added between the two quantisations.
    travel_scale_error_sd : float
        Sd of a per-instance scale-factor error of the travel encoder (fraction of the
        signed distance travelled; wheel wear, slip bias).
    travel_slip_m_per_sqrt_m : float
        Random-walk slip: sd of the travel bias increment per sqrt(metre travelled).
    slew_drift_deg_per_sqrt_s, luff_drift_deg_per_sqrt_s : float
        Time-driven bias random walk (sd per sqrt(second)).
    slew_drift_deg_per_sqrt_deg, luff_drift_deg_per_sqrt_deg : float
        Motion-driven bias random walk (sd per sqrt(degree moved)).
    slew_backlash_deg, luff_backlash_deg : float
        Slop in the linkage: full width of a play (hysteresis) operator between the
        joint and the encoder shaft; the reading lags by up to half of it after a
        reversal.
    travel_calibration_spacing_m : float or None
        Travel calibration marks along the rail every this many metres reset the travel
        bias when crossed (thesis §3.1); ``None`` = no marks.
    """

    name: str
    travel_resolution_m: float
    slew_resolution_deg: float
    luff_resolution_deg: float
    travel_noise_m: float
    slew_noise_deg: float
    luff_noise_deg: float
    travel_scale_error_sd: float
    travel_slip_m_per_sqrt_m: float
    slew_drift_deg_per_sqrt_s: float
    slew_drift_deg_per_sqrt_deg: float
    luff_drift_deg_per_sqrt_s: float
    luff_drift_deg_per_sqrt_deg: float
    slew_backlash_deg: float
    luff_backlash_deg: float
    travel_calibration_spacing_m: float | None = None


#: Encoder set 1 of thesis §3.3 (MatrixGroup): 0.5 mm, 0.001 deg, 0.01 deg.  Drift chosen
#: so that encoders-alone wheel-centre RMSE over a 1 h bench reclaim is ~0.6-0.7 m.
ENCODER_SET_1 = EncoderSpec(
    name="set 1", travel_resolution_m=0.0005, slew_resolution_deg=0.001,
    luff_resolution_deg=0.01, travel_noise_m=0.0005, slew_noise_deg=0.001,
    luff_noise_deg=0.01, travel_scale_error_sd=0.002, travel_slip_m_per_sqrt_m=0.01,
    slew_drift_deg_per_sqrt_s=0.0137, slew_drift_deg_per_sqrt_deg=0.0068,
    luff_drift_deg_per_sqrt_s=0.0114, luff_drift_deg_per_sqrt_deg=0.016,
    slew_backlash_deg=0.05, luff_backlash_deg=0.05)

#: Encoder set 2 of thesis §3.3: 1 mm, 0.02 deg, 0.01 deg; a lower-grade installation
#: (about twice the drift of set 1, as the thesis' 122 cm vs 66 cm).
ENCODER_SET_2 = EncoderSpec(
    name="set 2", travel_resolution_m=0.001, slew_resolution_deg=0.02,
    luff_resolution_deg=0.01, travel_noise_m=0.001, slew_noise_deg=0.02,
    luff_noise_deg=0.01, travel_scale_error_sd=0.004, travel_slip_m_per_sqrt_m=0.02,
    slew_drift_deg_per_sqrt_s=0.026, slew_drift_deg_per_sqrt_deg=0.013,
    luff_drift_deg_per_sqrt_s=0.022, luff_drift_deg_per_sqrt_deg=0.030,
    slew_backlash_deg=0.1, luff_backlash_deg=0.08)


def quantise_down(value, resolution: float) -> np.ndarray:
    """Round down to a multiple of ``resolution`` (an encoder's count): ``floor(v/r) * r``.

    Parameters
    ----------
    value : array_like
        Values in any unit.
    resolution : float
        Positive step in the same unit.

    Returns
    -------
    ndarray
        Same shape as ``value``; exact multiples ``k * resolution`` (k integer).
    """
    if not resolution > 0:
        raise ValueError(f"resolution must be > 0, got {resolution}")
    v = np.asarray(value, float)
    # the tiny epsilon keeps exact multiples (0.3 / 0.1 = 2.9999...) on their own count
    return np.floor(v / resolution + 1e-9) * resolution


class EncoderModel:
    """Travel, slew and luff encoders with quantisation, noise and unbounded drift.

    Per reading (thesis §3.2.1 plus drift): the true joint passes through the linkage's
    slop (a play operator), gets the current drift bias added, is quantised down to the
    resolution, gets Gaussian noise, and is quantised down again.  The biases evolve
    between readings: travel by scale error x distance + slip random walk in sqrt(distance);
    slew and luff by random walks in sqrt(time) and sqrt(angle moved).

    Parameters
    ----------
    spec : EncoderSpec
        :data:`ENCODER_SET_1` (default) or :data:`ENCODER_SET_2` or your own.
    rng : numpy.random.Generator
        Source of randomness (keyword-only, required).
    """

    def __init__(self, spec: EncoderSpec = ENCODER_SET_1, *, rng: np.random.Generator) -> None:
        self.spec = spec
        self.rng = _check_rng(rng)
        #: the instance's travel scale-factor error (fraction), drawn once
        self.travel_scale_error = float(rng.normal(0.0, spec.travel_scale_error_sd))
        self._t_ns: int | None = None
        self._travel_m = 0.0
        self._slew_deg = 0.0
        self._luff_deg = 0.0
        self._slew_shaft_deg = 0.0
        self._luff_shaft_deg = 0.0
        self._travel_bias_m = 0.0
        self._slew_bias_deg = 0.0
        self._luff_bias_deg = 0.0

    @property
    def bias(self) -> tuple[float, float, float]:
        """Current drift of (travel m, slew rad, luff rad), excluding slop and quantisation."""
        return (self._travel_bias_m, math.radians(self._slew_bias_deg),
                math.radians(self._luff_bias_deg))

    def read(self, t_ns, travel_m, slew_rad, luff_rad):
        """Encoder readings of the true joints at time ``t_ns``.

        Stateful: the drift evolves from the previous call's time and joints.  A batch
        (1-D arrays, time-ordered) is equivalent to calling once per element.

        Parameters
        ----------
        t_ns : int or array_like of int, shape () or (N,)
            UTC nanoseconds; non-decreasing, and not before the previous call.
        travel_m, slew_rad, luff_rad : float or array_like, shape like ``t_ns``
            True joints (m, rad, rad).

        Returns
        -------
        travel_m, slew_rad, luff_rad : float or ndarray (N,)
            Readings: travel a multiple of ``travel_resolution_m``; slew and luff are
            multiples of their resolution in degrees, returned in radians.

        Raises
        ------
        ValueError
            On mismatched shapes, non-finite joints or time going backwards.
        """
        scalar = np.ndim(t_ns) == 0
        t = np.atleast_1d(np.asarray(t_ns, dtype=np.int64))
        joints = [np.atleast_1d(np.asarray(a, float)) for a in (travel_m, slew_rad, luff_rad)]
        if t.ndim != 1 or any(j.shape != t.shape for j in joints):
            raise ValueError(f"t_ns and the joints must share one shape () or (N,); got "
                             f"{t.shape}, {[j.shape for j in joints]}")
        if not all(np.all(np.isfinite(j)) for j in joints):
            raise ValueError("joints must be finite")
        if np.any(np.diff(t) < 0) or (self._t_ns is not None and t.size and t[0] < self._t_ns):
            raise ValueError("t_ns must be non-decreasing across readings")
        n = t.size
        s = self.spec
        d = joints[0]
        sl = np.degrees(joints[1])
        lu = np.degrees(joints[2])
        z = self.rng.standard_normal((n, 3))
        pre = np.empty((n, 3))
        half_s, half_l = 0.5 * s.slew_backlash_deg, 0.5 * s.luff_backlash_deg
        cal = s.travel_calibration_spacing_m
        for k, (tk, dk, sk, lk) in enumerate(zip(t.tolist(), d.tolist(), sl.tolist(), lu.tolist())):
            if self._t_ns is None:          # first reading: calibrated, shafts at the joints
                self._slew_shaft_deg, self._luff_shaft_deg = sk, lk
            else:
                dt = (tk - self._t_ns) / NS_PER_S
                dd = dk - self._travel_m
                self._travel_bias_m += (self.travel_scale_error * dd
                                        + s.travel_slip_m_per_sqrt_m * math.sqrt(abs(dd)) * z[k, 0])
                if cal and math.floor(dk / cal) != math.floor(self._travel_m / cal):
                    self._travel_bias_m = 0.0
                self._slew_bias_deg += math.sqrt(s.slew_drift_deg_per_sqrt_s ** 2 * dt
                                                 + s.slew_drift_deg_per_sqrt_deg ** 2
                                                 * abs(sk - self._slew_deg)) * z[k, 1]
                self._luff_bias_deg += math.sqrt(s.luff_drift_deg_per_sqrt_s ** 2 * dt
                                                 + s.luff_drift_deg_per_sqrt_deg ** 2
                                                 * abs(lk - self._luff_deg)) * z[k, 2]
                self._slew_shaft_deg = min(max(self._slew_shaft_deg, sk - half_s), sk + half_s)
                self._luff_shaft_deg = min(max(self._luff_shaft_deg, lk - half_l), lk + half_l)
            self._t_ns, self._travel_m, self._slew_deg, self._luff_deg = tk, dk, sk, lk
            pre[k] = (dk + self._travel_bias_m, self._slew_shaft_deg + self._slew_bias_deg,
                      self._luff_shaft_deg + self._luff_bias_deg)
        res = np.array([s.travel_resolution_m, s.slew_resolution_deg, s.luff_resolution_deg])
        noise = np.array([s.travel_noise_m, s.slew_noise_deg, s.luff_noise_deg])
        # thesis §3.2.1: round down, add Gaussian noise, round down again (per column)
        counts = np.floor(pre / res + 1e-9)
        counts = np.floor(counts + self.rng.standard_normal((n, 3)) * (noise / res) + 1e-9)
        travel = counts[:, 0] * s.travel_resolution_m
        slew = np.radians(counts[:, 1] * s.slew_resolution_deg)
        luff = np.radians(counts[:, 2] * s.luff_resolution_deg)
        if scalar:
            return float(travel[0]), float(slew[0]), float(luff[0])
        return travel, slew, luff


# --------------------------------------------------------------------------------------
# GNSS
# --------------------------------------------------------------------------------------

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
        self.rng = _check_rng(rng)
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
        sig_d = c.dgps_sigma_m
        hdop_nom = float(hdop_from_satellites(c.satellites_nominal))
        u = rng.random((n, 6))                   # Markov switches + satellite moves
        w = rng.standard_normal((n, 2, 3))       # Gauss-Markov innovations
        gauss = np.empty((n, 3))
        quality = np.empty(n, np.int8)
        sats = np.empty(n, np.int16)
        ignition = np.empty(n, bool)
        uwb = np.empty(n, bool)
        axis_scale = np.array([1.0, 1.0, c.vertical_factor])
        for k in range(n):
            tk = int(t[k])
            if self._t_ns is None:               # stationary start
                self._dgps_err = sig_d * w[k, 0]
                self._auto_err = c.autonomous_sigma_m * w[k, 1]
            else:
                dt = (tk - self._t_ns) / NS_PER_S
                # first-order Gauss-Markov, exact for any dt: x <- a x + sigma sqrt(1 - a^2) w
                a = math.exp(-dt / c.dgps_tau_s)
                self._dgps_err = a * self._dgps_err + sig_d * math.sqrt(1.0 - a * a) * w[k, 0]
                a = math.exp(-dt / c.autonomous_tau_s)
                self._auto_err = (a * self._auto_err
                                  + c.autonomous_sigma_m * math.sqrt(1.0 - a * a) * w[k, 1])
                if c.dgps:
                    mean = (c.outage_mean_interval_s if self._corrections
                            else c.outage_mean_duration_s)
                    self._corrections = self._switch(-math.expm1(-dt / mean), u[k, 0],
                                                     self._corrections)
                mean = c.nofix_mean_duration_s if self._nofix else c.nofix_mean_interval_s
                self._nofix = self._switch(-math.expm1(-dt / mean), u[k, 1], self._nofix)
                mean = c.ignition_on_mean_s if self._ignition else c.ignition_off_mean_s
                self._ignition = self._switch(-math.expm1(-dt / mean), u[k, 2], self._ignition)
                mean = c.uwb_on_mean_s if self._uwb else c.uwb_off_mean_s
                self._uwb = self._switch(-math.expm1(-dt / mean), u[k, 3], self._uwb)
                if u[k, 4] < -math.expm1(-dt / c.satellites_change_mean_s):
                    p_up = 0.5 + 0.1 * (c.satellites_nominal - self._sats)
                    self._sats += 1 if u[k, 5] < p_up else -1
                    self._sats = min(max(self._sats, c.satellites_min), c.satellites_max)
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
        # white, heavy-tailed components, per axis
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


# --------------------------------------------------------------------------------------
# Ray casting on a heightmap
# --------------------------------------------------------------------------------------

def _bilinear(hflat: np.ndarray, nx: int, ny: int, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Bilinear height at grid coordinates gx, gy (in cells, 0 = first cell centre).

    Indices are clamped, so the outer half cell holds the edge values.  Any NaN among the
    four corners gives NaN.
    """
    i0 = np.clip(np.floor(gx), 0, nx - 2).astype(np.intp)
    j0 = np.clip(np.floor(gy), 0, ny - 2).astype(np.intp)
    fx = np.clip(gx - i0, 0.0, 1.0)
    fy = np.clip(gy - j0, 0.0, 1.0)
    k = j0 * nx + i0
    h00 = hflat[k]
    h01 = hflat[k + 1]
    h10 = hflat[k + nx]
    h11 = hflat[k + nx + 1]
    a = h00 + fx * (h01 - h00)
    b = h10 + fx * (h11 - h10)
    return a + fy * (b - a)


def _block_max_halo(h: np.ndarray, b: int) -> np.ndarray:
    """Maximum over each b x b block of ``h`` plus a one-cell halo around it.

    Returns an (ceil(ny/b), ceil(nx/b)) array; NaN cells are ignored, -inf where a block
    and its halo hold no finite height.
    """
    def pass_rows(a: np.ndarray) -> np.ndarray:   # max over rows b*J - 1 .. b*J + b
        n, m = a.shape
        nb = -(-n // b)
        out = np.full((nb, m), -np.inf)
        for off in range(-1, b + 1):
            j0 = 1 if off < 0 else 0
            sl = a[b * j0 + off::b]
            k = min(sl.shape[0], nb - j0)
            if k > 0:
                np.fmax(out[j0:j0 + k], sl[:k], out=out[j0:j0 + k])
        return out
    return pass_rows(pass_rows(h).T).T


def raycast_heightmap(height_m, origin_x_m: float, origin_y_m: float, cell_m: float,
                      ray_origin_m, ray_dir, max_range_m: float, *,
                      step_frac: float = 0.5, coarse_cells: int = 8) -> np.ndarray:
    """First intersection of rays with a heightmap surface (vectorised over rays).

    The surface is the **bilinear interpolation of cell-centre heights**: ``height_m[j, i]``
    is the height at the centre of cell (i, j), i.e. at ``x = origin_x_m + (i + 0.5) *
    cell_m``, ``y = origin_y_m + (j + 0.5) * cell_m`` (``origin`` = the grid corner, as in
    ``PileDeclared``).  Over the outer half cell the edge values are held (clamped), so the
    surface covers exactly ``[origin_x, origin_x + nx * cell] x [origin_y, origin_y + ny *
    cell]``; the region is solid below the surface (columns), so a ray entering the grid's
    footprint from the side below the edge height hits the side at the border.  A NaN cell
    means "no surface": every point whose four bilinear neighbours include a NaN is empty
    (so a NaN removes the surface within one cell of its centre).

    Method (vectorised over all rays): clip each ray to the grid footprint and to below
    the highest cell; skip segments of ``coarse_cells`` cells that lie above the maximum
    height of the blocks under them (a one-level max pyramid with a one-cell halo, so
    skipping is exact); march the remaining segments in steps of ``step_frac * cell_m``
    (one segment per ray per numpy pass); refine the first crossing step by 6 bisections
    and 2 false-position steps.  The range is exact on the bilinear surface to about
    10 micrometres (f is quadratic along a ray within a cell); at the edge of a NaN region
    (a vertical wall) to 1/64 of a step.  Limitation: a ray grazing a ridge that enters
    and leaves the surface within one step (less than ``step_frac * cell_m`` of travel
    below it) can be missed.  A ray starting below the surface returns 0.

    Parameters
    ----------
    height_m : ndarray, shape (ny, nx), ny, nx >= 2
        Heights (m, site z); NaN = no surface.
    origin_x_m, origin_y_m : float
        Grid corner (m, site frame).
    cell_m : float
        Cell size (m), > 0.
    ray_origin_m : array_like, shape (3,) or (N, 3)
        Ray origins (m, site frame).
    ray_dir : array_like, shape (N, 3)
        Ray directions (normalised here; must be non-zero).
    max_range_m : float
        Maximum range (m), > 0.
    step_frac : float
        Marching step as a fraction of ``cell_m`` (keyword-only).
    coarse_cells : int
        Block size (cells) of the max-height pyramid level used to skip empty space
        (keyword-only; a speed knob, no effect on the result).

    Returns
    -------
    ndarray, shape (N,)
        Range (m) along each ray to the first hit; NaN if nothing is hit within
        ``max_range_m``.
    """
    h = np.ascontiguousarray(height_m, dtype=float)
    if h.ndim != 2 or h.shape[0] < 2 or h.shape[1] < 2:
        raise ValueError(f"height_m must be a 2-D (ny, nx) array with ny, nx >= 2, got {h.shape}")
    if not (cell_m > 0 and math.isfinite(cell_m)):
        raise ValueError(f"cell_m must be > 0, got {cell_m}")
    if not (max_range_m > 0):
        raise ValueError(f"max_range_m must be > 0, got {max_range_m}")
    if not step_frac > 0 or int(coarse_cells) < 2:
        raise ValueError("step_frac must be > 0 and coarse_cells >= 2")
    d = np.asarray(ray_dir, float)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"ray_dir must have shape (N, 3), got {d.shape}")
    n = d.shape[0]
    o = np.asarray(ray_origin_m, float)
    if o.shape == (3,):
        o = np.broadcast_to(o, (n, 3))
    elif o.shape != (n, 3):
        raise ValueError(f"ray_origin_m must have shape (3,) or ({n}, 3), got {o.shape}")
    norm = np.linalg.norm(d, axis=1)
    if np.any(~(norm > 0)) or not np.all(np.isfinite(o)):
        raise ValueError("ray directions must be non-zero and finite, origins finite")
    d = d / norm[:, None]
    ny, nx = h.shape
    out = np.full(n, np.nan)
    if n == 0:
        return out
    hmax = float(np.fmax.reduce(h, axis=None))   # NaN-ignoring; NaN only if all NaN
    hmin = float(np.fmin.reduce(h, axis=None))
    if math.isnan(hmax):
        return out
    if math.isinf(hmax) or math.isinf(hmin):
        raise ValueError("height_m must not contain infinities (use NaN for no surface)")
    all_finite = not np.isnan(h).any()
    hflat = h.ravel()
    x0, y0 = float(origin_x_m), float(origin_y_m)
    x1, y1 = x0 + nx * cell_m, y0 + ny * cell_m
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]

    t_in = np.zeros(n)
    t_out = np.full(n, float(max_range_m))
    with np.errstate(divide="ignore", invalid="ignore"):
        for oc, dc, lo, hi in ((ox, dx, x0, x1), (oy, dy, y0, y1)):
            ta = (lo - oc) / dc
            tb = (hi - oc) / dc
            par = dc == 0
            inside = (oc >= lo) & (oc <= hi)
            ta = np.where(par, np.where(inside, -np.inf, np.inf), ta)
            tb = np.where(par, np.where(inside, np.inf, -np.inf), tb)
            t_in = np.maximum(t_in, np.minimum(ta, tb))
            t_out = np.minimum(t_out, np.maximum(ta, tb))
        # only where the ray is at or below the highest surface can it hit
        tz_top = np.where(dz < 0, (hmax - oz) / dz, np.where(oz <= hmax, -np.inf, np.inf))
        t_in = np.maximum(t_in, tz_top)
        if all_finite:  # below the lowest surface the ray is surely inside
            tz_bot = np.where(dz < 0, (hmin - oz) / dz, np.inf)
            t_out = np.minimum(t_out, tz_bot + 1e-9)
    step = step_frac * cell_m
    inv = 1.0 / cell_m
    gx0 = (ox - x0) * inv - 0.5          # grid coordinates (cells, 0 = first centre)
    gy0 = (oy - y0) * inv - 0.5
    gdx, gdy = dx * inv, dy * inv

    def f(tt, idx):  # ray height minus surface height, (m, k); NaN (no surface) -> +inf
        val = (oz[idx, None] + tt * dz[idx, None]
               - _bilinear(hflat, nx, ny, gx0[idx, None] + tt * gdx[idx, None],
                           gy0[idx, None] + tt * gdy[idx, None]))
        val[np.isnan(val)] = np.inf
        return val

    active = np.flatnonzero(t_in <= t_out)
    if active.size == 0:
        return out
    ts, te = t_in[active], t_out[active]

    # 1. coarse pass: skip segments of length b * cell that lie above every surface that can
    #    influence them (maxima of the blocks under the segment, with a one-cell halo for
    #    the bilinear support)
    b = int(coarse_cells)
    nyc, nxc = -(-ny // b), -(-nx // b)
    mhalo = _block_max_halo(h, b)
    seg = b * cell_m
    nseg = np.maximum(np.ceil((te - ts) / seg).astype(np.int64), 1)
    kk = np.arange(int(nseg.max()) + 1)[None, :]
    tk = np.minimum(ts[:, None] + kk * seg, te[:, None])          # segment ends
    ai = active[:, None]
    bi = np.clip(np.floor((ox[ai] + tk * dx[ai] - x0) / seg), 0, nxc - 1).astype(np.intp)
    bj = np.clip(np.floor((oy[ai] + tk * dy[ai] - y0) / seg), 0, nyc - 1).astype(np.intp)
    zk = oz[ai] + tk * dz[ai]
    # a segment (length <= one block) touches at most the 2 x 2 blocks of its two ends
    ia, ib, ja, jb = bi[:, :-1], bi[:, 1:], bj[:, :-1], bj[:, 1:]
    top = np.maximum(np.maximum(mhalo[ja, ia], mhalo[jb, ib]),
                     np.maximum(mhalo[ja, ib], mhalo[jb, ia]))
    cand = (np.minimum(zk[:, :-1], zk[:, 1:]) <= top) & (kk[:, :-1] < nseg[:, None])
    rows, segs = np.nonzero(cand)        # row-major: each ray's candidate segments in order
    if rows.size == 0:
        return out
    first_of_row = np.r_[True, rows[1:] != rows[:-1]]
    starts = np.flatnonzero(first_of_row)
    rank = np.arange(rows.size) - np.repeat(starts, np.diff(np.r_[starts, rows.size]))

    # 2. fine march inside candidate segments, one segment per ray per round
    sub = np.arange(int(math.ceil(b / step_frac)) + 1) * step   # samples incl. both ends
    done = np.zeros(active.size, bool)
    los, his, hits = [], [], []
    for r in range(int(rank.max()) + 1):
        pick = rank == r
        rr, kr = rows[pick], segs[pick]
        keep = ~done[rr]
        rr, kr = rr[keep], kr[keep]
        if rr.size == 0:
            break
        t_seg = ts[rr] + kr * seg
        tt = np.minimum(t_seg[:, None] + sub[None, :], te[rr, None])
        below = f(tt, active[rr]) <= 0.0
        anyb = below.any(axis=1)
        if anyb.any():
            hr = np.flatnonzero(anyb)
            first = below[hr].argmax(axis=1)
            t_hi = tt[hr, first]
            t_lo = np.where(first > 0, tt[hr, np.maximum(first - 1, 0)], t_hi)
            los.append(t_lo)
            his.append(t_hi)
            hits.append(active[rr[hr]])
            done[rr[hr]] = True
    if not hits:
        return out
    lo_t = np.concatenate(los)
    hi_t = np.concatenate(his)
    hit_idx = np.concatenate(hits)
    # 3. refine: bisection on [lo, hi] (f(lo) > 0 >= f(hi)) to 1/64 of a step, then two
    #    false-position steps (f is quadratic along a ray within a cell)
    for _ in range(6):
        mid = 0.5 * (lo_t + hi_t)
        fb = f(mid[:, None], hit_idx)[:, 0] <= 0.0
        hi_t = np.where(fb, mid, hi_t)
        lo_t = np.where(fb, lo_t, mid)
    f_lo = f(lo_t[:, None], hit_idx)[:, 0]
    f_hi = f(hi_t[:, None], hit_idx)[:, 0]
    t_hit = hi_t
    for _ in range(2):
        denom = f_lo - f_hi
        ok = np.isfinite(f_lo) & (denom > 0)
        frac = np.divide(f_lo, denom, where=ok, out=np.ones_like(f_lo))
        t_hit = np.where(ok, lo_t + (hi_t - lo_t) * np.clip(frac, 0.0, 1.0), hi_t)
        f_new = f(t_hit[:, None], hit_idx)[:, 0]
        below = f_new <= 0.0
        hi_t, f_hi = np.where(below, t_hit, hi_t), np.where(below, f_new, f_hi)
        lo_t, f_lo = np.where(below, lo_t, t_hit), np.where(below, f_lo, f_new)
    out[hit_idx] = np.clip(t_hit, lo_t, hi_t)
    out[out > max_range_m] = np.nan
    return out


# --------------------------------------------------------------------------------------
# SICK LMS200
# --------------------------------------------------------------------------------------

#: (field of view deg, step deg) -> values per scan; the LMS200's modes (App. A, §5)
_SCAN_MODES = {(100.0, 0.25): 401, (100.0, 0.5): 201, (100.0, 1.0): 101,
               (180.0, 0.5): 361, (180.0, 1.0): 181}

#: beam status codes returned by :meth:`ScannerModel.scan_with_status`
BEAM_OK = 0          # a range
BEAM_NO_HIT = 1      # nothing within the maximum range: NaN
BEAM_DROPOUT = 2     # a surface was there but no echo came back: NaN
BEAM_ERROR_CODE = 3  # the scanner sent an error code (top of the 13-bit scale): NaN
BEAM_MIXED = 4       # a range, but a mixed pixel (phantom) between two surfaces (truth only)


def scan_count(fov_deg: float, step_deg: float) -> int:
    """Values per LMS200 scan: 100/0.25 -> 401, 100/0.5 -> 201, 100/1 -> 101, 180/0.5 -> 361,
    180/1 -> 181.

    Raises
    ------
    ValueError
        For any other combination (180 deg at 0.25 deg is not an LMS200 mode).
    """
    try:
        return _SCAN_MODES[(float(fov_deg), float(step_deg))]
    except KeyError:
        raise ValueError(f"not an LMS200 mode: fov {fov_deg} deg, step {step_deg} deg; "
                         "choose one of " + ", ".join(f"{f:g}/{s:g}" for f, s in _SCAN_MODES)) from None


def beam_angles_rad(fov_deg: float, step_deg: float) -> np.ndarray:
    """Beam bearings ``a_k = -fov/2 + k * step`` (rad), k = 0 .. scan_count - 1, shape (n,)."""
    count = scan_count(fov_deg, step_deg)
    return np.radians(-0.5 * fov_deg + step_deg * np.arange(count))


def beam_directions_scanner_frame(fov_deg: float, step_deg: float) -> np.ndarray:
    """Unit beam directions in the scanner frame, shape (n, 3).

    The single definition of the scan geometry (Foxglove ``LaserScan`` / ROS convention):
    the scan plane is the scanner's x-y plane, bearing ``a`` counter-clockwise about +z
    from +x, ``a_k = -fov/2 + k * step`` (first value at -fov/2), direction
    ``(cos a, sin a, 0)``.  A point is ``position + R @ (range * direction)`` in the site
    frame for a pose (position, R).
    """
    a = beam_angles_rad(fov_deg, step_deg)
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
        An LMS200 mode (see :func:`scan_count`).
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
    """

    MM_MODE_MAX_RANGE_M = 8.18

    def __init__(self, *, fov_deg: float = 100.0, step_deg: float = 0.25,
                 range_noise_m: float = 0.0145, range_noise_frac: float = 2.0e-4,
                 max_range_m: float = 80.0, unit_mm: bool = False,
                 mixed_pixel_prob: float = 0.5, mixed_pixel_jump_m: float = 0.3,
                 dropout_prob: float = 0.002, error_code_prob: float = 0.0005,
                 rng: np.random.Generator) -> None:
        self.fov_deg, self.step_deg = float(fov_deg), float(step_deg)
        self.n_beams = scan_count(fov_deg, step_deg)
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
        self.rng = _check_rng(rng)
        self.angles_rad = beam_angles_rad(fov_deg, step_deg)
        self.directions = beam_directions_scanner_frame(fov_deg, step_deg)

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

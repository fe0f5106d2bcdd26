"""The joint encoders of the simulated bucket-wheel reclaimer, with their errors.

:class:`EncoderModel` reads travel ``d1`` (m), slew ``theta2`` (rad, from +y toward +x) and
luff ``theta3`` (rad, elevation), as in :mod:`sim.kinematics`, the way thesis §3.2.1
describes (quantise, add Gaussian noise, quantise again), plus the unbounded drift of §3.1
("degrade without boundary over time"): travel slip and scale error, slew/luff bias random
walks, and slop (backlash) in the linkages. :class:`EncoderSpec` holds one installation's
resolutions, noise and drift; :data:`ENCODER_SET_1` and :data:`ENCODER_SET_2` are the
thesis' two sets (docs/domain.md §5). Times are UTC nanoseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.times import NS_PER_S
from sim.rng import check_rng

__all__ = ["EncoderSpec", "ENCODER_SET_1", "ENCODER_SET_2", "EncoderModel", "quantise_down"]


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


#: Encoder set 1 of thesis §3.3 (MatrixGroup): 0.5 mm, 0.001 deg, 0.01 deg; drift tuned
#: to the thesis' encoders-alone error (see docs/design-notes.md).
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
        self.rng = check_rng(rng)
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

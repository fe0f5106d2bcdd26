"""The localizer's noise model: :class:`FilterTuning` and the covariance of a GNSS fix.

:class:`FilterTuning` holds the process and measurement noise of
:class:`services.localizer_filter.LocalizerFilter` (encoder noise and drift, joint rates,
the time-correlated GNSS error, the Mahalanobis gate, the sigma-point parameters);
:func:`gnss_covariance_m2` is what a GNSS front end can report for a fix that carries no
covariance of its own.  Thesis §3.1-§3.3 (Zhao 2016) gives the figures the defaults suit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

__all__ = ["FilterTuning", "gnss_covariance_m2"]


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

"""The localizer's UKF over a whole recorded sequence: readings and fixes in time order.

:func:`filter_sequence` runs :class:`services.localizer_filter.LocalizerFilter` over
time-stamped encoder readings and GNSS fixes and returns one estimate per reading
(:class:`SequenceResult`), with the wall time of every filter step; the benchmark
(``bench/localizer.py``) and the tests use it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from projector.kinematics import MachineGeometry
from services.localizer_filter import FilterCounters, LocalizerFilter
from services.localizer_tuning import FilterTuning

__all__ = ["SequenceResult", "filter_sequence"]


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
    clock = time.perf_counter
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

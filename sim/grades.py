"""Ore grades on the belt and the laboratory that measures them.

The grade of a lot drifts along the belt flow: per analyte an AR(1) process in time
around the lot's planned grade (thesis §5.2.1: grades vary along the pile because
the feed varies).  The laboratory samples the belt over windows, measures with
lab error and reports hours later (thesis §2.2.1), sometimes first provisionally.

Grades are mass %; times are UTC ns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from schemas.times import NS_PER_H, NS_PER_S

#: Analytes, in the order of every grade vector in the simulator.
ANALYTES: tuple[str, ...] = ("Fe", "SiO2", "Al2O3", "P", "LOI")


@dataclass(frozen=True)
class LotSpec:
    """A lot's planned grade (mean, mass %) and its variability along the belt (sd, mass %)."""

    lot_id: str
    origin: str
    mean_pct: tuple[float, ...]
    sd_pct: tuple[float, ...]
    bulk_density_t_m3: float = 2.4

    def planned_grade(self) -> dict[str, float]:
        return {a: round(m, 3) for a, m in zip(ANALYTES, self.mean_pct)}


def table_5_4_lots(prefix: str = "LOT") -> list[LotSpec]:
    """Four lots with the full-scale magnitudes of thesis Table 5.4.

    Fe, SiO2 ("Si") and Al2O3 ("Al") means and variances are the table's; P and LOI,
    which the table does not give, are typical Pilbara fines values.
    """
    rows = [  # Fe mean, var; Si mean, var; Al mean, var
        (56.23, 6.56, 4.98, 1.53, 0.24, 0.081),
        (60.77, 4.32, 5.33, 1.23, 0.35, 0.063),
        (51.43, 5.18, 7.66, 1.08, 0.41, 0.023),
        (62.05, 7.46, 5.08, 1.34, 0.21, 0.015),
    ]
    lots = []
    for i, (fe, fe_var, si, si_var, al, al_var) in enumerate(rows):
        mean = (fe, si, al, 0.08 + 0.01 * i, 5.5 + 0.4 * i)
        sd = (math.sqrt(fe_var), math.sqrt(si_var), math.sqrt(al_var), 0.01, 0.4)
        lots.append(LotSpec(f"{prefix}-{chr(ord('A') + i)}", f"pit-{i + 1}", mean, sd))
    return lots


class BeltGrade:
    """The grade of one lot's belt flow over time: an AR(1) process per analyte.

    ``g[k+1] = mean + phi (g[k] - mean) + sqrt(1 - phi^2) sd e``, ``phi = exp(-dt/tau)``,
    sampled every ``step_s`` from ``start_ns`` and linearly interpolated between
    samples.  Values stay in [0, 100] and their sum at or below 99.5 %.

    Parameters
    ----------
    lot : LotSpec
    start_ns, end_ns : int
        The span of belt time to cover (UTC ns).
    rng : numpy.random.Generator
    tau_s : float
        Correlation time of the drift (s).
    step_s : float
        Sampling step (s).
    """

    def __init__(self, lot: LotSpec, start_ns: int, end_ns: int, rng: np.random.Generator,
                 tau_s: float = 1200.0, step_s: float = 10.0) -> None:
        if end_ns < start_ns:
            raise ValueError("end_ns must not be before start_ns")
        self.lot = lot
        self.start_ns = int(start_ns)
        self.step_ns = int(step_s * NS_PER_S)
        n = int((end_ns - start_ns) // self.step_ns) + 2
        mean = np.asarray(lot.mean_pct, float)
        sd = np.asarray(lot.sd_pct, float)
        phi = math.exp(-step_s / tau_s)
        noise = rng.standard_normal((n, len(ANALYTES)))
        values = np.empty((n, len(ANALYTES)))
        values[0] = mean + sd * noise[0]
        innovation = math.sqrt(1.0 - phi * phi) * sd
        for k in range(1, n):
            values[k] = mean + phi * (values[k - 1] - mean) + innovation * noise[k]
        values = np.clip(values, 0.0, 100.0)
        total = values.sum(axis=1, keepdims=True)
        values = np.where(total > 99.5, values * (99.5 / total), values)
        self.samples_pct = values

    def at(self, time_ns) -> np.ndarray:
        """Grade vector(s) (mass %) at ``time_ns`` (scalar or array) -> shape (..., 5)."""
        t = (np.asarray(time_ns, dtype=np.float64) - self.start_ns) / self.step_ns
        t = np.clip(t, 0.0, len(self.samples_pct) - 1.000001)
        k = np.floor(t).astype(int)
        w = (t - k)[..., None]
        return self.samples_pct[k] * (1.0 - w) + self.samples_pct[k + 1] * w

    def mean_over(self, start_ns: int, end_ns: int, points: int = 64) -> np.ndarray:
        """Time-mean grade over [start, end] (the belt carries constant tonnes per second)."""
        times = np.linspace(start_ns, end_ns, points)
        return self.at(times).mean(axis=0)


@dataclass(frozen=True)
class LabResult:
    """One assay as the laboratory will report it."""

    assay_id: str
    lot_id: str
    window_start_ns: int
    window_end_ns: int
    analytes_pct: dict[str, float]
    moisture_pct: float
    bulk_density_t_m3: float
    status: str  # "PROVISIONAL" or "FINAL"
    supersedes: str
    lab_id: str
    reported_ns: int
    true_grade_pct: dict[str, float] = field(default_factory=dict)
    #: the lab's stated repeatability of this result, one sd per analyte (mass %)
    repeatability_pct: dict[str, float] = field(default_factory=dict)


@dataclass
class LabModel:
    """Samples a belt over windows and reports late, with lab error.

    Parameters
    ----------
    window_s : float
        Sampling window of belt flow per assay (s), 10-30 minutes by default.
    delay_h : (float, float)
        Reporting delay range after the window closes (hours of site time).
    error_sd_pct : tuple
        Lab error sd per analyte (mass %, absolute).
    provisional_fraction : float
        Share of windows first reported PROVISIONAL, then FINAL (superseding) later.
    """

    window_s: float = 1200.0
    delay_h: tuple[float, float] = (2.0, 6.0)
    error_sd_pct: tuple[float, ...] = (0.15, 0.08, 0.04, 0.003, 0.1)
    provisional_fraction: float = 0.15
    lab_id: str = "lab1"

    def assays(self, belt: BeltGrade, start_ns: int, end_ns: int, rng: np.random.Generator,
               counter: list[int]) -> list[LabResult]:
        """Assays for one lot's belt flow between ``start_ns`` and ``end_ns``.

        ``counter`` is a one-element list used to number assays across lots.
        """
        out: list[LabResult] = []
        window_ns = int(self.window_s * NS_PER_S)
        t = start_ns
        while t < end_ns:
            stop = min(t + window_ns, end_ns)
            true = belt.mean_over(t, stop)
            provisional = rng.random() < self.provisional_fraction
            delay_ns = int(rng.uniform(*self.delay_h) * NS_PER_H)
            counter[0] += 1
            assay_id = f"AS-{counter[0]:05d}"
            truth = {a: float(v) for a, v in zip(ANALYTES, true)}
            first_error = 2.0 if provisional else 1.0  # a provisional result is rougher
            measured = self._measure(true, rng, first_error)
            moisture = float(np.clip(rng.normal(6.0, 0.8), 0.0, 20.0))
            density = float(round(belt.lot.bulk_density_t_m3 * rng.normal(1.0, 0.01), 3))
            out.append(LabResult(assay_id, belt.lot.lot_id, t, stop, measured, moisture, density,
                                 "PROVISIONAL" if provisional else "FINAL", "", self.lab_id,
                                 stop + delay_ns, truth, self.stated(1.0)))
            if provisional:
                counter[0] += 1
                final_delay = delay_ns + int(rng.uniform(1.0, 3.0) * NS_PER_H)
                out.append(LabResult(f"AS-{counter[0]:05d}", belt.lot.lot_id, t, stop,
                                     self._measure(true, rng, 1.0), moisture, density, "FINAL",
                                     assay_id, self.lab_id, stop + final_delay, truth,
                                     self.stated(1.0)))
            t = stop
        return out

    def stated(self, scale: float) -> dict[str, float]:
        """The repeatability the lab states, ``scale`` times its error sd per analyte
        (mass %).  It states its method's (``scale`` 1) with every result, a rougher
        provisional one too, as a laboratory's export gives one figure per method."""
        return {a: float(sd) * scale for a, sd in zip(ANALYTES, self.error_sd_pct)}

    def _measure(self, true: np.ndarray, rng: np.random.Generator, scale: float) -> dict[str, float]:
        sd = np.asarray(self.error_sd_pct) * scale
        values = np.clip(true + sd * rng.standard_normal(len(ANALYTES)), 0.0, 100.0)
        if values.sum() > 99.9:
            values *= 99.9 / values.sum()
        return {a: round(float(v), 3) for a, v in zip(ANALYTES, values)}

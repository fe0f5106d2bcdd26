"""Grades joined to material at query time, from the assays known at a time K.

A lot is sampled on the belt over windows; the lab reports each window's assay hours later
(docs/domain.md §1, §2).  Material deposited at time t from lot L takes the grade of the assay of
L whose sampling window contains t, *as known at K* (recorded at or before K); without one
it takes the lot's planned grade and is marked not assayed.  So the same pile has different
grades as of different K, and the answer changes exactly when an assay is recorded.

Which assays count at K (:func:`effective_assays`)
--------------------------------------------------
1. Only assays recorded at or before K.  If one ``assay_id`` was recorded more than once,
   the copy recorded last counts.
2. An assay named in the ``supersedes`` field of another assay recorded at or before K is
   dropped (whatever the statuses; chains drop every replaced link; an assay naming itself
   is ignored).
3. A PROVISIONAL assay is dropped when a FINAL assay of the same lot that survived rule 2
   covers an overlapping window: the two windows share an interval of positive length,
   ``max(starts) < min(ends)``, or one of them is a single instant inside the other
   (``max(starts) <= min(ends)``).  Windows that merely touch at an end (consecutive lab
   windows share their boundary) do not overlap.

Which assay a time takes (:func:`grade_at`)
-------------------------------------------
Among the effective assays of the lot whose window contains t (``start <= t <= end``):
FINAL before PROVISIONAL, then the one recorded last, then the larger ``assay_id``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable, Mapping, Sequence

import numpy as np

from schemas.analytes import canonical_grades
from schemas.times import NS_PER_S

__all__ = ["AssayRecord", "GradeClasses", "effective_assays", "grade_at", "grade_classes",
           "coerce_time_ns", "grade_from_map", "STATUSES"]


def grade_from_map(grades: Mapping[str, float]) -> dict[str, float]:
    """A grade (analyte -> %) from a protobuf map field, in analyte-name order.

    A protobuf map iterates in an order that differs from one process to the next; every
    grade the projector builds from a message goes through here, so that sums over
    analytes, and the reports, come out the same in every process.  Names are canonical
    (:func:`schemas.analytes.canonical_grades`): ``FE`` counts as ``Fe``.
    """
    return canonical_grades(grades)

#: Assay statuses, in increasing precedence.
STATUSES: tuple[str, ...] = ("PROVISIONAL", "FINAL")

# protobuf enum values of stockpile.v1.AssayStatus (events.proto)
_STATUS_BY_NUMBER = {1: "PROVISIONAL", 2: "FINAL"}


def coerce_time_ns(value) -> int:
    """UTC ns of a protobuf ``Timestamp`` (``seconds``, ``nanos``) or of an integer."""
    if isinstance(value, bool):
        raise TypeError("a time must be a Timestamp or integer ns, got a bool")
    if isinstance(value, (int, np.integer)):
        return int(value)
    if hasattr(value, "seconds") and hasattr(value, "nanos"):
        return int(value.seconds) * NS_PER_S + int(value.nanos)
    raise TypeError(f"a time must be a Timestamp or integer ns, got {type(value).__name__}")


@dataclass(frozen=True)
class AssayRecord:
    """One lab result as the ledger recorded it.

    Attributes
    ----------
    assay_id, lot_id : str
    window_start_ns, window_end_ns : int
        The sampling window of belt flow (UTC ns), start <= end.
    analytes : dict
        Analyte -> mass %.
    bulk_density_t_m3 : float
        t/m3; 0 = unknown.
    status : str
        ``"PROVISIONAL"`` or ``"FINAL"``.
    supersedes : str
        The ``assay_id`` this one replaces; ``""`` none.
    recorded_ns : int
        When the ledger learned it (UTC ns): the K it becomes known at.
    repeatability_pp : dict
        Analyte -> the lab's stated repeatability, one sd (pp, finite, > 0); an analyte
        absent takes the configured one.
    """

    assay_id: str
    lot_id: str
    window_start_ns: int
    window_end_ns: int
    analytes: Mapping[str, float] = field(hash=False)
    bulk_density_t_m3: float
    status: str
    supersedes: str
    recorded_ns: int
    repeatability_pp: Mapping[str, float] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        for name in ("window_start_ns", "window_end_ns", "recorded_ns"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise TypeError(f"{name} must be an integer (UTC ns), got {value!r}")
        if self.window_end_ns < self.window_start_ns:
            raise ValueError(f"assay {self.assay_id!r}: window ends before it starts")
        if self.status not in STATUSES:
            raise ValueError(f"assay {self.assay_id!r}: status must be one of {STATUSES}, "
                             f"got {self.status!r}")
        density = float(self.bulk_density_t_m3)
        if not (math.isfinite(density) and density >= 0):
            raise ValueError(f"assay {self.assay_id!r}: bulk density must be >= 0 (0 = "
                             f"unknown), got {self.bulk_density_t_m3!r}")
        object.__setattr__(self, "analytes", canonical_grades(
            {str(k): float(v) for k, v in self.analytes.items()}))
        stated = canonical_grades({str(k): float(v) for k, v in self.repeatability_pp.items()})
        if not all(math.isfinite(v) and v > 0 for v in stated.values()):
            raise ValueError(f"assay {self.assay_id!r}: a stated repeatability must be finite "
                             f"and > 0 pp, got {dict(self.repeatability_pp)!r}")
        object.__setattr__(self, "repeatability_pp", stated)

    @classmethod
    def from_message(cls, msg, recorded_ns: int) -> "AssayRecord":
        """The record of an ``Assay`` message recorded at ``recorded_ns``.

        ``window_start`` / ``window_end`` may be protobuf Timestamps or integer ns; ``status``
        the enum number (1 = PROVISIONAL, 2 = FINAL) or its name.
        """
        status = msg.status
        if isinstance(status, str):
            status = status.upper()
        else:
            number = int(status)
            if number not in _STATUS_BY_NUMBER:
                raise ValueError(f"assay {msg.assay_id!r}: unknown status {status!r}")
            status = _STATUS_BY_NUMBER[number]
        return cls(assay_id=str(msg.assay_id), lot_id=str(msg.lot_id),
                   window_start_ns=coerce_time_ns(msg.window_start),
                   window_end_ns=coerce_time_ns(msg.window_end),
                   analytes=grade_from_map(msg.analytes),
                   bulk_density_t_m3=float(getattr(msg, "bulk_density_t_m3", 0.0) or 0.0),
                   status=status, supersedes=str(getattr(msg, "supersedes", "") or ""),
                   recorded_ns=int(recorded_ns),
                   repeatability_pp=dict(getattr(msg, "repeatability_pp", None) or {}))

    @property
    def is_final(self) -> bool:
        return self.status == "FINAL"


def _windows_overlap(a: AssayRecord, b: AssayRecord) -> bool:
    lo = max(a.window_start_ns, b.window_start_ns)
    hi = min(a.window_end_ns, b.window_end_ns)
    if a.window_start_ns == a.window_end_ns or b.window_start_ns == b.window_end_ns:
        return lo <= hi
    return lo < hi


def effective_assays(assays: Iterable[AssayRecord], known_ns: int) -> list[AssayRecord]:
    """The assays that count as known at ``known_ns`` (rules in the module docstring).

    Parameters
    ----------
    assays : iterable of AssayRecord
    known_ns : int
        K (UTC ns).

    Returns
    -------
    list of AssayRecord
        Ordered by (recorded_ns, assay_id).
    """
    if isinstance(known_ns, bool) or not isinstance(known_ns, (int, np.integer)):
        raise TypeError(f"known_ns must be an integer (UTC ns), got {known_ns!r}")
    latest: dict[str, AssayRecord] = {}
    for a in assays:
        if a.recorded_ns <= known_ns:
            old = latest.get(a.assay_id)
            if old is None or a.recorded_ns >= old.recorded_ns:
                latest[a.assay_id] = a
    known = list(latest.values())
    replaced = {a.supersedes for a in known if a.supersedes and a.supersedes != a.assay_id}
    alive = [a for a in known if a.assay_id not in replaced]
    finals: dict[str, list[AssayRecord]] = {}
    for a in alive:
        if a.is_final:
            finals.setdefault(a.lot_id, []).append(a)
    out = [a for a in alive
           if a.is_final or not any(_windows_overlap(a, f) for f in finals.get(a.lot_id, ()))]
    out.sort(key=lambda a: (a.recorded_ns, a.assay_id))
    return out


@dataclass(frozen=True, eq=False)
class GradeClasses:
    """Material of one lot sorted into the few grades it can take (:func:`grade_classes`).

    Attributes
    ----------
    index : ndarray, shape (N,), int64
        Class of each time: 0 = the planned grade, 1 = unknown time (NaN grade),
        ``2 + i`` = the i-th applying assay.
    grade : ndarray, shape (C, A)
        Mass % of each class.
    assayed : ndarray of bool, shape (C,)
        Whether the class is an assay's.
    density_t_m3 : ndarray, shape (C,)
        The class's bulk density (NaN: the planned grade, an unknown time, or an assay
        that reported none).
    lab_sd_pp : ndarray, shape (C, A)
        The assay's stated repeatability (pp; NaN: not an assay's class, or not stated).
    window_ns : ndarray, shape (C, 2), int64, or None
        The assay's sampling window (start, end; UTC ns; 0, 0: not an assay's class).
    """

    index: np.ndarray
    grade: np.ndarray
    assayed: np.ndarray
    density_t_m3: np.ndarray
    lab_sd_pp: np.ndarray
    window_ns: np.ndarray | None = None


def grade_classes(lot_id: str, planned_grade: Mapping[str, float],
                  assays_effective: Sequence[AssayRecord], times_ns,
                  analytes: tuple[str, ...]) -> GradeClasses:
    """Which grade each deposition time of lot ``lot_id`` takes, as known at K.

    The same rule as :func:`grade_at` with the grades kept once per class: a lot has a
    few assays and its material many cells, so sums over cells are sums over classes
    (``np.bincount(classes.index, weights)``) and never form an (N, A) array.

    Parameters and errors as :func:`grade_at`.
    """
    times = np.asarray(times_ns)
    if times.ndim != 1:
        raise ValueError(f"times_ns must have shape (N,), got {times.shape}")
    analytes = tuple(analytes)
    n, n_a = times.shape[0], len(analytes)
    planned = np.array([float(planned_grade.get(a, math.nan)) for a in analytes])
    index = np.zeros(n, dtype=np.int64)
    if times.dtype.kind in "iu":
        t = times.astype(np.int64)
        bound = int
    else:
        t = times.astype(np.float64)
        index[np.isnan(t)] = 1
        bound = float
    rows = [planned, np.full(n_a, math.nan)]
    assayed = [False, False]
    density = [math.nan, math.nan]
    stated = [np.full(n_a, math.nan), np.full(n_a, math.nan)]
    windows = [(0, 0), (0, 0)]
    mine = [a for a in assays_effective if a.lot_id == lot_id]
    # lowest precedence first: later ones overwrite
    mine.sort(key=lambda a: (a.is_final, a.recorded_ns, a.assay_id))
    for a in mine:
        with np.errstate(invalid="ignore"):
            hit = (t >= bound(a.window_start_ns)) & (t <= bound(a.window_end_ns))  # NaN: no
        if not hit.any():
            continue
        index[hit] = len(rows)
        rows.append(np.array([a.analytes.get(name, planned[j])
                              for j, name in enumerate(analytes)], dtype=np.float64))
        assayed.append(True)
        density.append(a.bulk_density_t_m3 if a.bulk_density_t_m3 > 0 else math.nan)
        stated.append(np.array([a.repeatability_pp.get(name, math.nan) for name in analytes],
                               dtype=np.float64))
        windows.append((a.window_start_ns, a.window_end_ns))
    return GradeClasses(index, np.stack(rows).reshape(len(rows), n_a), np.array(assayed),
                        np.array(density, dtype=np.float64),
                        np.stack(stated).reshape(len(stated), n_a),
                        np.array(windows, dtype=np.int64))


def grade_at(lot_id: str, planned_grade: Mapping[str, float],
             assays_effective: Sequence[AssayRecord], times_ns,
             analytes: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The grade of lot ``lot_id``'s material deposited at given times, as known at K.

    Parameters
    ----------
    lot_id : str
    planned_grade : mapping
        Analyte -> mass % (the lot's declared plan); analytes it lacks are NaN.
    assays_effective : sequence of AssayRecord
        :func:`effective_assays` at K (assays of other lots are ignored).
    times_ns : array_like, shape (N,)
        Deposition times (UTC ns); integer (exact) or float (NaN = unknown: NaN grade).
    analytes : tuple of str
        The analytes to return, in this order (A of them).

    Returns
    -------
    grade : ndarray, shape (N, A)
        Mass %.  From the assay whose window contains the time (module docstring); an
        analyte that assay does not report falls back to the planned value.  Otherwise the
        planned grade.
    assayed : ndarray of bool, shape (N,)
        Whether an assay applied.
    density_t_m3 : ndarray, shape (N,)
        The assay's bulk density; NaN where no assay applied or it reported none (0).

    Raises
    ------
    ValueError
        If ``times_ns`` is not one-dimensional.
    """
    c = grade_classes(lot_id, planned_grade, assays_effective, times_ns, analytes)
    return c.grade[c.index], c.assayed[c.index], c.density_t_m3[c.index]

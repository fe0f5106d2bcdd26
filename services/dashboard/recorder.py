"""Logging at the data's time: :class:`Recorder` wraps the Rerun recording stream and sets
its two timelines from the tracker, never from the wall clock: ``valid_time`` (timestamp,
V) and ``ledger_seq`` (sequence, K), and puts every path under the pile's prefix
(:func:`entity_prefix`).  Also :func:`rr` (the deferred ``rerun`` import) and :func:`iso`
(a time for people, to the second).
"""

from __future__ import annotations

import math

import numpy as np

from schemas.times import NS_PER_S, format_time_ns


def rr():
    """The ``rerun`` module."""
    import rerun   # deferred: rerun is heavy (the CLI's --help must not load it)

    return rerun


#: the root of the piles' entities when a recording shows several piles
PILES_ROOT = "/piles"


def entity_prefix(pile_id: str, piles) -> str:
    """The prefix of a pile's entity paths: ``""`` when ``piles`` (the piles of the
    recording) are this one pile or fewer, else ``/piles/<id>`` (the id escaped as one
    entity-path part)."""
    if len(tuple(piles)) <= 1:
        return ""
    return f"{PILES_ROOT}/{rr().escape_entity_path_part(str(pile_id))}"


def iso(ns: int) -> str:
    """UTC ns as ISO-8601, truncated to the second."""
    return format_time_ns(int(ns) // NS_PER_S * NS_PER_S)


class Recorder:
    """A RecordingStream ``rec`` and the clock of a :class:`~services.dashboard.tracker.PileTracker`.

    Attributes
    ----------
    rec : rerun.RecordingStream
    tracker : PileTracker
        Its ``valid_ns`` and ``seq`` are the default time of what is logged.
    update_v : int or None
        V of the update being logged (the default valid time while it is set), ns.
    prefix : str
        Put before every entity path logged (:func:`entity_prefix`; ``""``: none).
    """

    def __init__(self, rec, tracker, prefix: str = "") -> None:
        self.rec, self.tracker, self.prefix = rec, tracker, prefix
        self.update_v: int | None = None

    def path(self, path: str) -> str:
        """The entity path logged for ``path`` (under :attr:`prefix`)."""
        return self.prefix + path

    def at(self, valid_ns: int | None = None, seq: int | None = None) -> None:
        """Set the time of what is logged next (default: the update's V, or the newest
        valid time read; the seq read)."""
        if valid_ns is None:
            valid_ns = self.update_v if self.update_v is not None else self.tracker.valid_ns
        self.rec.set_time("valid_time", timestamp=np.datetime64(int(valid_ns), "ns"))
        self.rec.set_time("ledger_seq", sequence=int(self.tracker.seq if seq is None else seq))

    def log(self, path: str, entity, **kwargs) -> None:
        """``rec.log`` (at the time last set) under the prefix."""
        self.rec.log(self.prefix + path, entity, **kwargs)

    def series(self, path: str, value: float) -> None:
        """A scalar at the time last set (nothing for None or a non-finite value)."""
        if value is not None and math.isfinite(value):
            self.rec.log(self.prefix + path, rr().Scalars(float(value)))

    def band(self, path: str, value: float, sd: float | None) -> None:
        """A figure's one-sd band at the time last set: ``<path>_hi`` and ``<path>_lo``
        (``value`` +/- ``sd``; nothing for a non-finite value or sd)."""
        if value is not None and sd is not None and math.isfinite(value) and math.isfinite(sd):
            self.series(f"{path}_hi", value + sd)
            self.series(f"{path}_lo", value - sd)

    def text(self, text: str, level: str = "INFO", *, valid_ns: int | None = None,
             seq: int | None = None) -> None:
        """A line of ``/log`` at :meth:`at` ``(valid_ns, seq)``."""
        rerun = rr()
        self.at(valid_ns, seq)
        self.rec.log(self.prefix + "/log",
                     rerun.TextLog(text, level=getattr(rerun.TextLogLevel, level)))

"""Several piles on one dashboard: :class:`PileSet` holds one
:class:`~services.dashboard.core.Dashboard` per pile of ``config.piles`` on one Rerun
recording and feeds each the records read once (live or offline).

Each pile keeps its own fold, tracker, history and update cadence; only the reading, the
recording and the blueprint are shared.  With one pile nothing changes: its entities keep
their paths and it sends its own blueprint.  With several, each pile's entities are under
``/piles/<id>`` (:func:`~services.dashboard.recorder.entity_prefix`) and the blueprint
(:func:`~services.dashboard.style.piles_blueprint`, a tab per pile) is sent by the set.
"""

from __future__ import annotations

from typing import Callable, Iterable, Iterator

from services.dashboard.config import Config
from services.dashboard.core import Dashboard, feed
from services.dashboard.style import blueprint, piles_blueprint


class PileSet:
    """The dashboards of ``config.piles`` (in that order) on the recording ``rec``.

    Parameters
    ----------
    rec : rerun.RecordingStream
    config : Config
        ``piles``: at least one.
    offline : bool
        As :class:`Dashboard`'s.
    """

    def __init__(self, rec, config: Config, *, offline: bool = False) -> None:
        if not config.piles:
            raise ValueError("--pile is required")
        self.rec, self.config = rec, config
        layout = self if len(config.piles) > 1 else None
        self.dashes = [Dashboard(rec, pile_id, config, offline=offline, layout=layout)
                       for pile_id in config.piles]

    def __iter__(self) -> Iterator[Dashboard]:
        return iter(self.dashes)

    def __len__(self) -> int:
        return len(self.dashes)

    @property
    def first(self) -> Dashboard:
        """The dashboard of the first pile."""
        return self.dashes[0]

    @property
    def seq(self) -> int:
        """The newest global seq every pile has read (-1 before any)."""
        return min(d.seq for d in self.dashes)

    @property
    def known_ns(self) -> int:
        """The newest recorded time every pile has read, ns."""
        return min(d.known_ns for d in self.dashes)

    @property
    def updates(self) -> int:
        """Updates logged, all piles."""
        return sum(d.updates for d in self.dashes)

    def feed(self, records: Iterable, *, updates: bool = True,
             rebuild: Callable[[Dashboard], None] | None = None, on_record=None) -> int:
        """Feed the records (global order) to each pile's dashboard that has not read them
        (:func:`~services.dashboard.core.feed`, updating when due; ``rebuild(dash)`` refolds
        a stale one; ``on_record(n)`` follows the last pile); returns the records given."""
        records = list(records)
        last = self.dashes[-1]
        for dash in self.dashes:
            todo = [r for r in records if r.global_seq > dash.seq]
            feed(dash, todo, updates=updates,
                 rebuild=None if rebuild is None else (lambda d=dash: rebuild(d)),
                 on_record=on_record if dash is last else None)
        return len(records)

    def log_text(self, text: str, level: str = "INFO", **kwargs) -> None:
        """A line about the whole ledger (a gap, quarantined input) in every pile's log."""
        for dash in self.dashes:
            dash.log_text(text, level, **kwargs)

    def flush_known_now(self) -> None:
        """Each pile's :meth:`Dashboard.flush_known_now`."""
        for dash in self.dashes:
            dash.flush_known_now()

    def blueprint(self):
        """The blueprint of every pile as known now (its analytes and footprint)."""
        if len(self.dashes) == 1:
            d = self.first
            return blueprint(d.blueprint_analytes, self.config.analyte,
                             layers=self.config.layers, pile=d.pile_box())
        return piles_blueprint([(d.pile_id, d.out.prefix, d.blueprint_analytes, d.pile_box())
                                for d in self.dashes], self.config.analyte,
                               layers=self.config.layers)

    def send_blueprint(self, *, make_active: bool) -> None:
        """Send :meth:`blueprint` (the dashboards call it when a pile is first drawn or its
        analytes grow)."""
        self.rec.send_blueprint(self.blueprint(), make_active=make_active, make_default=True)

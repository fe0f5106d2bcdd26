"""The dashboard: ledger records in, Rerun out.

:class:`Dashboard` takes committed records in global order (:meth:`Dashboard.add`) and,
when an update is due, logs the pile as of V as known at K (:meth:`Dashboard.update`).
It ties together the collaborators that hold each concern: the
:class:`~services.dashboard.tracker.PileTracker` (what the records said), the
:class:`~services.dashboard.history.History` (the pile over time), the
:class:`~services.dashboard.cuts.CutLog` (reclaim cuts) and the
:class:`~services.dashboard.scene.PileScene` (the 3D pile), the
:class:`~services.dashboard.surveys.SurveyMaps` (survey minus model), all logging through one
:class:`~services.dashboard.recorder.Recorder`.  :func:`feed` and :func:`rebuild_from`
drive a dashboard from a source of records, live or offline.
"""

from __future__ import annotations

import math
import time
from typing import Callable, Iterable

from schemas.events import decode_payload
from schemas.times import NS_PER_S
from services.dashboard.config import Config
from services.dashboard.cuts import CutLog
from services.dashboard.history import History, HistoryPoint
from services.dashboard.recorder import Recorder, entity_prefix, rr
from services.dashboard.scene import PileScene, log_machines, log_scan, log_status
from services.dashboard.style import blueprint, log_series_styles
from services.dashboard.surveys import SurveyMaps
from services.dashboard.tracker import GEOMETRY_TYPES, PileTracker
from services.projector_service import catch_up

#: while feeding, the projection advances at every this many records of a geometry type
ADVANCE_EVERY = 64


class Dashboard:
    """Takes ledger records in global order and logs the pile to a Rerun recording.

    Parameters
    ----------
    rec : rerun.RecordingStream
    pile_id : str
    config : Config
    offline : bool
        The blueprint (with the camera on the pile) goes with the sinks, once; live it is
        re-sent when the pile is first known or analytes are added.
    layout : object or None
        Several piles on one recording: what sends the blueprint of them all (its
        ``send_blueprint(make_active=...)``, :class:`services.dashboard.piles.PileSet`);
        None: this pile's own.

    Its entities are under :func:`~services.dashboard.recorder.entity_prefix` of the pile
    among ``config.piles`` (none when it is the only one).
    """

    def __init__(self, rec, pile_id: str, config: Config, *, offline: bool = False,
                 layout=None) -> None:
        self.rec, self.pile_id, self.config = rec, pile_id, config
        self.layout = layout
        self.tracker = PileTracker(pile_id, int(config.reorder_s * NS_PER_S))
        self.out = Recorder(rec, self.tracker, entity_prefix(pile_id, config.piles))
        self.history = History(self.out, self.tracker, int(config.every_s * NS_PER_S))
        self.cuts = CutLog(self.out, self.tracker, config)
        self.scene = PileScene(self.out, self.tracker, config)
        self.surveys = SurveyMaps(self.out, pile_id)
        self.updates = 0
        self.rebuilds = 0
        self.last_update_valid_ns: int | None = None
        self.last_update_seq = -1
        #: the summary of the last update
        self.last_state = None
        #: live: "as known now" logged with each update and re-logged when revised; before
        #: (catch-up, offline) it waits for :meth:`flush_known_now`
        self.live = False
        self.offline = offline
        self._camera_set = offline
        self._blueprint_analytes: tuple[str, ...] = ()
        self._last_3d_wall = -math.inf
        self._joined_version = 0
        self.out.log("/site", rr().ViewCoordinates.RIGHT_HAND_Z_UP, static=True)

    # -- what has been read ----------------------------------------------------------------

    @property
    def projection(self):
        """The live projection (:class:`services.projector_service.LiveProjection`)."""
        return self.tracker.projection

    @property
    def seq(self) -> int:
        """The newest global seq read (K), -1 before any."""
        return self.tracker.seq

    @property
    def known_ns(self) -> int:
        """The newest recorded time read, ns."""
        return self.tracker.known_ns

    @property
    def valid_ns(self) -> int:
        """The newest valid time read, or K if later (an update's V is at least this)."""
        return self.tracker.valid_ns

    @property
    def reasons(self) -> set[str]:
        """Why the next update is due now."""
        return self.tracker.reasons

    @property
    def points(self) -> list[HistoryPoint]:
        """The kept history points."""
        return self.history.points

    def log_text(self, text: str, level: str = "INFO", *, valid_ns: int | None = None,
                 seq: int | None = None) -> None:
        """A line of ``/log`` (default time: the update's V or the newest read; the seq read)."""
        self.out.text(text, level, valid_ns=valid_ns, seq=seq)

    def add(self, record) -> None:
        """Take one committed record (global order)."""
        for text, level in self.tracker.add(record):
            self.out.text(text, level, seq=record.global_seq)
        if record.type == "survey" and self.surveys.add(record):
            self.tracker.reasons.add("survey")

    # -- updates ---------------------------------------------------------------------------

    def due(self, *, boundary: bool) -> bool:
        """Whether an update is due (at a recorded-time boundary during catch-up/offline)."""
        if not boundary or self.seq < 0 or self.seq == self.last_update_seq:
            return False
        if self.reasons:
            return True
        return (self.last_update_valid_ns is None
                or self.valid_ns - self.last_update_valid_ns
                >= int(self.config.every_s * NS_PER_S))

    def next_valid_ns(self) -> int:
        """V of the next update: :attr:`valid_ns`, or 1 ns after the last update's V when
        the ledger grew without the valid time advancing (still the same as-of set:
        every record read has valid time <= V)."""
        v = self.valid_ns
        if self.last_update_valid_ns is not None:
            v = max(v, self.last_update_valid_ns + 1)
        return v

    def update(self) -> bool:
        """Log the pile as of V as known at K; returns False if there was nothing to log."""
        tracker = self.tracker
        if tracker.seq < 0 or tracker.seq == self.last_update_seq:
            return False
        tracker.projection.advance()
        state = tracker.projection.summary()
        if state.geometry is None:
            # nothing to draw (the pile not declared yet): not due again before a reason
            # (its declaration is one) or ``every_s`` of valid time, as after an update
            tracker.reasons.clear()
            self.last_update_seq = tracker.seq
            self.last_update_valid_ns = self.next_valid_ns()
            return False
        v = self.next_valid_ns()
        self.out.update_v = v
        self.updates += 1
        if not self._camera_set:
            self._ensure_styles(state.analytes)
            self._send_blueprint(make_active=True)   # the camera on the pile, once
            self._camera_set = True
        self.out.at(v, tracker.seq)
        keep_point = self.history.keep_due(v, live=self.live)
        self._ensure_styles(state.analytes)
        self.history.log_totals(state, now=self.live)
        if keep_point:
            self.history.keep(state, v, live=self.live)
        grades_changed = tracker.assay_version != self._joined_version
        self.cuts.log(state, v, live=self.live)
        if self._redraw_due(grades_changed):
            self.scene.log(state)
            tracker.geometry_dirty = False
            self._last_3d_wall = time.monotonic()
        log_machines(self.out, tracker.machines, tracker.projection.state.pile)
        self._log_scan()
        log_status(self.out, self.pile_id, state, updates=self.updates, rebuilds=self.rebuilds)
        if self.surveys.pending:
            self.surveys.log_pending()
            self.out.at(v, tracker.seq)
        if grades_changed and self.live:
            self.history.revise(state, v)
        self._joined_version = tracker.assay_version
        tracker.reasons.clear()
        self.last_update_valid_ns = v
        self.last_update_seq = tracker.seq
        self.last_state = state
        self.out.update_v = None
        return True

    def _redraw_due(self, grades_changed: bool) -> bool:
        """Whether the surface and voxels are redrawn: after a geometry record or an assay;
        live at most every ``geometry_period_s`` unless a cut or an assay came."""
        redraw = self.tracker.geometry_dirty or grades_changed
        if (redraw and self.live and not grades_changed and "cut" not in self.reasons
                and time.monotonic() - self._last_3d_wall < self.config.geometry_period_s):
            redraw = False
        return redraw

    def _log_scan(self) -> None:
        """The latest scan, if one came since the last update."""
        if self.tracker.latest_scan is None:
            return
        msg = decode_payload("scan", self.tracker.latest_scan.payload)
        self.tracker.latest_scan = None
        log_scan(self.out, msg, self.tracker.scanner_poses)

    def flush_known_now(self) -> None:
        """Log "as known now" (at the latest K) for every history point and cut not yet logged
        so (the end of an offline render or of the live catch-up); then go live."""
        state = self.last_state
        if state is not None:
            self.history.flush(state, self.last_update_seq, self.last_update_valid_ns)
            for cut in state.cuts:
                self.cuts.log_now(cut)
        self.live = True

    def log_plan(self, plan: dict) -> int:
        """Show a reclaim plan (:func:`planner.cli.make_plan`): each planned cut's
        footprint at its floor coloured by its predicted grade, and a table; returns the
        number of cuts shown."""
        return self.cuts.log_plan(plan, self.next_valid_ns())

    # -- layout ----------------------------------------------------------------------------

    def _ensure_styles(self, analytes) -> None:
        """The series' styles of analytes not yet styled (live: and the blueprint again)."""
        if tuple(analytes) == self._blueprint_analytes or not analytes:
            return
        new = [a for a in analytes if a not in self._blueprint_analytes]
        first = not self._blueprint_analytes
        self._blueprint_analytes = tuple(analytes)
        log_series_styles(self.rec, new, first=first, prefix=self.out.prefix)
        if not first and not self.offline:
            self._send_blueprint(make_active=False)

    @property
    def blueprint_analytes(self) -> tuple[str, ...]:
        """The analytes the series are styled for (the blueprint's), Fe before any."""
        return self._blueprint_analytes or ("Fe",)

    def pile_box(self):
        """``(origin_x_m, origin_y_m, width_m, length_m, ground_z_m)`` of the pile, or None
        before it is declared (the 3D camera's aim)."""
        pile = self.projection.state.pile
        if pile is None:
            return None
        g = pile.geometry
        return (g.origin_x_m, g.origin_y_m, g.length_x_m, g.length_y_m, pile.ground_z_m)

    def _send_blueprint(self, *, make_active: bool) -> None:
        if self.layout is not None:
            self.layout.send_blueprint(make_active=make_active)
            return
        self.rec.send_blueprint(blueprint(self.blueprint_analytes, self.config.analyte,
                                          layers=self.config.layers, pile=self.pile_box()),
                                make_active=make_active, make_default=True)


# -- driving a dashboard ----------------------------------------------------------------------


def feed(dash: Dashboard, records: Iterable, *, updates: bool = True,
         rebuild: Callable[[], None] | None = None, on_record=None) -> int:
    """Add records, updating at recorded-time boundaries when due; returns records added."""
    n = 0
    for record in records:
        if (updates and dash.seq >= 0 and record.recorded_time_ns > dash.known_ns
                and dash.due(boundary=True)):
            if dash.projection.stale and rebuild is not None:
                rebuild()
            dash.update()
        dash.add(record)
        if record.type in GEOMETRY_TYPES and n % ADVANCE_EVERY == 0:
            dash.projection.advance()
        n += 1
        if on_record is not None:
            on_record(n)
    return n


def rebuild_from(source, dash: Dashboard) -> None:
    """Refold the projection from the source up to the dashboard's position (stale state)."""
    upto = dash.seq
    dash.projection.reset()
    catch_up(source, dash.projection, upto)
    dash.projection.advance()
    dash.rebuilds += 1
    dash.log_text(f"rebuilt the projection from the ledger (a geometry event arrived late), "
                  f"seq {upto:,}", "WARN")

"""``stockpile service localizer``: fuse joint readings and GNSS fixes, publish poses.

One process per reclaimer (``--machine-id``, default ``bwr1``).  It subscribes on
``stockpile/<site>/@v1/`` to ``site_declared``, ``machine_declared``, ``joint_reading``
and ``location_fix`` with Zenoh advanced subscribers (history with late-publisher
detection, so declarations published before it started come from the publishers'
caches, or from the ledger service when no cache has them
(:mod:`services.localizer_declarations`), and the last ``HISTORY_SAMPLES`` measurements of each source), runs
:class:`services.localizer_filter.LocalizerFilter` (a UKF over the joints,
the encoder biases and the correlated GNSS error) and publishes, as source
``<machine>.localizer``:

- ``joint_estimate`` at each encoder reading (or at most every ``--estimate-period``
  site seconds): the joints, their 3x3 covariance (travel, slew, luff) and the wheel
  centre's 3x3 covariance, at the reading's valid time;
- two ``frame_transform`` events at the same time, parent frame ``site``:
  ``<machine>/wheel`` (the wheel centre; rotation: the level wheel frame, x along the
  boom, z up, :func:`projector.kinematics.wheel_rotation`) and ``<machine>/scanner`` (the
  wheel pose composed with ``MachineDeclared.scanner``; the simulator's scanner pose;
  :mod:`services.localizer_messages`).

Each estimate is held ``--smooth-lag`` site seconds (default
:data:`services.service.DEFAULT_SMOOTH_LAG_S`) and published with its joints
smoothed by the measurements since (:class:`services.localizer_smoother.FixedLagSmoother`,
a block of estimates at a time, so each goes out one to one and a half lags after its
reading); the covariances are the filter's at the reading.  On shutdown every held
estimate is published.  ``--smooth-lag 0`` publishes each estimate at once, as the
filter has it.

Input handling
--------------
- Every sample is decoded with :func:`schemas.events.event_from_sample` and checked
  with :func:`schemas.validate.check_event`; malformed or invalid input (NaN joints,
  bad payloads) is counted (``malformed``, ``invalid``) and skipped.  Duplicates (same
  source, epoch, seq, e.g. a sample received live and again from a cache) are skipped.
- Readings of other machines are ignored (``other_machine``).  A fix belongs to the
  machine when its ``frame_id`` is ``<machine>`` or starts with ``<machine>/``, or, with
  an empty ``frame_id``, when its source is ``<machine>.<something>``.
- Fixes are converted to site ENU with ``pymap3d.geodetic2enu`` against the datum of
  ``site_declared``; the covariance is the fix's ``position_covariance`` (ENU, m^2) when
  its type is known, else ``--gnss-sd`` per horizontal axis (1.7x vertically).

Reorder buffer
--------------
Readings and fixes travel on independent streams, and the filter must see them in valid
time order.  Measurements wait in a heap keyed by (valid time, readings before fixes,
arrival).  The *watermark* is the earliest of the latest valid times of every stream
seen so far (one stream per (type, source)), defined once both a reading stream and a
fix stream have been seen; a measurement is released once its valid time is at or below
the watermark (every stream has caught up with it), or once it has waited
``--reorder-hold`` wall seconds (a silent stream, e.g. a GNSS outage or a machine
without GNSS, delays the estimates by at most that much and does not stall the filter).
A measurement older than the filter's time when it would be released is counted
``late`` and skipped.  Nothing is released until the site and the
machine are declared; the buffer holds at most ``MAX_BUFFERED`` items (the oldest are
dropped and counted ``dropped``).  On shutdown the buffer is flushed.

Counters on the status line: ``readings``, ``fixes``, ``fixes_gated`` (rejected by
the Mahalanobis gate), ``fixes_skipped`` (before the first reading, or too coarse),
``regates`` (the filter re-opened its bias uncertainty after rejecting every fix for
two minutes), ``published``, ``other_machine``, ``duplicates``, and the errors
``malformed``, ``invalid``, ``late``, ``dropped``, ``errors``.
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import math
import queue
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh.ext as zext

from schemas.events import Event, Malformed, event_from_sample, is_valid_source, make_event
from schemas.times import NS_PER_S
from schemas.validate import InvalidEvent, check_event
from projector.kinematics import MachineGeometry
from services.ledger_client import LedgerClient
from services.localizer_declarations import FromLedger, LedgerDeclarations
from services.localizer_filter import GNSS_ERROR_STATES, N_STATE, LocalizerFilter
from services.localizer_messages import estimate_messages, fix_covariance_m2, fix_enu_m
from services.localizer_smoother import FixedLagSmoother
from services.localizer_tuning import FilterTuning
from services.pump import SamplePump
from services.service import (
    DEFAULT_SITE,
    DEFAULT_SMOOTH_LAG_S,
    DEFAULT_STATUS_PERIOD_S,
    Inbox,
    ServiceRuntime,
    Stopper,
    ZenohOptions,
)

SERVICE = "localizer"
#: measurements the reorder buffer holds at most
MAX_BUFFERED = 100_000
#: samples taken from the queue before the buffer is released again
MAX_BATCH = 500
#: the most recent measurements of each source asked from its cache on start-up (the
#: declarations: all the cache holds)
HISTORY_SAMPLES = {"joint_reading": 2_000, "location_fix": 2_000}
#: subscribed event types
INPUT_TYPES = ("site_declared", "machine_declared", "joint_reading", "location_fix")
_READING, _FIX = 0, 1


@dataclass(frozen=True)
class Config:
    """Options of the localizer service.

    Attributes
    ----------
    site : str
        Site id (keys ``stockpile/<site>/@v1/...``).
    zenoh : ZenohOptions
    status_period_s : float
        Seconds between status lines (0 = none).
    machine_id : str
        The reclaimer to localise.
    estimate_period_s : float
        Minimum site time between published estimates; 0 = at every reading.
    reorder_hold_s : float
        Longest wall time a measurement waits in the reorder buffer.
    gnss_sd_m : float
        Horizontal sd per axis of a fix without a covariance (m).
    gate_probability : float
        Chi-square (3 dof) probability of the GNSS Mahalanobis gate.
    drift_scale : float
        Multiplies the filter's encoder drift figures (1 = encoder set 1 of the thesis).
    antenna_along_boom_m, antenna_up_m : float
        GNSS antenna mount relative to the wheel centre (the schema has no field yet).
    smooth_lag_s : float
        Site seconds each estimate is held and smoothed with the measurements after it
        before it is published (0: published at once, as the filter has it;
        ``math.inf``: at the end of the run, smoothed over all of it).
    """

    site: str = DEFAULT_SITE
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    status_period_s: float = DEFAULT_STATUS_PERIOD_S
    machine_id: str = "bwr1"
    estimate_period_s: float = 0.0
    reorder_hold_s: float = 0.5
    gnss_sd_m: float = 0.45
    gate_probability: float = 0.999
    drift_scale: float = 1.0
    antenna_along_boom_m: float = 0.0
    antenna_up_m: float = 0.0
    smooth_lag_s: float = DEFAULT_SMOOTH_LAG_S

    def __post_init__(self) -> None:
        if not is_valid_source(f"{self.machine_id}.localizer") or "/" in self.machine_id:
            raise ValueError(f"bad machine id {self.machine_id!r}")
        if not (self.estimate_period_s >= 0 and self.reorder_hold_s >= 0
                and self.gnss_sd_m > 0 and 0 < self.gate_probability < 1
                and self.drift_scale > 0 and math.isfinite(self.antenna_along_boom_m)
                and math.isfinite(self.antenna_up_m) and self.smooth_lag_s >= 0):
            raise ValueError("--estimate-period, --reorder-hold and --smooth-lag must be >= 0, "
                             "--gnss-sd and --drift-scale > 0, --gate-probability in (0, 1)")

    def tuning(self) -> FilterTuning:
        """The filter's noise model for these options."""
        base = FilterTuning()
        k = self.drift_scale
        return FilterTuning(
            bias_walk_per_sqrt_s=tuple(k * v for v in base.bias_walk_per_sqrt_s),
            bias_walk_per_sqrt_moved=tuple(k * v for v in base.bias_walk_per_sqrt_moved),
            travel_scale_sd=k * base.travel_scale_sd,
            gate_probability=self.gate_probability)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The localizer's own options (the shared ones are added by ``service_cli``)."""
    parser.add_argument("--machine-id", "--machine", dest="machine_id", default="bwr1",
                        help="the reclaimer to localise (default bwr1)")
    parser.add_argument("--estimate-period", type=float, default=0.0, metavar="S",
                        help="minimum site seconds between published estimates "
                        "(default 0: every encoder reading)")
    parser.add_argument("--reorder-hold", type=float, default=0.5, metavar="S",
                        help="longest wall time a measurement waits for the other stream "
                        "(default 0.5)")
    parser.add_argument("--gnss-sd", type=float, default=0.45, metavar="M",
                        help="horizontal sd of a fix without covariance, m (default 0.45)")
    parser.add_argument("--gate-probability", type=float, default=0.999, metavar="P",
                        help="chi-square probability of the GNSS gate (default 0.999)")
    parser.add_argument("--drift-scale", type=float, default=1.0, metavar="K",
                        help="scale of the encoder drift model (default 1: thesis set 1)")
    parser.add_argument("--antenna-along-boom", type=float, default=0.0, metavar="M",
                        help="GNSS antenna beyond the wheel centre along the boom, m")
    parser.add_argument("--antenna-up", type=float, default=0.0, metavar="M",
                        help="GNSS antenna mast height, m")
    parser.add_argument("--smooth-lag", type=float, default=DEFAULT_SMOOTH_LAG_S, metavar="S",
                        help="site seconds each estimate waits to be smoothed with the "
                        f"fixes after it (default {DEFAULT_SMOOTH_LAG_S:g}; 0: publish at once)")


def config_from_args(args: argparse.Namespace) -> Config:
    """A :class:`Config` from parsed arguments (ValueError on bad values)."""
    return Config(site=args.site, zenoh=ZenohOptions.from_args(args),
                  status_period_s=args.status_period, machine_id=args.machine_id,
                  estimate_period_s=args.estimate_period, reorder_hold_s=args.reorder_hold,
                  gnss_sd_m=args.gnss_sd, gate_probability=args.gate_probability,
                  drift_scale=args.drift_scale, antenna_along_boom_m=args.antenna_along_boom,
                  antenna_up_m=args.antenna_up, smooth_lag_s=args.smooth_lag)


class _SeenSeqs:
    """Which sequence numbers of one (source, epoch) stream were seen (bounded memory)."""

    __slots__ = ("floor", "above")

    def __init__(self) -> None:
        self.floor = 0          # every seq below this was seen
        self.above: set[int] = set()

    def add(self, seq: int) -> bool:
        """Record ``seq``; False if it was seen before."""
        if seq < self.floor or seq in self.above:
            return False
        self.above.add(seq)
        while self.floor in self.above:
            self.above.discard(self.floor)
            self.floor += 1
        if len(self.above) > 10_000:     # a long gap: forget the oldest holes
            self.floor = min(self.above)
            self.above = {s for s in self.above if s > self.floor}
            self.floor += 1
        return True


# -- the service ------------------------------------------------------------------------------


class Localizer:
    """The service's state machine, independent of Zenoh (``handle`` events, ``release``).

    Parameters
    ----------
    config : Config
    publish : callable(message) -> None
        Called with each message to publish, in order.
    count : callable(name, n=1) -> None
        Status counter increment.
    log : callable(msg, **fields) -> None
    """

    def __init__(self, config: Config, publish, count, log) -> None:
        self.config = config
        self._publish = publish
        self._count = count
        self._log = log
        self.datum: tuple[float, float, float] | None = None
        self.geometry: MachineGeometry | None = None
        self.filter: LocalizerFilter | None = None
        self._heap: list[tuple[int, int, int, float, Event, Any]] = []
        self._arrival = itertools.count()
        self._stream_latest: dict[tuple[str, str], int] = {}
        self._seen: dict[tuple[str, int], _SeenSeqs] = {}
        self._last_published_ns: int | None = None
        self._late = 0

    # -- input ----------------------------------------------------------------------------

    def handle(self, item: Event | Malformed, now_s: float | None = None) -> None:
        """Take one decoded sample: declarations at once, measurements into the buffer."""
        if isinstance(item, Malformed):
            self._count("malformed")
            return
        try:
            message = check_event(item)
        except InvalidEvent as exc:
            self._count("invalid")
            self._log("invalid event", level="warning", type=item.type, source=item.source,
                      seq=item.seq, code=exc.code, detail=exc.detail)
            return
        seen = self._seen.setdefault((item.source, item.epoch), _SeenSeqs())
        if not seen.add(item.seq):
            self._count("duplicates")
            return
        now_s = time.monotonic() if now_s is None else now_s
        if item.type == "site_declared":
            self._declare_site(message)
        elif item.type == "machine_declared":
            self._declare_machine(message)
        elif item.type == "joint_reading":
            if message.machine_id != self.config.machine_id:
                self._count("other_machine")
                return
            self._buffer(_READING, item, message, now_s)
        elif item.type == "location_fix":
            if not self._fix_is_ours(item.source, message.frame_id):
                self._count("other_machine")
                return
            self._buffer(_FIX, item, message, now_s)

    @property
    def needs_declarations(self) -> bool:
        """True while the site's datum or this machine's geometry is unknown."""
        return self.datum is None or self.geometry is None

    def fill_declaration(self, event: Event) -> None:
        """Take a declaration read from the ledger only when it is still missing."""
        if ((event.type == "site_declared" and self.datum is None)
                or (event.type == "machine_declared" and self.geometry is None)):
            self.handle(event)

    def _fix_is_ours(self, source: str, frame_id: str) -> bool:
        m = self.config.machine_id
        if frame_id:
            return frame_id == m or frame_id.startswith(m + "/")
        return source.split(".", 1)[0] == m

    def _declare_site(self, message) -> None:
        datum = (message.datum_lat_deg, message.datum_lon_deg, message.datum_alt_m)
        if datum != self.datum:
            self.datum = datum
            self._log("site declared", site_id=message.site_id, lat=datum[0], lon=datum[1],
                      alt_m=datum[2])

    def _declare_machine(self, message) -> None:
        if message.machine_id != self.config.machine_id:
            return
        try:
            geometry = MachineGeometry.from_machine_declared(
                message, antenna_along_boom_m=self.config.antenna_along_boom_m,
                antenna_up_m=self.config.antenna_up_m)
        except ValueError as exc:
            self._count("invalid")
            self._log("bad machine declaration", level="warning", detail=str(exc))
            return
        if geometry == self.geometry:
            return
        self.geometry = geometry
        if self.filter is None:
            self.filter = LocalizerFilter(geometry, self.config.tuning())
            if self.config.smooth_lag_s > 0:
                self.filter.recorder = FixedLagSmoother(
                    N_STATE, GNSS_ERROR_STATES, self.config.smooth_lag_s * NS_PER_S)
        else:
            self.filter.set_geometry(geometry)
        self._log("machine declared", machine_id=message.machine_id, l5_m=geometry.l5_m)

    def _buffer(self, kind: int, event: Event, message, now_s: float) -> None:
        stream = (event.type, event.source)
        latest = self._stream_latest.get(stream)
        if latest is None or event.valid_time_ns > latest:
            self._stream_latest[stream] = event.valid_time_ns
        heapq.heappush(self._heap, (event.valid_time_ns, kind, next(self._arrival), now_s,
                                    event, message))
        if len(self._heap) > MAX_BUFFERED:
            heapq.heappop(self._heap)        # the oldest measurement goes
            self._count("dropped")

    @property
    def backlog(self) -> int:
        """Measurements waiting in the reorder buffer and estimates held for smoothing."""
        smoother = self._smoother
        return len(self._heap) + (smoother.held if smoother is not None else 0)

    @property
    def _smoother(self) -> FixedLagSmoother | None:
        return self.filter.recorder if self.filter is not None else None

    # -- processing ------------------------------------------------------------------------

    def release(self, now_s: float | None = None, *, flush: bool = False) -> int:
        """Process the buffered measurements that are due; return how many."""
        if self.filter is None or self.datum is None:
            return 0
        now_s = time.monotonic() if now_s is None else now_s
        kinds_seen = {type_name for type_name, _source in self._stream_latest}
        watermark = (min(self._stream_latest.values())
                     if kinds_seen >= {"joint_reading", "location_fix"} else None)
        hold = self.config.reorder_hold_s
        done = 0
        while self._heap:
            t_ns, kind, _n, arrived_s, event, message = self._heap[0]
            due = flush or (watermark is not None and t_ns <= watermark) \
                or now_s - arrived_s >= hold
            if not due:
                break
            heapq.heappop(self._heap)
            self._process(kind, t_ns, event, message)
            done += 1
        smoother = self._smoother
        if smoother is not None:
            for (t_ns, g, joint_cov, wheel_cov), state in smoother.due(flush=flush):
                self._emit(t_ns, g, state[:3], joint_cov, wheel_cov)
        return done

    def _process(self, kind: int, t_ns: int, event: Event, message) -> None:
        f = self.filter
        assert f is not None
        if f.t_ns is not None and t_ns < f.t_ns:
            self._count("late")
            self._late += 1
            if self._late <= 10 or self._late % 1000 == 0:   # the first few, then sparsely
                self._log("late measurement skipped", level="warning", type=event.type,
                          source=event.source, seq=event.seq, valid_time_ns=t_ns,
                          filter_time_ns=f.t_ns, late_total=self._late)
            return
        try:
            if kind == _READING:
                f.update_joints((message.travel_m, message.slew_rad, message.luff_rad),
                                t_ns=t_ns)
                self._count("readings")
                self._maybe_publish(t_ns)
            else:
                assert self.datum is not None
                enu = fix_enu_m(message, self.datum)
                cov = fix_covariance_m2(message, self.config.gnss_sd_m)
                regates = f.counters.regates
                outcome = f.update_gnss(enu, cov, t_ns=t_ns)
                self._count("fixes")
                if f.counters.regates != regates:
                    self._count("regates")
                    self._log("fixes rejected for too long: bias uncertainty re-opened",
                              level="warning", valid_time_ns=t_ns)
                if outcome == "gated":
                    self._count("fixes_gated")
                elif outcome == "skipped":
                    self._count("fixes_skipped")
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            self._count("errors")
            self._log("measurement skipped", level="warning", type=event.type,
                      source=event.source, seq=event.seq, detail=str(exc))

    def _maybe_publish(self, t_ns: int) -> None:
        period_ns = int(self.config.estimate_period_s * NS_PER_S)
        if self._last_published_ns is not None and t_ns - self._last_published_ns < period_ns:
            return
        f, g = self.filter, self.geometry
        assert f is not None and g is not None
        e = f.estimate()
        self._last_published_ns = t_ns
        if f.recorder is not None:        # published once smoothed (release)
            f.recorder.hold((t_ns, g, e.joint_covariance, e.wheel_covariance_m2))
            return
        self._emit(t_ns, g, e.joints, e.joint_covariance, e.wheel_covariance_m2)

    def _emit(self, t_ns: int, g: MachineGeometry, joints, joint_cov, wheel_cov) -> None:
        """Publish one estimate's messages, unless one fails the ledger's checks."""
        messages = estimate_messages(self.config.machine_id, g, t_ns, joints, joint_cov,
                                     wheel_cov)
        source = f"{self.config.machine_id}.localizer"
        for m in messages:   # every event must pass the ledger's checks before it leaves
            try:
                check_event(make_event(m, source=source, epoch=0, seq=0))
            except InvalidEvent as exc:
                self._count("errors")
                self._log("estimate not published", level="warning", code=exc.code,
                          detail=exc.detail)
                return
        for m in messages:
            self._publish(m)
            self._count("published")


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the localizer until SIGINT/SIGTERM (or ``stopper``); return the exit code."""
    samples = Inbox()

    def on_sample(sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        samples.put((str(sample.key_expr), sample.payload.to_bytes(), attachment))

    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name=config.machine_id,
                             status_period_s=config.status_period_s, stopper=stopper)
    localizer: Localizer | None = None
    runtime.open(backlog=lambda: localizer.backlog if localizer else 0,
                 error_keys=("malformed", "invalid", "late", "dropped", "errors"),
                 announce=False)
    with runtime:
        publisher = runtime.publisher(f"{config.machine_id}.localizer")
        publisher.declare("joint_estimate", "frame_transform")
        status = runtime.status
        assert status is not None and runtime.stopper is not None
        localizer = Localizer(config, publisher.publish, status.add, runtime.log)
        for name in ("readings", "fixes", "fixes_gated", "fixes_skipped", "regates",
                     "published"):
            status.add(name, 0)
        subscribers = [SamplePump(
            lambda handler, type_name=type_name: zext.declare_advanced_subscriber(
                runtime.session, f"stockpile/{config.site}/@v1/{type_name}/**", handler,
                history=zext.HistoryConfig(
                    detect_late_publishers=True,
                    max_samples=HISTORY_SAMPLES.get(type_name)),
                recovery=zext.RecoveryConfig(heartbeat=True),
                subscriber_detection=True),
            on_sample, name=f"localizer-{type_name}")
            for type_name in INPUT_TYPES]
        runtime.log("subscribed", machine_id=config.machine_id,
                    keys=",".join(f"{t}/**" for t in INPUT_TYPES))
        runtime.announce()     # the liveliness token: subscribed and serving
        LedgerDeclarations(LedgerClient(runtime.session, config.site, stop=runtime.stopper.event),
                           config.machine_id, samples.put,
                           lambda: localizer.needs_declarations, runtime.stopper.event,
                           runtime.log).start()
        stop = runtime.stopper
        try:
            while not stop.is_set():
                try:
                    batch = [samples.get(0.02)]
                except queue.Empty:
                    batch = []
                while batch and len(batch) < MAX_BATCH:
                    try:
                        batch.append(samples.get_nowait())
                    except queue.Empty:
                        break
                for item in batch:
                    _handle_safely(localizer, item, status, runtime)
                localizer.release()
        finally:
            for sub in subscribers:
                try:
                    sub.undeclare()
                except Exception:  # noqa: BLE001 - the session may be closing
                    pass
            while True:   # what already arrived is still processed
                try:
                    _handle_safely(localizer, samples.get_nowait(), status, runtime)
                except queue.Empty:
                    break
            localizer.release(flush=True)
    return 0


def _handle_safely(localizer: Localizer, item, status, runtime: ServiceRuntime) -> None:
    """Decode and handle one raw sample; an unexpected failure is counted, never fatal."""
    try:
        if isinstance(item, FromLedger):
            localizer.fill_declaration(item.event)
        else:
            localizer.handle(event_from_sample(*item))
    except Exception as exc:  # noqa: BLE001 - bad input must not stop the service
        status.add("errors")
        runtime.log("sample skipped", level="warning", error=f"{type(exc).__name__}: {exc}")

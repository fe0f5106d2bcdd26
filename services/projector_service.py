"""``stockpile service projector``: a live projection of one pile from the ledger service.

It follows the ledger service over Zenoh (never the DuckDB file): a catch-up read of
everything committed, then every committed head as it is published.  Geometry events are
folded in (valid time, global seq) order behind a reorder window of ``--reorder-s`` site
seconds; a geometry event that arrives later than that (valid before what was already
folded) makes the live state stale, and the service rebuilds it from the ledger's as-of
read before it answers again, so the answer is never silently wrong.  Lots and assays
only feed the grade join, which is done at each answer as known at the ledger's head.

Out:

- ``stockpile/<site>/projector/<pile>/state``: the pile's summary (JSON, the shape of
  ``stockpile project --json`` plus ``ledger_seq`` and ``rebuilds``) after each change,
  at most every ``--publish-period-s`` wall seconds;
- the same key answers queries with the latest summary.

Log lines: ``caught up``, ``rebuilt`` (with the late event's type), ``stopped``.
"""

from __future__ import annotations

import argparse
import heapq
import json
import queue
import threading
import time
from dataclasses import dataclass, field

from projector import fold as F
from projector.grades import AssayRecord, grade_from_map
from projector.query import PileState, summarise
from schemas.events import decode_payload
from schemas.jsonl import json_safe
from schemas.times import NS_PER_S
from services.ledger_client import LedgerClient, LedgerUnavailable
from services.service import (
    DEFAULT_SITE,
    LIVE_REORDER_S,
    Inbox,
    ServiceRuntime,
    Stopper,
    ZenohOptions,
)

SERVICE = "projector"
DEFAULT_REORDER_S = LIVE_REORDER_S   # the localizer's smoothed poses come late
DEFAULT_PUBLISH_PERIOD_S = 1.0
READ_CHUNK = 5_000


def state_key(site: str, pile_id: str) -> str:
    """The key the projector publishes (and answers) its summary on."""
    return f"stockpile/{site}/projector/{pile_id}/state"


@dataclass
class Config:
    """``stockpile service projector`` options.

    Attributes
    ----------
    pile_id : str
        The pile to project.
    site : str
        Site id.
    zenoh : ZenohOptions
    reorder_s : float
        Site seconds a geometry event may arrive behind the newest one and still be
        folded in order (later: the state is rebuilt from the ledger).
    publish_period_s : float
        Shortest wall time between two published summaries, seconds.
    status_period_s : float
        Period of the status line, seconds.
    """

    pile_id: str
    site: str = DEFAULT_SITE
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    reorder_s: float = DEFAULT_REORDER_S
    publish_period_s: float = DEFAULT_PUBLISH_PERIOD_S
    status_period_s: float = 5.0

    def __post_init__(self) -> None:
        if not self.pile_id:
            raise ValueError("pile_id must not be empty")
        if self.reorder_s < 0 or self.publish_period_s < 0:
            raise ValueError("reorder_s and publish_period_s must be >= 0")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pile", dest="pile_id", required=True, help="pile id to project")
    parser.add_argument("--reorder-s", type=float, default=DEFAULT_REORDER_S,
                        help="site seconds of reordering before a late geometry event "
                             "forces a rebuild (default %(default)s)")
    parser.add_argument("--publish-period-s", type=float, default=DEFAULT_PUBLISH_PERIOD_S,
                        help="shortest wall time between published summaries "
                             "(default %(default)s)")


def config_from_args(args: argparse.Namespace) -> Config:
    return Config(pile_id=args.pile_id, site=args.site, zenoh=ZenohOptions.from_args(args),
                  reorder_s=args.reorder_s, publish_period_s=args.publish_period_s,
                  status_period_s=args.status_period)


class LiveProjection:
    """The live fold of one pile: ledger records in, a :class:`PileState` out (no I/O).

    Parameters
    ----------
    pile_id : str
    reorder_ns : int
        Geometry events wait until the newest valid time seen is this far past theirs.
    """

    def __init__(self, pile_id: str, reorder_ns: int) -> None:
        self.pile_id, self.reorder_ns = pile_id, int(reorder_ns)
        self.reset()

    def reset(self) -> None:
        """Forget everything (before a rebuild)."""
        self.state = F.initial_state(self.pile_id)
        self._waiting: list[tuple[int, int, object]] = []
        self._newest_valid_ns = -(2 ** 62)
        self.lots: dict[str, dict[str, float]] = {}
        self.assays: list[AssayRecord] = []
        self.ledger_seq = -1
        self.known_ns = -(2 ** 62)
        self.stale = False

    def add(self, record) -> None:
        """Take one committed ledger record (in global order)."""
        self.ledger_seq = max(self.ledger_seq, record.global_seq)
        self.known_ns = max(self.known_ns, record.recorded_time_ns)
        if record.type == "lot_declared":
            msg = decode_payload(record.type, record.payload)
            self.lots[msg.lot_id] = grade_from_map(msg.planned_grade)
        elif record.type == "assay":
            self.assays.append(AssayRecord.from_message(
                decode_payload(record.type, record.payload), record.recorded_time_ns))
        elif record.type in F.GEOMETRY_TYPES:
            if (record.valid_time_ns, record.global_seq) < self.state.high_water:
                self.stale = True   # it belongs before what is folded: rebuild
                return
            heapq.heappush(self._waiting, (record.valid_time_ns, record.global_seq, record))
            self._newest_valid_ns = max(self._newest_valid_ns, record.valid_time_ns)

    def advance(self, *, everything: bool = False) -> int:
        """Fold the waiting geometry events that are past the reorder window; returns how many."""
        limit = (2 ** 62) if everything else self._newest_valid_ns - self.reorder_ns
        n = 0
        while self._waiting and self._waiting[0][0] <= limit:
            F.apply(self.state, heapq.heappop(self._waiting)[2])
            n += 1
        return n

    def summary(self) -> PileState:
        """The pile now (everything folded or waiting), grades as known at the head."""
        view = self.state.copy()
        for _v, _g, record in sorted(self._waiting, key=lambda w: (w[0], w[1])):
            F.apply(view, record)
        F.flush(view)
        return summarise(view, self.lots, self.assays, valid_time_ns=view.high_water[0],
                         known_time_ns=self.known_ns)


def _summary_json(projection: LiveProjection, rebuilds: int) -> bytes:
    state = projection.summary()
    body = state.to_json()
    body.update(ledger_seq=projection.ledger_seq, rebuilds=rebuilds)
    return json.dumps(json_safe(body), allow_nan=False).encode()


def catch_up(client, projection: LiveProjection, head_seq: int, log=None) -> int:
    """Read committed records ``ledger_seq + 1 .. head_seq`` in chunks and add them."""
    read = 0
    start = projection.ledger_seq + 1
    while start <= head_seq:
        stop = min(head_seq + 1, start + READ_CHUNK)
        for record in client.read(start, stop):
            projection.add(record)
            read += 1
        projection.ledger_seq = max(projection.ledger_seq, stop - 1)
        start = stop
        if log is not None and read and read % (10 * READ_CHUNK) == 0:
            log("catching up", read=read, head=head_seq)
    return read


def rebuild(client, projection: LiveProjection) -> int:
    """Refold from the ledger (everything known now) after a late geometry event."""
    head = client.head()["global_seq"]
    projection.reset()
    return catch_up(client, projection, head)


def newest_head(heads: Inbox, timeout_s: float) -> int | None:
    """The newest committed head announced (waiting up to ``timeout_s`` for one), or None."""
    try:
        newest = heads.get(timeout_s)
    except queue.Empty:
        return None
    while True:
        try:
            newest = max(newest, heads.get_nowait())
        except queue.Empty:
            return newest


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the projector until SIGINT/SIGTERM (or ``stopper``); return the exit code."""
    heads = Inbox()
    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name=config.pile_id,
                             status_period_s=config.status_period_s, stopper=stopper)
    projection = LiveProjection(config.pile_id, int(config.reorder_s * NS_PER_S))
    runtime.open(backlog=lambda: heads.qsize(), error_keys=("errors",), announce=False)
    latest: list[bytes] = [b""]
    lock = threading.Lock()
    with runtime:
        status = runtime.status
        assert status is not None and runtime.stopper is not None
        for name in ("records", "folded", "published", "rebuilds", "errors"):
            status.add(name, 0)
        session = runtime.session
        key = state_key(config.site, config.pile_id)
        publisher = session.declare_publisher(key)

        def on_query(query) -> None:
            with lock:
                body = latest[0]
            if body:
                query.reply(key, body)
            else:
                query.reply_err(b"no projection yet")

        queryable = session.declare_queryable(key, on_query)
        client = LedgerClient(session, config.site, stop=runtime.stopper.event)
        subscriber = client.follow_head(lambda head: heads.put(head["global_seq"]))
        rebuilds = 0
        try:
            first = client.first_head(log=runtime.log)
            if first is None:   # stopped before the ledger service answered
                return 0
            head = first["global_seq"]
            n = catch_up(client, projection, head, runtime.log)
            status.add("records", n)
            status.add("folded", projection.advance())
            runtime.log("caught up", records=n, head=head)
            runtime.announce()
            dirty, last_pub = True, 0.0
            stop = runtime.stopper
            while not stop.is_set():
                target = newest_head(heads, 0.05)
                try:
                    if target is not None and target > projection.ledger_seq:
                        status.add("records", catch_up(client, projection, target))
                        status.add("folded", projection.advance())
                        dirty = True
                    if projection.stale:
                        rebuilds += 1
                        status.add("rebuilds")
                        read = rebuild(client, projection)
                        status.add("folded", projection.advance())
                        runtime.log("rebuilt", head=projection.ledger_seq, records=read)
                        dirty = True
                    if dirty and time.monotonic() - last_pub >= config.publish_period_s:
                        body = _summary_json(projection, rebuilds)
                        with lock:
                            latest[0] = body
                        publisher.put(body)
                        status.add("published")
                        dirty, last_pub = False, time.monotonic()
                except Exception as exc:  # noqa: BLE001 - a failed read is retried later
                    if stop.is_set():     # a read given up because the service stops
                        break
                    status.add("errors")
                    runtime.log("update failed", level="warning",
                                error=f"{type(exc).__name__}: {exc}")
                    stop.wait(0.5)
        except LedgerUnavailable:
            if not runtime.stopper.is_set():   # given up because the service stops: fine
                raise
        finally:
            for entity in (subscriber, queryable, publisher):
                try:
                    entity.undeclare()
                except Exception:  # noqa: BLE001 - the session may be closing
                    pass
    return 0

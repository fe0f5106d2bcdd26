"""``stockpile service ledger``: the single writer of the ledger.

Data flow::

    zenoh  stockpile/<site>/@v1/**  --AdvancedSubscriber callback-->  bounded queue
        --writer thread: batches (size or time bound, whichever first)-->  LedgerStore.append
        --> put  stockpile/<site>/@ledger/head   (JSON: global_seq, recorded_time_ns, chain)

    zenoh get stockpile/<site>/@ledger/q/<what>  --queryable-->  reader thread --> replies

- **Subscribing and recovery.** One ``zenoh.ext`` AdvancedSubscriber on the site's
  events with history (``detect_late_publishers``): a (re)started ledger asks every
  publisher's cache for what it published before, so a ledger killed mid-run loses
  nothing its publishers still cache.  Any event that does not arrive shows up as a
  jump in its source's sequence, which the store records in its gap table with the
  exact range (:mod:`ledger.store`), and the service logs a ``gap opened`` line.
  Then :class:`GapRepair` asks that source's publisher cache again (a short-lived
  history subscriber whose samples are kept only if they fall in an open gap); what
  comes back closes the gap, what the cache no longer holds stays an open gap,
  reported.  (Zenoh's own heartbeat recovery is not used: in zenoh 1.x enabling it
  makes the late-joiner history skip samples older than the first live one.)
  Duplicates (history replayed after a restart, a retransmission) are no-ops.
- **Backpressure.** The callback only queues the raw sample; when the queue is full
  it blocks, which backs up Zenoh's transport and, through congestion control BLOCK,
  the publishers: nothing is dropped.
- **Reads** over queryables (other processes never open the DuckDB file while the
  service runs); :class:`services.ledger_client.LedgerClient` is the client:

  ===============  ==========================================  ====================
  key              query payload (JSON)                         reply
  ===============  ==========================================  ====================
  ``q/events``     ``start``, ``stop``, ``types``, ``sources``,  record chunks
                   ``limit``
  ``q/as_of``      ``valid_time_ns``, ``known_time_ns``,        record chunks
                   ``types``, ``after`` ([valid_ns, global_seq]),
                   ``max_global_seq``, ``limit``
  ``q/stats``      (none)                                       JSON
  ``q/head``       (none)                                       JSON
  ``q/gaps``       ``open_only``                                JSON list
  ``q/quarantine`` (none)                                       JSON list
  ``q/streams``    (none)                                       JSON list
  ``q/backup``     ``to`` (a directory)                         JSON manifest (by the
                                                                writer, between batches)
  ===============  ==========================================  ====================

  ``limit`` caps the records of one answer (a client pages with ``start`` or
  ``after``); ``max_global_seq`` keeps the events committed up to a head the client
  pinned.  The JSON forms are :mod:`ledger.wire`'s.
- **Holder file.** While it runs, the service leaves ``<ledger>.service.json`` beside
  the file (:mod:`ledger.holder`): its site, pid and the endpoints a reader on this
  machine connects to, so that ``stockpile audit`` and the other read commands given
  the file read through these queryables instead of failing on DuckDB's lock.

  Record chunks are :mod:`ledger.wire` bytes of up to ``chunk_bytes``; each reply's
  attachment is ``u32 chunk index | u8 last | u64 total records`` so a client can
  check it got every chunk.  An error is one ``reply_err`` with a message.
- **A PostgreSQL ledger** (``--ledger postgresql://...``): the same writer, batches and
  queryables.  What only a DuckDB file has is left out: no holder file (readers open the
  URL themselves, read-only, each on one snapshot), no free-space watermark (the server
  watches its own disk; a full disk, SQLSTATE 53100, still pauses the writer through
  :class:`~services.ledger_disk.DiskGuard`), no buffer pool cap (``--memory-limit-mb``
  is refused: the server's memory is its own settings), no ``q/backup`` (a one-line
  error naming ``pg_basebackup`` / ``pg_dump``), and checkpoints go to ``--checkpoints``
  only (there is no file to put them beside).  The URL's password is never logged.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import queue
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
import zenoh.ext as zext

from common.options import (add_accept_loss, add_analytes, add_batch_size, add_clock,
                            add_duration, add_ledger, describe_ledger, is_ledger_url)
from ledger import clock_by_name, open_ledger
from ledger.signing import SigningPolicy, add_signing_options, policy_from_args
from ledger.views import check_declared
from ledger.wire import stats_to_json
from ledger.errors import LedgerError
from ledger.holder import LedgerHolder, remove_holder, this_host, write_holder
from ledger.store import LedgerStore
from ledger.wire import (encode_records, gap_to_json, head_to_json, quarantine_to_json,
                         stream_to_json)
from schemas.analytes import AnalyteOptions, policy_from_args as analyte_options
from schemas.events import Malformed, event_from_sample
from services.service import ServiceRuntime, Stopper, ZenohOptions, log
from services.ledger_backup import BackupRequest, next_sample
from services.ledger_checkpoints import Checkpointer
from services.ledger_disk import DEFAULT_MIN_FREE_MB, DiskGuard, publish_status
from services.ledger_repair import GapRepair
from services.resubscribe import CacheRecall
from services.pump import SamplePump
from services.zenoh_config import reader_endpoints

SERVICE = "ledger"
DEFAULT_BATCH_SIZE = 2_000
DEFAULT_BATCH_INTERVAL_S = 0.02
DEFAULT_QUEUE_SIZE = 200_000
DEFAULT_CHUNK_BYTES = 1 << 20
DEFAULT_CHECKPOINT_EVERY_S = 3600.0

#: what the ledger's queryables answer (``stockpile/<site>/@ledger/q/<what>``)
QUERIES = ("events", "as_of", "stats", "head", "gaps", "quarantine", "streams")

#: attachment of every record-chunk reply: chunk index, last flag, total records
CHUNK_ATTACHMENT = struct.Struct("<IBQ")


def head_key(site: str) -> str:
    """Where the committed head is published after each batch."""
    return f"stockpile/{site}/@ledger/head"


def query_key(site: str, what: str) -> str:
    """The queryable serving ``what`` (one of :data:`QUERIES`)."""
    return f"stockpile/{site}/@ledger/q/{what}"


@dataclass(frozen=True)
class Config:
    """Options of the ledger service.

    Attributes
    ----------
    ledger_path : str
        The DuckDB file (created if missing), a ``postgresql://`` URL (the schema is
        installed if missing and the user may), or ``:memory:``.
    clock : str
        Recorded time: ``wall`` (a real yard) or ``events`` (the simulated yard's
        ``clock`` events).
    batch_size : int
        Most events per append (one transaction).
    batch_interval_s : float
        Longest time the first event of a batch waits for more, seconds, counted from
        its arrival (a batch the writer takes late waits only for what is queued).
    queue_size : int
        Samples held between Zenoh and the writer; a full queue blocks Zenoh.
    history : bool
        Ask publishers' caches for what was published before this start.
    chunk_bytes : int
        Target size of one reply chunk of records, bytes.
    checkpoint_dir : str or None
        Where checkpoints of the chain head go (:mod:`ledger.checkpoint`); default
        ``<ledger>.checkpoints`` beside a ledger file, none for an in-memory one.
    checkpoint_every_s : float
        Seconds between checkpoints while the head moves; one more at every clean stop.
    signing : SigningPolicy or None
        Types that must be signed and the admin key trusted (:mod:`ledger.signing`).
    accept_loss : bool
        Open a ledger whose head went backwards (:mod:`ledger.head_file`).
    analytes : AnalyteOptions or None
        The site's declared analytes and unknown-analyte policy (:mod:`schemas.analytes`);
        None: what the ledger recorded.
    memory_limit_mb : int or None
        Cap on DuckDB's buffer pool, megabytes (None: ``WRITER_MEMORY_LIMIT_MB`` of
        :mod:`ledger.duckdb_store`), so the service's memory stays flat as the file grows.
    min_free_mb : float
        Free-space watermark, MiB (alarm ``low_disk``, :mod:`services.ledger_disk`).
    """

    site: str
    zenoh: ZenohOptions
    ledger_path: str
    status_period_s: float = 5.0
    clock: str = "wall"
    batch_size: int = DEFAULT_BATCH_SIZE
    batch_interval_s: float = DEFAULT_BATCH_INTERVAL_S
    queue_size: int = DEFAULT_QUEUE_SIZE
    history: bool = True
    chunk_bytes: int = DEFAULT_CHUNK_BYTES
    checkpoint_dir: str | None = None
    checkpoint_every_s: float = DEFAULT_CHECKPOINT_EVERY_S
    signing: SigningPolicy | None = None
    accept_loss: bool = False
    analytes: AnalyteOptions | None = None
    memory_limit_mb: int | None = None
    min_free_mb: float = DEFAULT_MIN_FREE_MB

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ValueError(f"batch size must be >= 1, got {self.batch_size}")
        if not self.batch_interval_s > 0:
            raise ValueError(f"batch interval must be > 0 s, got {self.batch_interval_s}")
        if self.queue_size < 1:
            raise ValueError(f"queue size must be >= 1, got {self.queue_size}")
        if self.memory_limit_mb is not None and self.memory_limit_mb < 16:
            raise ValueError(f"memory limit must be >= 16 MB, got {self.memory_limit_mb}")
        if not self.min_free_mb >= 0:
            raise ValueError(f"--min-free-mb must be >= 0 MiB, got {self.min_free_mb}")
        if self.postgres and self.memory_limit_mb is not None:
            raise ValueError("--memory-limit-mb caps a DuckDB file's buffer pool; a PostgreSQL "
                             "ledger's memory is the server's (shared_buffers, work_mem)")

    @property
    def postgres(self) -> bool:
        """Whether the ledger is a PostgreSQL URL (no file: no holder file, no watermark)."""
        return is_ledger_url(self.ledger_path)

    @property
    def file_path(self) -> str | None:
        """The ledger's file, None for a PostgreSQL or an in-memory ledger."""
        return None if self.postgres or self.ledger_path == ":memory:" else self.ledger_path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_ledger(parser, help="created if missing")
    add_clock(parser, help="recorded time from the wall clock or the site's clock events "
              "(simulated yard)")
    add_batch_size(parser)
    parser.add_argument("--batch-interval", type=float, default=DEFAULT_BATCH_INTERVAL_S,
                        metavar="S", help="longest wait for a batch to fill, seconds "
                        f"(default {DEFAULT_BATCH_INTERVAL_S})")
    parser.add_argument("--queue-size", type=int, default=DEFAULT_QUEUE_SIZE,
                        help=f"samples buffered before Zenoh is backed up (default {DEFAULT_QUEUE_SIZE})")
    parser.add_argument("--no-history", action="store_true",
                        help="do not ask publishers' caches for earlier events on start")
    parser.add_argument("--checkpoints", metavar="DIR",
                        help="where signed checkpoints of the chain head go (default "
                        "LEDGER.checkpoints; keep a copy away from the ledger file)")
    add_duration(parser, "--checkpoint-every", default=DEFAULT_CHECKPOINT_EVERY_S,
                 help="time between checkpoints while the ledger grows, with a unit, wall "
                 "time (default 1h); one more at every clean stop")
    add_signing_options(parser)
    add_accept_loss(parser)
    add_analytes(parser)
    parser.add_argument("--memory-limit-mb", type=int, default=None, metavar="MB",
                        help="cap on the database's buffer pool, megabytes (default 256)")
    parser.add_argument("--min-free-mb", type=float, default=DEFAULT_MIN_FREE_MB, metavar="MB",
                        help="warn and raise the low_disk alarm when the ledger's file system "
                        f"has less free, MiB (default {DEFAULT_MIN_FREE_MB:g}; a PostgreSQL "
                        "ledger: the server's disk, not watched here)")


def config_from_args(args: argparse.Namespace) -> Config:
    analytes = analyte_options(args)
    if analytes is not None and analytes.declared:
        check_declared(analytes.declared)
    return Config(site=args.site, zenoh=ZenohOptions.from_args(args), ledger_path=args.ledger,
                  status_period_s=args.status_period, clock=args.clock,
                  batch_size=args.batch_size, batch_interval_s=args.batch_interval,
                  queue_size=args.queue_size, history=not args.no_history,
                  checkpoint_dir=args.checkpoints, checkpoint_every_s=args.checkpoint_every,
                  signing=policy_from_args(args), accept_loss=args.accept_loss,
                  analytes=analytes, memory_limit_mb=args.memory_limit_mb,
                  min_free_mb=args.min_free_mb)


# -- writing ------------------------------------------------------------------------------

_STOP = object()


class Writer:
    """Drains the sample queue into the store in batches; publishes the head after each.

    Runs on its own thread (:meth:`run`).  ``on_committed(head_json)`` is called after
    every batch that changed the ledger.  ``disk`` holds a batch a full disk refuses.
    """

    def __init__(self, store: LedgerStore, samples: queue.Queue, runtime: ServiceRuntime,
                 config: Config, on_committed, on_gaps=None,
                 disk: DiskGuard | None = None) -> None:
        self.store, self.samples, self.runtime, self.config = store, samples, runtime, config
        self.on_committed = on_committed
        self.on_gaps, self.disk = on_gaps, disk
        self._missing = 0
        self.failed: BaseException | None = None
        self.batches = 0

    def _take_batch(self) -> tuple[list, bool]:
        """Block for the first sample, then gather until size or time bound (the window
        counted from the first sample's arrival)."""
        first = next_sample(self.samples, self.store)
        if first is _STOP:
            return [], True
        batch = [first]
        # the window runs from the first sample's arrival (a sample tuple's last item): a
        # sample that queued while the writer committed waits no longer than the window
        arrived = first[-1] if isinstance(first, tuple) else time.monotonic()
        deadline = arrived + self.config.batch_interval_s
        stop = False
        while len(batch) < self.config.batch_size:
            remaining = deadline - time.monotonic()
            try:
                item = next_sample(self.samples, self.store, remaining)
            except queue.Empty:
                break
            if item is _STOP:
                stop = True
                break
            batch.append(item)
        return batch, stop

    def run(self) -> None:
        assert self.runtime.status is not None
        stop = False
        try:
            while True:
                raw, stop = self._take_batch()
                if raw:
                    self._append(raw)
                if stop:
                    return
        except BaseException as exc:  # noqa: BLE001 - reported by the main thread
            self.failed = exc
            log(SERVICE, "writer failed", level="error", error=f"{type(exc).__name__}: {exc}")
            self.runtime.stopper and self.runtime.stopper.set()
            # room for the main thread's _STOP; the publishers' caches keep what is dropped
            # (a backup request met on the way is still served: the committed head is sound)
            while not stop and next_sample(self.samples, self.store) is not _STOP:
                pass

    def _append(self, raw: list) -> None:
        status = self.runtime.status
        assert status is not None
        items = [event_from_sample(key, payload, attachment)
                 for key, payload, attachment, _t in raw]
        result = self.disk.append(self.store, items) if self.disk else self.store.append(items)
        counts = result.counts
        status.add("received", len(items))
        for name in ("appended", "duplicate", "conflict", "rejected"):
            if counts[name]:
                status.add(name, counts[name])
        malformed = sum(1 for item in items if isinstance(item, Malformed))
        if malformed:
            status.add("malformed", malformed)
        if counts["rejected"] or counts["conflict"]:
            for item, outcome in zip(items, result.outcomes):
                if outcome.status in ("rejected", "conflict"):
                    log(SERVICE, "quarantined", level="warning",
                        source=getattr(item, "source", ""), seq=getattr(item, "seq", ""),
                        reason=outcome.reason)
        now = time.monotonic()
        latency_ms = max((now - t) * 1e3 for *_x, t in raw)
        status.add("batches")
        self.batches += 1
        self.last_latency_ms = latency_ms
        if counts["appended"] or counts["rejected"] or counts["conflict"]:
            self.on_committed()
        if self.disk is not None:
            self.disk.check()
        missing = sum(st.missing for st in self.store.streams())
        if missing != self._missing:
            self._missing = missing
            if self.on_gaps is not None:
                self.on_gaps()


# -- reading ------------------------------------------------------------------------------


class Reader:
    """Serves queries from a queue on its own thread, so Zenoh's threads never wait on reads."""

    def __init__(self, store: LedgerStore, site: str, chunk_bytes: int) -> None:
        self.store, self.site, self.chunk_bytes = store, site, chunk_bytes
        self.queries: queue.Queue = queue.Queue()
        self.served = 0
        self.errors = 0

    def run(self) -> None:
        while True:
            item = self.queries.get()
            if item is _STOP:
                return
            what, query = item
            with query:
                try:
                    self._serve(what, query)
                    self.served += 1
                except (LedgerError, ValueError, KeyError, TypeError) as exc:
                    self.errors += 1
                    query.reply_err(f"{type(exc).__name__}: {exc}".encode())

    def _params(self, query) -> dict[str, Any]:
        payload = query.payload
        if payload is None:
            return {}
        text = payload.to_bytes()
        if not text:
            return {}
        params = json.loads(text)
        if not isinstance(params, dict):
            raise ValueError("query payload must be a JSON object")
        return params

    def _serve(self, what: str, query) -> None:
        params = self._params(query)
        key = query_key(self.site, what)
        limit = _opt_int(params.get("limit"))
        if what == "events":
            rows = self.store.read(int(params.get("start", 0)), _opt_int(params.get("stop")),
                                   types=params.get("types"), sources=params.get("sources"))
            self._reply_records(query, key, itertools.islice(rows, limit))
        elif what == "as_of":
            after = params.get("after")
            rows = self.store.as_of(int(params["valid_time_ns"]), int(params["known_time_ns"]),
                                    types=params.get("types"),
                                    after=None if after is None else (int(after[0]), int(after[1])))
            pinned = _opt_int(params.get("max_global_seq"))
            if pinned is not None:
                rows = (r for r in rows if r.global_seq <= pinned)
            self._reply_records(query, key, itertools.islice(rows, limit))
        elif what == "stats":
            self._reply_json(query, key, stats_to_json(self.store.stats()))
        elif what == "head":
            self._reply_json(query, key, head_to_json(self.store.head()))
        elif what == "gaps":
            gaps = self.store.gaps(open_only=bool(params.get("open_only", False)))
            self._reply_json(query, key, [gap_to_json(g) for g in gaps])
        elif what == "quarantine":
            self._reply_json(query, key, [quarantine_to_json(q) for q in self.store.quarantine()])
        elif what == "streams":
            self._reply_json(query, key, [stream_to_json(s) for s in self.store.streams()])
        else:  # pragma: no cover - only declared keys arrive
            raise ValueError(f"unknown query {what!r}")

    @staticmethod
    def _reply_json(query, key: str, data) -> None:
        query.reply(key, json.dumps(data).encode())

    def _reply_records(self, query, key: str, rows) -> None:
        index, total, pending, size = 0, 0, [], 0
        for row in rows:
            pending.append(row)
            size += len(row.payload) + 128
            if size >= self.chunk_bytes:
                total += len(pending)
                query.reply(key, encode_records(pending),
                            attachment=CHUNK_ATTACHMENT.pack(index, 0, total))
                index, pending, size = index + 1, [], 0
        total += len(pending)
        query.reply(key, encode_records(pending), attachment=CHUNK_ATTACHMENT.pack(index, 1, total))


def _opt_int(value: object) -> int | None:
    return None if value is None else int(value)  # type: ignore[arg-type]


def _write_holder(config: Config) -> LedgerHolder | None:
    """Leave the holder file beside the ledger file (none for an in-memory or a PostgreSQL
    ledger: readers open a PostgreSQL URL themselves)."""
    if config.file_path is None:
        return None
    holder = LedgerHolder(site=config.site, pid=os.getpid(),
                          endpoints=reader_endpoints(config.zenoh.to_config()),
                          started_ns=time.time_ns(), host=this_host())
    try:
        path = write_holder(config.ledger_path, holder)
    except OSError as exc:
        log(SERVICE, "cannot write the holder file: read commands given the ledger file "
            "will fail on its lock", level="warning", error=str(exc))
        return None
    log(SERVICE, "holder file written", path=str(path), endpoints=list(holder.endpoints))
    if not holder.endpoints:
        log(SERVICE, "no fixed endpoint to read the ledger through: read commands given the "
            "file cannot reach this service (give --listen or --connect)", level="warning")
    return holder


# -- main ---------------------------------------------------------------------------------


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the ledger service until SIGINT/SIGTERM (or ``stopper``); return an exit code."""
    try:
        if config.file_path is not None:
            Path(config.file_path).parent.mkdir(parents=True, exist_ok=True)
        store = open_ledger(config.ledger_path, clock_by_name(config.clock),
                            signing=config.signing, accept_loss=config.accept_loss,
                            analytes=config.analytes, memory_limit_mb=config.memory_limit_mb)
    except (LedgerError, OSError, ValueError) as exc:
        log(SERVICE, "cannot open the ledger", level="error",
            ledger=describe_ledger(config.ledger_path), error=str(exc).splitlines()[0])
        return 2
    samples: queue.Queue = queue.Queue(maxsize=config.queue_size)
    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name="writer",
                             status_period_s=config.status_period_s, stopper=stopper)
    error_keys = ("rejected", "conflict", "malformed", "misses_reported", "writer_errors")
    with store:
        runtime.open(rate_of="appended", backlog=samples.qsize, error_keys=error_keys,
                     announce=False)
        try:
            return _serve(config, store, samples, runtime)
        finally:
            runtime.close()


def _serve(config: Config, store: LedgerStore, samples: queue.Queue,
           runtime: ServiceRuntime) -> int:
    session = runtime.session
    status = runtime.status
    assert status is not None and runtime.stopper is not None
    head_publisher = session.declare_publisher(head_key(config.site),
                                               congestion_control=zenoh.CongestionControl.BLOCK)

    def publish_head() -> None:
        head_publisher.put(json.dumps(head_to_json(store.head())).encode())

    status_publisher = publish_status(session, config.site, SERVICE, status)
    disk = DiskGuard(config.file_path, config.min_free_mb, status, runtime.stopper)
    disk.check(force=True)
    repair = GapRepair(session, config.site, store, samples, runtime)
    writer = Writer(store, samples, runtime, config, publish_head, on_gaps=repair.check,
                    disk=disk)
    reader = Reader(store, config.site, config.chunk_bytes)
    threads = [threading.Thread(target=writer.run, name="ledger-writer", daemon=True),
               threading.Thread(target=reader.run, name="ledger-reader", daemon=True)]
    for thread in threads:
        thread.start()

    queryables = [
        session.declare_queryable(query_key(config.site, what),
                                  lambda q, what=what: reader.queries.put((what, q)))
        for what in QUERIES
    ] + [session.declare_queryable(query_key(config.site, "backup"), lambda q: samples.put(
        BackupRequest(q, query_key(config.site, "backup"))))]
    if config.postgres:
        runtime.log("PostgreSQL ledger: readers open it themselves (read-only role "
                    "stockpile_reader); the server watches its own disk; back it up with "
                    "pg_basebackup or pg_dump", ledger=describe_ledger(config.ledger_path))

    def on_sample(sample) -> None:
        attachment = sample.attachment
        samples.put((str(sample.key_expr), sample.payload.to_bytes(),
                     None if attachment is None else attachment.to_bytes(), time.monotonic()))

    def on_miss(miss) -> None:
        status.add("misses_reported", miss.nb)
        log(SERVICE, "samples missed", level="warning", publisher=str(miss.source), nb=miss.nb,
            note="recorded as a gap when the source's next event arrives")

    history = zext.HistoryConfig(detect_late_publishers=True) if config.history else None
    subscriber = SamplePump(lambda handler: zext.declare_advanced_subscriber(
        session, f"stockpile/{config.site}/@v1/**", handler, history=history,
        subscriber_detection=True), on_sample, capacity=config.queue_size, name="ledger-pump",
        on_error=lambda exc: runtime.log("sample not queued", level="error", error=str(exc)))
    miss_listener = subscriber.subscriber.sample_miss_listener(on_miss)
    recall = CacheRecall.of_events(session, config.site, on_sample, SERVICE, config.history)
    runtime.log("serving", ledger=describe_ledger(config.ledger_path),
                head=store.head().global_seq,
                subscribe=f"stockpile/{config.site}/@v1/**",
                queries=query_key(config.site, "*"), head_key=head_key(config.site))
    publish_head()
    holder = _write_holder(config)
    checkpoints = Checkpointer(
        store, session, config.site, config.zenoh.certificate,
        config.checkpoint_dir or (None if config.file_path is None
                                  else config.file_path + ".checkpoints"))
    runtime.announce()
    try:
        while not runtime.stopper.wait(config.checkpoint_every_s):
            checkpoints.take()
    finally:
        if holder is not None:
            remove_holder(config.ledger_path, os.getpid())
    # clean stop: no new samples, drain what was queued, then stop the threads
    recall.close()
    miss_listener.undeclare()
    subscriber.undeclare()
    repair.close()
    samples.put(_STOP)
    threads[0].join()
    for q in queryables:
        q.undeclare()
    reader.queries.put(_STOP)
    threads[1].join(timeout=5.0)
    head_publisher.undeclare()
    status.on_status = None
    status_publisher.undeclare()
    if writer.failed is not None:
        runtime.log("stopping after a writer failure", level="error",
                    error=f"{type(writer.failed).__name__}: {writer.failed}")
        return 2
    checkpoints.take()
    checkpoints.close()
    runtime.log("committed", head=store.head().global_seq, batches=writer.batches)
    return 0

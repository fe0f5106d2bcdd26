"""``stockpile record`` and ``stockpile service recorder``: live events to MCAP.

Data flow::

    zenoh  stockpile/<site>/@v1/**  --AdvancedSubscriber callback-->  SampleQueue (bounded)
        --writer thread: identity, site-clock log time, duplicates, gaps-->  EventWriter (MCAP)
                                                  flush every second; rotate by size or time

- **No silent loss.** The subscriber is a ``zenoh.ext`` AdvancedSubscriber with
  history (``detect_late_publishers``), like the ledger's: a recorder started after
  the publishers asks their caches for what they published before.  A jump in a
  source's sequence is written to the file as a ``stockpile.gap`` metadata record
  (and logged); Zenoh's own miss reports become ``stockpile.miss`` records; the
  gaps still open at the end are listed in the closing ``stockpile.recording``
  record.  A sample that is not an event (no identity attachment, an unknown type)
  is kept as a ``stockpile.malformed/<n>`` attachment.  Duplicates (history that
  overlaps live samples) are dropped and counted.
- **Backpressure.** The callback only queues the raw sample; when the queue is full
  it blocks, which backs up Zenoh and, through congestion control BLOCK, the
  publishers: nothing is dropped.
- **Crash safety.** The writer closes the chunk in progress and hands the file to
  the OS every ``flush_interval_s`` (1 s), so a recorder killed with SIGKILL loses at
  most that much; ``stockpile record --recover BROKEN FIXED`` salvages the rest
  (:mod:`replay.recover`).  SIGINT/SIGTERM close the file properly.
- **Checkpoints.** The ledger service's signed checkpoints of the chain head
  (``stockpile/<site>/@ledger/checkpoint``) are written, byte for byte, on their own
  schema-less JSON channel (:meth:`EventWriter.write_checkpoint`), so that a recorded
  session can prove later that a ledger still holds what it held
  (``stockpile ledger verify --checkpoint SESSION.mcap``).
- **Signatures.** A signed event (a version-2 attachment with the producer's key id
  and signature) has its signature written on the companion signature channel just
  before the event (:meth:`EventWriter.write_signature`).  Signed samples leave the hot
  loop for :meth:`Recorder._write_sample`; unsigned ones pay nothing more than before.
- **Time.** ``log_time`` is the receive time in site-clock time (``--clock wall``:
  the machine's UTC clock; ``--clock site``: the site's ``clock`` events, as the
  scanner service does), never going backwards, across the files of a split too.

The recorder's Zenoh-free parts (file naming, the bounded queue, sequence bookkeeping)
are in :mod:`replay.record_parts`.
"""

from __future__ import annotations

import argparse
import gc
import json
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import zenoh.ext as zext

from common.options import add_clock, add_duration
from ledger.checkpoint import checkpoint_topic
from replay.mcap_format import DEFAULT_CHUNK_BYTES, MASK64, SEQ_LOW_MASK, library_id
from replay.mcap_writer import EventWriter
from replay.record_parts import (
    DUPLICATE,
    WAKE,
    Counters,
    FileNamer,
    SampleQueue,
    StreamTracker,
)
from schemas.events import EVENT_TYPES, decode_signed_attachment, parse_key_expr, site_key_expr
from schemas.times import NS_PER_S
from services.pump import SamplePump
from services.resubscribe import CacheRecall
from services.service import ServiceRuntime, SiteTime, Stopper, ZenohOptions, log

SERVICE = "recorder"
DEFAULT_FLUSH_INTERVAL_S = 1.0
DEFAULT_QUEUE_SIZE = 100_000


@dataclass(frozen=True)
class Config:
    """Options of the recorder.

    Attributes
    ----------
    out : str
        The MCAP file.  With a split, files are ``<stem>-0000<suffix>``,
        ``<stem>-0001<suffix>``, ... continuing after any that exist.
    keys : tuple of str
        Key expressions to record (default: every event of the site).
    duration_s : float or None
        Stop after this many wall seconds (default: on SIGINT/SIGTERM).
    split_size_bytes, split_duration_s : int or float or None
        Start a new file when the current one holds this many bytes or has been
        open this many wall seconds.
    clock : str
        ``wall`` or ``site``: where log times come from.
    history : bool
        Ask the publishers' caches for what they published before this start.
    flush_interval_s : float
        Longest time a received event stays only in memory, seconds.
    """

    site: str
    zenoh: ZenohOptions
    out: str
    keys: tuple[str, ...] = ()
    duration_s: float | None = None
    split_size_bytes: int | None = None
    split_duration_s: float | None = None
    clock: str = "wall"
    history: bool = True
    flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S
    chunk_size_bytes: int = DEFAULT_CHUNK_BYTES
    queue_size: int = DEFAULT_QUEUE_SIZE
    status_period_s: float = 5.0

    def __post_init__(self) -> None:
        if self.clock not in ("wall", "site"):
            raise ValueError(f"clock must be 'wall' or 'site', got {self.clock!r}")
        if self.split_size_bytes is not None and self.split_duration_s is not None:
            raise ValueError("give --split-size or --split-duration, not both")
        for name in ("duration_s", "split_duration_s", "split_size_bytes"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        if not self.flush_interval_s > 0:
            raise ValueError(f"flush interval must be > 0 s, got {self.flush_interval_s}")
        if self.queue_size < 1:
            raise ValueError(f"queue size must be >= 1, got {self.queue_size}")

    @property
    def split(self) -> bool:
        return self.split_size_bytes is not None or self.split_duration_s is not None

    @property
    def key_exprs(self) -> tuple[str, ...]:
        return self.keys or (site_key_expr(self.site),)


def add_recording_arguments(parser: argparse.ArgumentParser) -> None:
    """Options ``stockpile record`` and ``stockpile service recorder`` share."""
    parser.add_argument("--keys", nargs="+", metavar="EXPR", default=None,
                        help="key expressions to record (default stockpile/<site>/@v1/**)")
    add_duration(parser, "--duration",
                 help="stop after this much wall time, with a unit: 90s, 15min ... (default: on "
                 "SIGINT/SIGTERM)")
    split = parser.add_mutually_exclusive_group()
    split.add_argument("--split-size", type=int, metavar="BYTES",
                       help="start a new file every BYTES bytes (files OUT-0000.mcap, ...)")
    add_duration(split, "--split-duration",
                 help="start a new file every this much wall time, with a unit: 15min, 1h ...")
    add_clock(parser, events_as="site",
              help="log time from the wall clock or the site's clock events (simulated yard)")
    parser.add_argument("--no-history", action="store_true",
                        help="do not ask publishers' caches for earlier events on start")
    parser.add_argument("--flush-interval", type=float, default=DEFAULT_FLUSH_INTERVAL_S,
                        metavar="S", help="close a chunk and flush the file at least every S "
                        f"seconds (default {DEFAULT_FLUSH_INTERVAL_S:g}): what a crash can lose")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``stockpile service recorder``'s own options (the shared ones come from service_cli)."""
    parser.add_argument("--out", required=True, metavar="PATH",
                        help="the MCAP file (with a split: PATH-0000.mcap, PATH-0001.mcap, ...)")
    add_recording_arguments(parser)


def config_from_args(args: argparse.Namespace) -> Config:
    return Config(site=args.site, zenoh=ZenohOptions.from_args(args), out=args.out,
                  keys=tuple(args.keys or ()), duration_s=args.duration,
                  split_size_bytes=args.split_size, split_duration_s=args.split_duration,
                  clock=args.clock, history=not args.no_history,
                  flush_interval_s=args.flush_interval, status_period_s=args.status_period)


# -- the recorder ----------------------------------------------------------------------------


class _Checkpoint:
    __slots__ = ("key", "payload", "arrived_s")

    def __init__(self, key: str, payload: bytes, arrived_s: float) -> None:
        self.key, self.payload, self.arrived_s = key, payload, arrived_s


class _Miss:
    __slots__ = ("publisher", "count", "arrived_s")

    def __init__(self, publisher: str, count: int, arrived_s: float) -> None:
        self.publisher, self.count, self.arrived_s = publisher, count, arrived_s


class Recorder:
    """Queue -> writer thread -> MCAP files, independent of Zenoh.

    The Zenoh callbacks call :meth:`offer` and :meth:`note_miss`; :meth:`run` is the
    writer thread; :meth:`close` ends the input, after which ``run`` drains what is
    queued, closes the file and returns.

    Parameters
    ----------
    config : Config
    site_time : SiteTime
        Maps a local ``time.monotonic()`` reading to site time.
    status : object with ``add(name, n)``
    """

    def __init__(self, config: Config, site_time: SiteTime, status=None,
                 logger: Callable[..., None] | None = None) -> None:
        self.config = config
        self.site_time = site_time
        self.status = status if status is not None else Counters()
        self._log = logger or (lambda msg, level="info", **f: log(SERVICE, msg, level=level, **f))
        self.queue = SampleQueue(config.queue_size)
        self.namer = FileNamer(config.out, config.split)
        self.streams = StreamTracker()
        self.files: list[str] = []
        self.failed: BaseException | None = None
        self._file: EventWriter | None = None
        self._file_opened_s = 0.0
        self._file_started_ns = 0
        self._last_log_ns: int | None = None
        self._keys: dict[str, tuple[str, str] | str] = {}
        #: (key, epoch) -> (channel id in the current file, the stream's [highest seq])
        self._fast: dict[tuple[str, int], tuple[int, list[int]]] = {}
        self._stamped_by_valid = 0
        #: called (from the writer thread) when writing fails, e.g. to stop the service
        self.on_failure: Callable[[], None] | None = None

    # -- the callback side --------------------------------------------------------------

    def offer(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        """Queue one received sample (blocks while the queue is full)."""
        self.queue.put((key, payload, attachment, time.monotonic()))

    def offer_checkpoint(self, key: str, payload: bytes) -> None:
        """Queue one checkpoint the ledger service published on ``key``."""
        self.queue.put(_Checkpoint(key, payload, time.monotonic()))

    def note_miss(self, publisher: str, count: int) -> None:
        """Zenoh reported ``count`` samples of ``publisher`` missed."""
        self.queue.put(_Miss(publisher, count, time.monotonic()))

    def close(self) -> None:
        self.queue.close()

    # -- the writer thread ------------------------------------------------------------------

    def run(self) -> None:
        try:
            self._wait_for_clock()
            self._open_next()
            next_flush = time.monotonic() + self.config.flush_interval_s
            while True:
                batch = self.queue.drain(max(0.0, next_flush - time.monotonic()))
                if batch:
                    self._write_batch(batch)
                now = time.monotonic()
                if now >= next_flush:
                    assert self._file is not None
                    self._file.flush()
                    next_flush = now + self.config.flush_interval_s
                if self._rotation_due(now):
                    self._close_file()
                    self._open_next()
                if self.queue.closed and not len(self.queue):
                    break
            self._close_file()
        except BaseException as exc:  # noqa: BLE001 - reported by the main thread
            self.failed = exc
            self._log("writer failed", level="error", error=f"{type(exc).__name__}: {exc}")
            self._abandon()
            if self.on_failure is not None:
                self.on_failure()

    def _wait_for_clock(self) -> None:
        """In site mode, hold the samples until the site clock's speed is known."""
        while not self.site_time.ready.wait(0.1):
            if self.queue.closed:
                self._log("no site clock before the end: log times are the events' valid "
                          "times", level="warning")
                return
        if self.site_time.mode == "site":
            self._log("site clock ready", speed=round(self.site_time.speed, 3))

    def _open_next(self) -> None:
        path = self.namer.next()
        self._file = EventWriter(path, chunk_size_bytes=self.config.chunk_size_bytes)
        self._fast.clear()  # channel ids are per file
        self._file_opened_s = time.monotonic()
        self._file_started_ns = time.time_ns()
        self.files.append(str(path))
        self.status.add("files")
        self._log("recording", file=str(path))

    def _rotation_due(self, now: float) -> bool:
        cfg, file = self.config, self._file
        if file is None or file.messages == 0:
            return False
        if cfg.split_size_bytes is not None and file.bytes_written >= cfg.split_size_bytes:
            return True
        return cfg.split_duration_s is not None and now - self._file_opened_s >= cfg.split_duration_s

    def _close_file(self) -> None:
        file = self._file
        if file is None:
            return
        self._file = None
        meta = {"site": self.config.site, "keys": list(self.config.key_exprs),
                "clock": self.config.clock, "recorder": library_id(),
                "wall_start_ns": self._file_started_ns, "wall_end_ns": time.time_ns(),
                "messages": file.messages, "malformed": file.malformed,
                "checkpoints": file.checkpoints, "signatures": file.signatures,
                "log_time_from_valid_time": self._stamped_by_valid,
                "open_gaps": self.streams.open_gaps()}
        file.close(("stockpile.recording", meta))
        self._log("file closed", file=file.path, messages=file.messages, malformed=file.malformed,
                  bytes=Path(file.path).stat().st_size)

    def _abandon(self) -> None:
        """After a failure: hand what was written to the OS; recover() can read it."""
        file, self._file = self._file, None
        if file is not None:
            try:
                file.flush()
            except BaseException:  # noqa: BLE001 - already failing
                pass

    # -- writing --------------------------------------------------------------------------

    def _log_times(self, batch: list) -> tuple[int, float] | None:
        """(site ns at the batch's reference arrival, site ns per local second), if known.

        Site time is linear in local time between clock fits, so two numbers per batch
        give every sample's log time.
        """
        st = self.site_time
        if not st.ready.is_set():
            return None
        ref = batch[-1] if batch[-1] is not WAKE or len(batch) == 1 else batch[-2]
        ref_s = ref[3] if type(ref) is tuple else getattr(ref, "arrived_s", time.monotonic())
        return st.at(ref_s), st.speed * NS_PER_S

    def _write_batch(self, batch: list) -> None:
        """Write a drained batch.  The loop is the recorder's hot path: the common case
        (a known key, a readable unsigned attachment, the next sequence number) is
        inline; the rest (signed events too) goes through :meth:`_write_sample`."""
        timing = self._log_times(batch)
        ref = batch[-1] if batch[-1] is not WAKE or len(batch) == 1 else batch[-2]
        ref_s = ref[3] if type(ref) is tuple else getattr(ref, "arrived_s", time.monotonic())
        base_ns, ns_per_s = timing if timing is not None else (0, 0.0)
        file = self._file
        assert file is not None
        fast_path, add_message = self._fast, file.add_message
        last = self._last_log_ns if self._last_log_ns is not None else -(1 << 63)
        written = fast = 0
        for item in batch:
            if type(item) is not tuple:
                if item is not WAKE:
                    self._last_log_ns = last if last > -(1 << 63) else None
                    if type(item) is _Checkpoint:
                        self._write_checkpoint(item, timing, ref_s)
                    else:
                        self._write_miss(item, timing, ref_s)
                    if self._last_log_ns is not None:
                        last = self._last_log_ns
                continue
            key, payload, attachment, arrived_s = item
            if attachment is not None and timing is not None:
                try:
                    epoch, seq, valid_ns, signer, _signature = decode_signed_attachment(
                        attachment)
                except (ValueError, struct.error):
                    epoch = -1
                known = fast_path.get((key, epoch))
                if known is not None and signer is None and known[1][0] + 1 == seq \
                        and seq <= SEQ_LOW_MASK and valid_ns >= 0:
                    channel, cell = known
                    cell[0] = seq
                    log_ns = base_ns + int((arrived_s - ref_s) * ns_per_s)
                    if log_ns < last:
                        log_ns = last
                    last = log_ns
                    add_message(channel, log_ns & MASK64, payload, valid_ns, seq)
                    fast += 1
                    continue
            self._last_log_ns = last if last > -(1 << 63) else None
            log_ns = None if timing is None else base_ns + int((arrived_s - ref_s) * ns_per_s)
            written += self._write_sample(file, key, payload, attachment, log_ns)
            if self._last_log_ns is not None:
                last = self._last_log_ns
        self._last_log_ns = last if last > -(1 << 63) else None
        file.messages += fast
        if written + fast:
            self.status.add("recorded", written + fast)

    def _monotone(self, log_ns: int) -> int:
        last = self._last_log_ns
        if last is not None and log_ns < last:
            log_ns = last
        self._last_log_ns = log_ns
        return log_ns

    def _identity(self, key: str) -> tuple[str, str] | str:
        known = self._keys.get(key)
        if known is None:
            try:
                _site, type_name, source = parse_key_expr(key)
                known = (type_name, source) if type_name in EVENT_TYPES else \
                    f"unknown_type: {type_name!r}"
            except ValueError as exc:
                known = f"bad_key: {exc}"
            self._keys[key] = known
        return known

    def _write_sample(self, file: EventWriter, key: str, payload: bytes,
                      attachment: bytes | None, log_ns: int | None) -> int:
        ident = self._identity(key)
        reason = ident if type(ident) is str else None
        if reason is None:
            if attachment is None:
                reason = "bad_attachment: missing"
            else:
                try:
                    epoch, seq, valid_ns, signer, signature = decode_signed_attachment(
                        attachment)
                except (ValueError, struct.error) as exc:
                    reason = f"bad_attachment: {exc}"
        if reason is not None:
            stamp = self._monotone(log_ns if log_ns is not None else (self._last_log_ns or 0))
            file.add_malformed(key, payload, attachment, reason, stamp)
            self.status.add("malformed")
            self._log("malformed sample kept as an attachment", level="warning", key=key,
                      reason=reason)
            return 0
        type_name, source = ident  # type: ignore[misc]
        seen, gap = self.streams.observe(source, epoch, seq)
        if seen == DUPLICATE:
            self.status.add("duplicates")
            return 0
        if log_ns is None:
            log_ns = valid_ns
            self._stamped_by_valid += 1
        log_ns = self._monotone(log_ns)
        if gap is not None:
            self._record_gap(file, source, epoch, gap, log_ns)
        file.write(key, type_name, source, epoch, seq, valid_ns, payload, log_ns, signer,
                   signature)
        if seq <= SEQ_LOW_MASK:  # the next ones of this key and epoch take the fast path
            self._fast[(key, epoch)] = (file.channel_id(key, type_name, source, epoch),
                                        self.streams.cell(source, epoch))
        return 1

    def _record_gap(self, file: EventWriter, source: str, epoch: int, gap: tuple[int, int],
                    log_ns: int) -> None:
        self.status.add("gaps_opened")
        file.add_metadata("stockpile.gap", {"source": source, "epoch": str(epoch),
                                            "first_seq": str(gap[0]), "last_seq": str(gap[1]),
                                            "log_time_ns": str(log_ns)})
        self._log("gap opened", level="warning", source=source, epoch=epoch, first_seq=gap[0],
                  last_seq=gap[1], missing=gap[1] - gap[0] + 1)

    def _write_checkpoint(self, item: _Checkpoint, timing, ref_s: float) -> None:
        assert self._file is not None
        log_ns = self._last_log_ns or 0
        if timing is not None:
            log_ns = timing[0] + int((item.arrived_s - ref_s) * timing[1])
        self._file.write_checkpoint(item.key, item.payload, self._monotone(log_ns))
        self.status.add("checkpoints")
        try:
            global_seq = json.loads(item.payload)["global_seq"]
        except (ValueError, KeyError, TypeError):
            self._log("checkpoint recorded, but it is not a checkpoint's JSON", level="warning",
                      key=item.key, bytes=len(item.payload))
            return
        self._log("checkpoint recorded", key=item.key, global_seq=global_seq)

    def _write_miss(self, miss: _Miss, timing, ref_s: float) -> None:
        assert self._file is not None
        log_ns = self._last_log_ns or 0
        if timing is not None:
            log_ns = timing[0] + int((miss.arrived_s - ref_s) * timing[1])
        self.status.add("misses_reported", miss.count)
        self._file.add_metadata("stockpile.miss", {"publisher": miss.publisher,
                                                   "missed": str(miss.count),
                                                   "log_time_ns": str(log_ns)})
        self._log("samples missed", level="warning", publisher=miss.publisher, nb=miss.count,
                  note="a gap in the source's sequence is recorded when its next event arrives")


# -- main ----------------------------------------------------------------------------------


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Record until SIGINT/SIGTERM, ``stopper`` or ``config.duration_s``; return an exit code."""
    try:
        continued_in = FileNamer(config.out, config.split).check()
    except OSError as exc:
        log(SERVICE, "cannot record", level="error", out=config.out, error=str(exc))
        return 2
    if continued_in is not None:
        log(SERVICE, "output exists; continuing in a new part (nothing overwritten)",
            level="warning", out=config.out, part=str(continued_in))
    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name=Path(config.out).stem,
                             status_period_s=config.status_period_s, stopper=stopper)
    site_time = SiteTime("site" if config.clock == "site" else "wall")
    recorder: Recorder | None = None
    error_keys = ("malformed", "misses_reported", "gaps_opened")
    runtime.open(rate_of="recorded", backlog=lambda: len(recorder.queue) if recorder else 0,
                 error_keys=error_keys, announce=False)
    try:
        recorder = Recorder(config, site_time, runtime.status)
        return _record(config, runtime, recorder, site_time)
    finally:
        runtime.close()


def _record(config: Config, runtime: ServiceRuntime, recorder: Recorder,
            site_time: SiteTime) -> int:
    assert runtime.stopper is not None
    session = runtime.session
    site_time.follow(session, config.site)
    recorder.on_failure = runtime.stopper.set
    writer = threading.Thread(target=recorder.run, name="recorder-writer", daemon=True)
    writer.start()

    def on_sample(sample) -> None:
        attachment = sample.attachment
        recorder.offer(str(sample.key_expr), sample.payload.to_bytes(),
                       None if attachment is None else attachment.to_bytes())

    def on_miss(miss) -> None:
        recorder.note_miss(str(miss.source), int(miss.nb))

    history = zext.HistoryConfig(detect_late_publishers=True) if config.history else None
    subscribers, listeners = [], []
    for key in config.key_exprs:
        subscriber = SamplePump(
            lambda handler, key=key: zext.declare_advanced_subscriber(
                session, key, handler, history=history, subscriber_detection=True),
            on_sample, name="recorder-pump")
        subscribers.append(subscriber)
        listeners.append(subscriber.subscriber.sample_miss_listener(on_miss))
    # a publisher back after a router outage: ask its cache (services.resubscribe)
    recalls = [CacheRecall(session, key, on_sample, on_recall=lambda token, n: runtime.log(
        "publisher back: cache asked", token=token, replies=n))
        for key in config.key_exprs] if config.history else []
    checkpoints = session.declare_subscriber(
        checkpoint_topic(config.site),
        lambda sample: recorder.offer_checkpoint(str(sample.key_expr), sample.payload.to_bytes()))
    # what start-up built lives as long as the process: keep the cyclic GC from walking
    # it again and again while samples stream through
    gc.collect()
    gc.freeze()
    runtime.log("serving", subscribe=",".join((*config.key_exprs, checkpoint_topic(config.site))),
                out=config.out, clock=config.clock)
    runtime.announce()
    runtime.stopper.wait(config.duration_s)
    # clean stop: no new samples, then drain the queue and close the file
    for recall in recalls:
        recall.close()
    for listener in listeners:
        listener.undeclare()
    for subscriber in subscribers:
        subscriber.undeclare()
    checkpoints.undeclare()
    recorder.close()
    writer.join()
    site_time.close()
    if recorder.failed is not None:
        runtime.log("stopping after a writer failure", level="error",
                    error=f"{type(recorder.failed).__name__}: {recorder.failed}")
        return 2
    runtime.log("recorded", files=len(recorder.files), last=recorder.files[-1] if recorder.files else "")
    return 0

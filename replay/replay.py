"""``stockpile replay``: an MCAP file back onto Zenoh, or straight into a ledger.

Into a ledger (:func:`replay_to_ledger`): messages are appended in file order (the
order they were recorded or ledgered), in batches, as fast as the ledger takes them.
With ``preserve_recorded_time`` (the default) each event's recorded time is the
message's ``log_time``, so a ledger exported to MCAP and replayed into an empty
ledger is the same ledger: same global order, same recorded times, same hash chain,
and as-of-known queries answer exactly as the original did.  A signed event keeps its
signer and signature (from the file's signature channel), so a ledger that requires
signatures checks it as it would have live.  Samples the recorder kept as malformed go
to the ledger's quarantine, as they would have live.

Onto Zenoh (:func:`replay_publish`): byte-identical payloads with the original
identity attachments (epoch, sequence, valid time; a signed event's signer and
signature in a version-2 attachment) on the original keys, through
the same AdvancedPublishers the yard's producers use (cache, congestion control
BLOCK), so a ledger fed twice from the same file adds nothing the second time.

Pacing (``rate``; ``None`` = as fast as possible): messages go out in file order;
each is due when the replay clock reaches its ``publish_time`` (valid time), the
clock running at ``rate`` site seconds per wall second from the first message.  A
message whose valid time is earlier than one already sent (a late assay) goes out
at once, right after its predecessor in the file.

``start_offset_s`` / ``until_s`` select by log time, in seconds after the start of
the file (the later of its first message's log and valid times); ``topics`` keeps the topics under any of the given key expressions.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

from common.progress import Progress

from replay.mcap_entries import Entry, MalformedSample, read_entries
from replay.mcap_scan import McapScan, ScanReport
from schemas.events import Event, encode_attachment, event_from_sample, key_expr
from schemas.times import NS_PER_S
from services.service import declare_ledger_publisher

DEFAULT_BATCH = 5_000


def _offset_ns(seconds: float | None) -> int | None:
    return None if seconds is None else int(round(seconds * NS_PER_S))


def _fraction(scan: McapScan) -> float:
    return scan.position / scan.size if scan.size else 1.0


# -- into a ledger ------------------------------------------------------------------------


@dataclass
class LedgerReplay:
    """What a replay into a ledger did."""

    path: str
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(
        ("appended", "duplicate", "conflict", "rejected"), 0))
    events: int = 0  # events read from the file and offered to the ledger
    malformed: int = 0  # recorded malformed samples sent to the quarantine
    signed: int = 0  # of the events, how many carried a signature
    first_log_ns: int | None = None  # the later of the first event's log and valid times
    last_log_ns: int | None = None
    wall_s: float = 0.0
    head_global_seq: int = -1
    scan: ScanReport | None = None

    @property
    def site_span_s(self) -> float:
        """Site time the replayed events cover (start to last log time), seconds."""
        if self.first_log_ns is None or self.last_log_ns is None:
            return 0.0
        return (self.last_log_ns - self.first_log_ns) / NS_PER_S

    @property
    def speed_up(self) -> float:
        """Site seconds replayed per wall second."""
        return self.site_span_s / self.wall_s if self.wall_s > 0 else float("inf")


def replay_to_ledger(path: str | Path, store, *, preserve_recorded_time: bool = True,
                     topics: Callable[[str], bool] | None = None,
                     start_offset_s: float | None = None, until_s: float | None = None,
                     batch_size: int = DEFAULT_BATCH,
                     progress: Progress | None = None) -> LedgerReplay:
    """Append a file's events to ``store`` (a :class:`ledger.store.LedgerStore`)."""
    result = LedgerReplay(str(path))
    started = time.monotonic()
    with McapScan(path) as scan:
        result.scan = scan.report
        if progress is not None and progress.total is None and topics is None \
                and start_offset_s is None and until_s is None:
            progress.total = scan.report.total
        malformed: list[MalformedSample] = []
        batch: list = []
        for entry in read_entries(scan, topics=topics, start_offset_ns=_offset_ns(start_offset_s),
                                  until_offset_ns=_offset_ns(until_s), malformed=malformed):
            if malformed:
                batch.extend(_quarantined(malformed, result))
            batch.append(Event(entry.type, entry.source, entry.epoch, entry.seq,
                               entry.valid_time_ns, entry.payload,
                               entry.log_time_ns if preserve_recorded_time else None,
                               entry.signer, entry.signature))
            result.events += 1
            if entry.signer is not None:
                result.signed += 1
            if result.first_log_ns is None:
                result.first_log_ns = max(entry.log_time_ns, entry.valid_time_ns)
            result.last_log_ns = entry.log_time_ns
            if len(batch) >= batch_size:
                _append(store, batch, result)
                batch = []
                if progress is not None:
                    progress.update_to(result.events, fraction=_fraction(scan))
        batch.extend(_quarantined(malformed, result))
        if batch:
            _append(store, batch, result)
    result.head_global_seq = store.head().global_seq
    result.wall_s = time.monotonic() - started
    if progress is not None:
        progress.update_to(result.events)
    return result


def _quarantined(malformed: list[MalformedSample], result: LedgerReplay) -> list:
    """Recorded malformed samples, as the ledger service would have received them."""
    out = [event_from_sample(m.key, m.payload, m.attachment) for m in malformed]
    result.malformed += len(out)
    malformed.clear()
    return out


def _append(store, batch: list, result: LedgerReplay) -> None:
    outcome = store.append(batch)
    for status, n in outcome.counts.items():
        result.counts[status] += n


# -- onto Zenoh -----------------------------------------------------------------------------


@dataclass
class PublishReplay:
    """What a replay onto Zenoh did."""

    path: str
    published: int = 0
    passes: int = 0
    wall_s: float = 0.0
    max_late_s: float = 0.0  # the largest delay behind the paced schedule, wall seconds
    scan: ScanReport | None = None
    stopped: bool = False

    @property
    def rate_per_s(self) -> float:
        return self.published / self.wall_s if self.wall_s > 0 else 0.0


class Publishers:
    """One AdvancedPublisher per key, as the yard's producers declare them."""

    def __init__(self, session, cache_samples: int) -> None:
        self.session, self.cache_samples = session, cache_samples
        self._by_key: dict[str, object] = {}

    def put(self, key: str, payload: bytes, attachment: bytes) -> None:
        publisher = self._by_key.get(key)
        if publisher is None:
            publisher = declare_ledger_publisher(self.session, key,
                                                 cache_samples=self.cache_samples)
            self._by_key[key] = publisher
        publisher.put(payload, attachment=attachment)  # type: ignore[attr-defined]

    def close(self) -> None:
        for publisher in self._by_key.values():
            publisher.undeclare()  # type: ignore[attr-defined]
        self._by_key.clear()


class Pacer:
    """When each message is due: the replay clock follows valid time at ``rate``."""

    def __init__(self, rate: float | None) -> None:
        self.rate = rate
        self._origin: tuple[float, int] | None = None  # (wall s, valid ns)
        self._frontier_ns = 0

    def due_in_s(self, valid_time_ns: int, log_time_ns: int, now_s: float) -> float:
        """Seconds until a message with these times is due (<= 0: now).

        The clock starts at the first message: at the later of its valid and log
        times (a file that starts with a late assay does not wait for the hours
        between its valid time and the messages after it).
        """
        if self.rate is None:
            return 0.0
        if self._origin is None:
            start = max(valid_time_ns, log_time_ns)
            self._origin = (now_s, start)
            self._frontier_ns = start
            return 0.0
        self._frontier_ns = max(self._frontier_ns, valid_time_ns)
        wall0, valid0 = self._origin
        return wall0 + (self._frontier_ns - valid0) / NS_PER_S / self.rate - now_s


def replay_publish(path: str | Path, session, *, rate: float | None = 1.0, loop: bool = False,
                   topics: Callable[[str], bool] | None = None,
                   start_offset_s: float | None = None, until_s: float | None = None,
                   site: str | None = None, stop=None, cache_samples: int = 50_000,
                   progress: Progress | None = None) -> PublishReplay:
    """Publish a file's events on ``session`` (see the module docstring).

    ``stop`` is a :class:`services.service.Stopper` (or anything with ``wait(s)`` and
    ``is_set()``); ``site`` republishes under another site's keys.
    """
    if rate is not None and not rate > 0:
        raise ValueError(f"rate must be > 0, got {rate}")
    result = PublishReplay(str(path))
    publishers = Publishers(session, cache_samples)
    started = time.monotonic()
    try:
        while True:
            result.passes += 1
            finished = _publish_pass(path, publishers, result, rate=rate, topics=topics,
                                     start_offset_ns=_offset_ns(start_offset_s),
                                     until_offset_ns=_offset_ns(until_s), site=site, stop=stop,
                                     progress=progress, loop=loop)
            if not finished or not loop or result.published == 0:
                result.stopped = not finished
                break
    finally:
        result.wall_s = time.monotonic() - started
        publishers.close()
    if progress is not None:
        progress.update_to(result.published)
    return result


def _publish_pass(path, publishers: Publishers, result: PublishReplay, *, rate, topics,
                  start_offset_ns, until_offset_ns, site, stop, progress, loop) -> bool:
    """One pass over the file; False when stopped early."""
    pacer = Pacer(rate)
    with McapScan(path) as scan:
        result.scan = scan.report
        if progress is not None and not loop and progress.total is None \
                and topics is None and start_offset_ns is None and until_offset_ns is None:
            progress.total = scan.report.total
        for entry in read_entries(scan, topics=topics, start_offset_ns=start_offset_ns,
                                  until_offset_ns=until_offset_ns):
            if not _wait_due(pacer, entry, result, stop):
                return False
            key = entry.topic if site is None else key_expr(site, entry.type, entry.source)
            publishers.put(key, entry.payload,
                           encode_attachment(entry.epoch, entry.seq, entry.valid_time_ns,
                                             entry.signer, entry.signature))
            result.published += 1
            if progress is not None:
                progress.update_to(result.published, fraction=None if loop else _fraction(scan))
    return True


def _wait_due(pacer: Pacer, entry: Entry, result: PublishReplay, stop) -> bool:
    delay_s = pacer.due_in_s(entry.valid_time_ns, entry.log_time_ns, time.monotonic())
    if delay_s > 0:
        if stop is not None:
            if stop.wait(delay_s):
                return False
        else:
            time.sleep(delay_s)
    else:
        result.max_late_s = max(result.max_late_s, -delay_s) if pacer.rate else 0.0
        if stop is not None and stop.is_set():
            return False
    return True


def iter_events(path: str | Path) -> Iterator[Entry]:
    """Every stockpile event of a file (a convenience for tests and tools)."""
    with McapScan(path) as scan:
        yield from read_entries(scan)

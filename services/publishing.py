"""Ledger-bound publishing: one event source on Zenoh with its epoch and dense sequence.

:func:`declare_ledger_publisher` declares the ``AdvancedPublisher`` every ledger-bound
key uses (congestion control BLOCK, reliable, a sample cache for recovery, sample-miss
detection with a heartbeat, publisher detection); :class:`EventPublisher` is one source
(``stockpile/<site>/@v1/<type>/<source>`` per type) numbering its events densely, so a
ledger that restarts can recover what it missed from the caches.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import zenoh
import zenoh.ext as zext
from google.protobuf.message import Message

from ledger.signing import sign_event
from schemas.events import Event, encode_attachment, is_valid_source, key_expr, make_event
from security.event_keys import SigningKey

__all__ = ["DEFAULT_CACHE_SAMPLES", "HEARTBEAT_PERIOD_S", "EventPublisher",
           "declare_ledger_publisher"]

#: samples each AdvancedPublisher keeps for late joiners and recovery (per key)
DEFAULT_CACHE_SAMPLES = 50_000
#: period of the AdvancedPublisher heartbeat that lets a subscriber detect a lost last sample, s
HEARTBEAT_PERIOD_S = 0.5


def declare_ledger_publisher(session, key: str, *, cache_samples: int = DEFAULT_CACHE_SAMPLES,
                             priority=None):
    """An AdvancedPublisher for ledger-bound events on ``key``.

    Congestion control BLOCK (never drops), reliable, a cache of ``cache_samples``
    whose replies also block rather than drop, sample-miss detection with a heartbeat,
    and publisher detection, so a ledger that (re)starts finds it and asks its cache.
    """
    priority = zenoh.Priority.DATA if priority is None else priority
    return zext.declare_advanced_publisher(
        session, key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        priority=priority,
        reliability=zenoh.Reliability.RELIABLE,
        cache=zext.CacheConfig(cache_samples, replies_config=zext.RepliesConfig(
            congestion_control=zenoh.CongestionControl.BLOCK, priority=priority)),
        sample_miss_detection=zext.MissDetectionConfig(
            heartbeat=HEARTBEAT_PERIOD_S, sporadic_heartbeat=None),
        publisher_detection=True,
    )


class EventPublisher:
    """One ledger-bound event source on Zenoh: epoch, dense sequence, reliable keys.

    Each event type gets its own ``AdvancedPublisher`` on
    ``stockpile/<site>/@v1/<type>/<source>`` with a cache of ``cache_samples``
    samples, sample-miss detection with a heartbeat, publisher detection, and
    congestion control BLOCK, so nothing is dropped on the way and a subscriber that
    joins late (a restarted ledger) can query what it missed.

    The sequence is shared by all types of the source (the ledger's identity is
    ``(source, epoch, seq)``).  Thread-safe.

    Parameters
    ----------
    session : zenoh.Session
    site, source : str
    epoch : int, optional
        Default: the wall clock in nanoseconds at construction (never reused).
    cache_samples : int
        Samples kept per key for recovery.
    priority : zenoh.Priority, optional
        Default ``Priority.DATA``.
    signing_key : SigningKey, optional
        When given, every event is signed with it (signer and signature ride in the
        attachment).
    """

    def __init__(self, session, site: str, source: str, *, epoch: int | None = None,
                 cache_samples: int = DEFAULT_CACHE_SAMPLES, priority=None,
                 signing_key: SigningKey | None = None) -> None:
        if not is_valid_source(source):
            raise ValueError(f"bad source name {source!r}")
        self.session, self.site, self.source = session, site, source
        self.epoch = time.time_ns() if epoch is None else int(epoch)
        self.cache_samples = int(cache_samples)
        self.priority = zenoh.Priority.DATA if priority is None else priority
        self.seq = 0
        self.signing_key = signing_key
        self._publishers: dict[str, Any] = {}
        self._lock = threading.Lock()

    def _publisher(self, type_name: str):
        publisher = self._publishers.get(type_name)
        if publisher is None:
            publisher = declare_ledger_publisher(
                self.session, key_expr(self.site, type_name, self.source),
                cache_samples=self.cache_samples, priority=self.priority)
            self._publishers[type_name] = publisher
        return publisher

    def wait_matched(self, type_name: str, timeout_s: float) -> None:
        """Block until a subscriber matches this source's key for ``type_name``.

        An event published before any subscriber matched reaches it only through the
        publisher's cache (on the subscriber's next history query); waiting first makes
        the first event live.  Raises :class:`TimeoutError` after ``timeout_s``.
        """
        key = self._publisher(type_name).key_expr
        plain = self.session.declare_publisher(key,
                                               congestion_control=zenoh.CongestionControl.BLOCK)
        matched = threading.Event()
        listener = plain.declare_matching_listener(lambda s: s.matching and matched.set())
        try:
            if not (plain.matching_status.matching or matched.wait(timeout_s)):
                raise TimeoutError(f"no subscriber matched {key} in {timeout_s:g} s")
        finally:
            listener.undeclare()
            plain.undeclare()

    def declare(self, *type_names: str) -> None:
        """Declare the keys up front (so subscribers can match before the first event)."""
        with self._lock:
            for name in type_names:
                self._publisher(name)

    def publish(self, message: Message) -> Event:
        """Publish one message as the next event of this source; return the event.

        The valid time is the message's own timestamp field.
        """
        with self._lock:
            event = make_event(message, source=self.source, epoch=self.epoch, seq=self.seq)
            if self.signing_key is not None:
                event = sign_event(event, self.signing_key)
            self._publisher(event.type).put(
                event.payload,
                attachment=encode_attachment(event.epoch, event.seq, event.valid_time_ns,
                                             event.signer, event.signature))
            self.seq += 1
            return event

    @property
    def count(self) -> int:
        return self.seq

    def close(self) -> None:
        with self._lock:
            for publisher in self._publishers.values():
                try:
                    publisher.undeclare()
                except Exception:  # noqa: BLE001 - the session may already be closed
                    pass
            self._publishers.clear()

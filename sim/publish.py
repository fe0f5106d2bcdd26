"""Where the simulator's events go: producers number them, sinks carry them.

A :class:`Producer` is one source (``bwr1.encoders``, ``lab1`` ...): it wraps each
protobuf message in an :class:`~schemas.events.Event` with its epoch and dense
sequence.  Sinks receive every event in emission order:

- :class:`JsonlSink`: canonical JSON lines (``events.jsonl``), for tests, the
  ledger import and byte-for-byte reproducibility checks;
- :class:`ZenohSink`: publishes on ``stockpile/<site>/@v1/<type>/<source>`` with the
  identity in the attachment, as the real yard's producers do.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Protocol

import zenoh
from google.protobuf.message import Message

from ledger.signing import sign_event
from schemas.events import Event, encode_attachment, key_expr, make_event
from security.event_keys import SigningKey
from schemas.jsonl import event_line
from services.service import declare_ledger_publisher


class Sink(Protocol):
    def emit(self, event: Event) -> None: ...

    def close(self) -> None: ...


class Producer:
    """One event source with its epoch and next sequence number; with ``key``, every event
    it emits is signed with that key.  A ``muted`` producer emits nothing and counts
    nothing (a live run before its live moment) until :meth:`restart`."""

    def __init__(self, source: str, epoch: int, sinks: list[Sink],
                 key: SigningKey | None = None) -> None:
        self.source, self.epoch, self.sinks, self.key = source, epoch, sinks, key
        self.seq = 0
        self.muted = False

    def restart(self, epoch: int) -> None:
        """Start afresh as a restarted device does: a new ``epoch`` from seq 0, unmuted."""
        self.epoch, self.seq, self.muted = int(epoch), 0, False

    def emit(self, message: Message) -> Event | None:
        """Number (and sign) ``message`` and hand it to every sink; None when muted."""
        if self.muted:
            return None
        event = make_event(message, source=self.source, epoch=self.epoch, seq=self.seq)
        if self.key is not None:
            event = sign_event(event, self.key)
        self.seq += 1
        for sink in self.sinks:
            sink.emit(event)
        return event


class JsonlSink:
    """Appends canonical JSON lines to a file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._file = self.path.open("w", encoding="utf-8")
        self.count = 0

    def emit(self, event: Event) -> None:
        self._file.write(event_line(event))
        self._file.write("\n")
        self.count += 1

    def close(self) -> None:
        self._file.close()


class MemorySink:
    """Keeps events in a list (tests)."""

    def __init__(self) -> None:
        self.events: list[Event] = []

    def emit(self, event: Event) -> None:
        self.events.append(event)

    def close(self) -> None:
        return None


class ZenohSink:
    """Publishes events on Zenoh as the yard's ledger-bound producers do.

    Each key gets an AdvancedPublisher (:func:`services.service.declare_ledger_publisher`):
    congestion control BLOCK (never drops) and a cache a restarted ledger recovers from.
    """

    def __init__(self, session, site: str) -> None:
        self.session, self.site = session, site
        self._publishers: dict[tuple[str, str], object] = {}
        self._block = zenoh.CongestionControl.BLOCK
        self.count = 0

    def _publisher(self, type_name: str, source: str):
        key = (type_name, source)
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = declare_ledger_publisher(self.session,
                                                 key_expr(self.site, type_name, source))
            self._publishers[key] = publisher
        return publisher

    def emit(self, event: Event) -> None:
        publisher = self._publisher(event.type, event.source)
        publisher.put(event.payload,
                      attachment=encode_attachment(event.epoch, event.seq, event.valid_time_ns,
                                                   event.signer, event.signature))
        self.count += 1

    def wait_for_subscriber(self, type_name: str, source: str, timeout_s: float) -> bool:
        """Block until a subscriber matches ``type``/``source`` (or ``timeout_s`` passes).

        Lets a run start only once its consumer listens, so nothing is published into
        the void.  Returns whether one matched.
        """
        self._publisher(type_name, source)
        # an AdvancedPublisher has no matching listener: watch a plain one on the same key
        probe = self.session.declare_publisher(key_expr(self.site, type_name, source),
                                               congestion_control=self._block)
        matched = threading.Event()

        def on_status(status) -> None:
            if status.matching:
                matched.set()

        listener = probe.declare_matching_listener(on_status)
        try:
            if probe.matching_status.matching:
                return True
            return matched.wait(timeout_s)
        finally:
            listener.undeclare()
            probe.undeclare()

    def close(self) -> None:
        for publisher in self._publishers.values():
            publisher.undeclare()
        self._publishers.clear()

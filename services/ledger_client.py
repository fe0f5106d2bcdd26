"""Read a running ledger service over Zenoh (never the DuckDB file).

:class:`LedgerClient` is the query API; :class:`RemoteLedger` wraps it as a read-only
ledger store, which the read commands use for a file a service holds.

>>> client = LedgerClient(session, "demo")            # doctest: +SKIP
>>> client.head()["global_seq"]                        # doctest: +SKIP
>>> for record in client.read(start=0): ...            # doctest: +SKIP

Every read method raises :class:`LedgerUnavailable` when no ledger service answers
in ``timeout_s`` and :class:`LedgerQueryError` when it answers with an error or an
incomplete reply.
"""

from __future__ import annotations

import json
import threading
from typing import Any, Callable, Iterator, Sequence

import zenoh

from ledger.errors import InterfaceError, LedgerError, OperationalError
from ledger.holder import LedgerHolder
from ledger.records import Gap, Head, LedgerStats, QuarantineEntry, RecordedEvent, StreamInfo
from ledger.store import LedgerStore
from ledger.wire import (decode_records, gap_from_json, head_from_json, quarantine_from_json,
                         stats_from_json, stream_from_json)
from services.ledger_service import CHUNK_ATTACHMENT, head_key, query_key
from services.service import ZenohOptions, open_session

DEFAULT_TIMEOUT_S = 30.0
DEFAULT_PAGE_RECORDS = 10_000
BACKUP_TIMEOUT_S = 3600.0  # longest wait for a backup's copy and verification, seconds


class LedgerUnavailable(OperationalError):
    """No ledger service answered."""


class LedgerQueryError(LedgerError):
    """The ledger service answered with an error, or the reply was incomplete."""


class LedgerClient:
    """Queries of one site's ledger service.

    Parameters
    ----------
    session : zenoh.Session
    site : str
    timeout_s : float
        Longest wait for a whole answer, seconds.
    stop : threading.Event, optional
        When set, a query still waiting for its answer gives up at once
        (:class:`LedgerUnavailable`).  A service passes its stopper's event: a wait
        inside Zenoh does not run Python's signal handlers, so without it SIGTERM
        waited for the query's whole timeout.
    """

    def __init__(self, session, site: str, *, timeout_s: float = DEFAULT_TIMEOUT_S,
                 stop: threading.Event | None = None) -> None:
        self.session, self.site, self.timeout_s = session, site, float(timeout_s)
        self.stop = stop

    def _get(self, what: str, params: dict[str, Any] | None = None) -> list:
        replies = self.session.get(
            query_key(self.site, what),
            payload=json.dumps(params or {}).encode(),
            consolidation=zenoh.ConsolidationMode.NONE,
            target=zenoh.QueryTarget.BEST_MATCHING,
            timeout=self.timeout_s,
        )
        out = []
        for reply in self._replies(replies, what):
            if reply.err is not None:
                raise LedgerQueryError(f"ledger service error on {what}: "
                                       f"{reply.err.payload.to_bytes().decode(errors='replace')}")
            out.append(reply.ok)
        if not out:
            raise LedgerUnavailable(f"no ledger service answered {query_key(self.site, what)} "
                                    f"within {self.timeout_s:g} s")
        return out

    def _replies(self, handler, what: str):
        """The replies as they come; with ``stop``, polled so that setting it ends the
        wait within 10 ms."""
        if self.stop is None:
            yield from handler
            return
        while True:
            try:
                reply = handler.try_recv()
            except zenoh.ZError:          # the channel closed: every reply is in
                return
            if reply is not None:
                yield reply
            elif self.stop.wait(0.01):
                raise LedgerUnavailable(f"stopped while waiting for the ledger's answer "
                                        f"to {query_key(self.site, what)}")

    def _json(self, what: str, params: dict[str, Any] | None = None) -> Any:
        return json.loads(self._get(what, params)[0].payload.to_bytes())

    def _records(self, what: str, params: dict[str, Any]) -> list[RecordedEvent]:
        chunks: dict[int, bytes] = {}
        last_index, total = None, 0
        for sample in self._get(what, params):
            if sample.attachment is None:
                raise LedgerQueryError(f"{what}: a reply chunk came without its attachment")
            index, last, total_so_far = CHUNK_ATTACHMENT.unpack(sample.attachment.to_bytes())
            chunks[index] = sample.payload.to_bytes()
            if last:
                last_index, total = index, total_so_far
        if last_index is None or sorted(chunks) != list(range(last_index + 1)):
            raise LedgerQueryError(f"{what}: incomplete reply (chunks {sorted(chunks)}, "
                                   f"last {last_index})")
        records: list[RecordedEvent] = []
        for index in range(last_index + 1):
            try:
                records.extend(decode_records(chunks[index]))
            except ValueError as exc:
                raise LedgerQueryError(f"{what}: bad reply chunk {index}: {exc}") from None
        if len(records) != total:
            raise LedgerQueryError(f"{what}: got {len(records)} records, the service sent {total}")
        return records

    # -- queries --------------------------------------------------------------------------

    def read(self, start: int = 0, stop: int | None = None, *,
             types: Sequence[str] | None = None,
             sources: Sequence[str] | None = None,
             limit: int | None = None) -> list[RecordedEvent]:
        """Events with ``start <= global_seq < stop`` in global order (catch-up), at most
        ``limit`` of them."""
        return self._records("events", {"start": start, "stop": stop,
                                        "types": list(types) if types else None,
                                        "sources": list(sources) if sources else None,
                                        "limit": limit})

    def as_of(self, valid_time_ns: int, known_time_ns: int, *,
              types: Sequence[str] | None = None,
              after: tuple[int, int] | None = None,
              max_global_seq: int | None = None,
              limit: int | None = None) -> list[RecordedEvent]:
        """Events with valid time <= V recorded at or before K, in (valid, global seq) order.

        ``after=(valid_ns, global_seq)`` starts after that position; ``max_global_seq``
        keeps the events committed up to that head; ``limit`` caps the answer.
        """
        return self._records("as_of", {"valid_time_ns": int(valid_time_ns),
                                       "known_time_ns": int(known_time_ns),
                                       "types": list(types) if types else None,
                                       "after": None if after is None else list(after),
                                       "max_global_seq": max_global_seq, "limit": limit})

    def stats(self) -> dict[str, Any]:
        """The ledger's stats as JSON (as ``stockpile ledger stats --json``)."""
        return self._json("stats")

    def head(self) -> dict[str, Any]:
        """``{"global_seq", "recorded_time_ns", "chain_sha256"}`` of the committed end."""
        return self._json("head")

    def gaps(self, *, open_only: bool = False) -> list[dict[str, Any]]:
        """Sequence gaps (``source, epoch, first_seq, last_seq, ...``)."""
        return self._json("gaps", {"open_only": open_only})

    def quarantine(self) -> list[dict[str, Any]]:
        """Every quarantined input (:func:`ledger.wire.quarantine_to_json` form)."""
        return self._json("quarantine")

    def streams(self) -> list[dict[str, Any]]:
        """Sequence bookkeeping per (source, epoch)."""
        return self._json("streams")

    # -- following ------------------------------------------------------------------------

    def backup(self, target_dir: str, *, timeout_s: float = BACKUP_TIMEOUT_S) -> dict[str, Any]:
        """Have the service back its ledger up into ``target_dir`` (an absolute path on
        the service's machine) between two batches; the backup's manifest
        (:class:`ledger.backup.Manifest` as JSON) once the copy is verified."""
        slow = LedgerClient(self.session, self.site, timeout_s=timeout_s, stop=self.stop)
        return slow._json("backup", {"to": target_dir})

    def follow_head(self, callback: Callable[[dict[str, Any]], None]):
        """Call ``callback(head)`` after every committed batch; returns the subscriber."""

        def on_sample(sample) -> None:
            callback(json.loads(sample.payload.to_bytes()))

        return self.session.declare_subscriber(head_key(self.site), on_sample)

    def first_head(self, *, period_s: float = 1.0,
                   log: Callable[..., None] | None = None) -> dict[str, Any] | None:
        """The committed head once a ledger service answers, asking every ``period_s``
        seconds (a service started before its site's ledger waits for it); None when
        ``stop`` is set first.  ``log("waiting for the ledger service", ...)`` once, as a
        warning, if the first question goes unanswered."""
        waited = False
        while True:
            try:
                return self.head()
            except LedgerUnavailable as exc:
                if self.stop is not None and self.stop.is_set():
                    return None
                if not waited and log is not None:
                    log("waiting for the ledger service", level="warning", error=str(exc))
                waited = True
            if self.stop is not None:
                if self.stop.wait(period_s):   # the retry period; set: the service stops
                    return None
            else:
                threading.Event().wait(period_s)

    def wait_for(self, predicate: Callable[[dict[str, Any]], bool], timeout_s: float) -> dict:
        """Block until a committed head satisfies ``predicate``; return it.

        Checks the current head first, then every published head.  Raises
        :class:`TimeoutError` after ``timeout_s``.
        """
        done = threading.Event()
        found: list[dict[str, Any]] = []

        def check(head: dict[str, Any]) -> None:
            if not done.is_set() and predicate(head):
                found.append(head)
                done.set()

        subscriber = self.follow_head(check)
        try:
            check(self.head())
            if not done.wait(timeout_s):
                raise TimeoutError(f"the ledger head did not reach the condition in {timeout_s:g} s")
            return found[0]
        finally:
            subscriber.undeclare()


class RemoteLedger(LedgerStore):
    """A read-only :class:`~ledger.store.LedgerStore` over a running ledger service.

    The read commands (``project``, ``audit``, ``plan``, ``ledger export|stats|verify``,
    ``info``, ``dashboard``) use it, through :func:`ledger.open_ledger`, when the ledger
    file is held by a service.  It reads the ledger as of the head committed when it
    was opened: ``head()``, ``read()`` and ``as_of()`` leave out what was appended
    since (``stats()``, ``gaps()``, ``quarantine()`` and ``streams()`` are the
    service's current ones).  Records come in pages of ``page_records``.

    Parameters
    ----------
    client : LedgerClient
    close_session : bool
        Close the client's Zenoh session when the store closes.
    page_records : int
        Most records one query answers.
    """

    backend = "remote"

    def __init__(self, client: LedgerClient, *, close_session: bool = False,
                 page_records: int = DEFAULT_PAGE_RECORDS) -> None:
        super().__init__(read_only=True)
        if page_records < 1:
            raise ValueError(f"page_records must be >= 1, got {page_records}")
        self.client, self.page_records = client, page_records
        self._close_session = close_session
        try:
            self._head = head_from_json(client.head())
        except ValueError as exc:
            raise LedgerQueryError(f"head: {exc}") from None

    def head(self) -> Head:
        self._check_open()
        return self._head

    def read(self, start_seq: int = 0, stop_seq: int | None = None, *,
             types: Sequence[str] | None = None,
             sources: Sequence[str] | None = None) -> Iterator[RecordedEvent]:
        self._check_open()
        stop = self._head.global_seq + 1 if stop_seq is None else min(
            stop_seq, self._head.global_seq + 1)
        return self._read_pages(start_seq, stop, types, sources)

    def _read_pages(self, start: int, stop: int, types, sources) -> Iterator[RecordedEvent]:
        while start < stop:
            page = self.client.read(start, stop, types=types, sources=sources,
                                    limit=self.page_records)
            yield from page
            if len(page) < self.page_records:
                return
            start = page[-1].global_seq + 1

    def as_of(self, valid_time_ns: int, known_time_ns: int, *,
              types: Sequence[str] | None = None,
              after: tuple[int, int] | None = None) -> Iterator[RecordedEvent]:
        self._check_open()
        return self._as_of_pages(int(valid_time_ns), int(known_time_ns), types, after)

    def _as_of_pages(self, valid_ns: int, known_ns: int, types, after) -> Iterator[RecordedEvent]:
        while True:
            page = self.client.as_of(valid_ns, known_ns, types=types, after=after,
                                     max_global_seq=self._head.global_seq,
                                     limit=self.page_records)
            yield from page
            if len(page) < self.page_records:
                return
            after = (page[-1].valid_time_ns, page[-1].global_seq)

    def gaps(self, *, open_only: bool = False) -> list[Gap]:
        self._check_open()
        return self._decode(gap_from_json, self.client.gaps(open_only=open_only), "gaps")

    def quarantine(self) -> list[QuarantineEntry]:
        self._check_open()
        return self._decode(quarantine_from_json, self.client.quarantine(), "quarantine")

    def streams(self) -> list[StreamInfo]:
        self._check_open()
        return self._decode(stream_from_json, self.client.streams(), "streams")

    def stats(self) -> LedgerStats:
        self._check_open()
        try:
            return stats_from_json(self.client.stats())
        except ValueError as exc:
            raise LedgerQueryError(f"stats: {exc}") from None

    @staticmethod
    def _decode(convert, items, what: str) -> list:
        if not isinstance(items, list):
            raise LedgerQueryError(f"{what}: expected a JSON list")
        try:
            return [convert(item) for item in items]
        except ValueError as exc:
            raise LedgerQueryError(f"{what}: {exc}") from None

    def _lookup(self, keys, valid_span_ns=None):  # pragma: no cover - read-only: never appends
        raise InterfaceError("a remote ledger is read-only")

    def _commit(self, plan):  # pragma: no cover - a read-only store never appends
        raise InterfaceError("a remote ledger is read-only")

    def request_backup(self, target_dir: str) -> dict[str, Any]:
        """A backup taken by the service (:meth:`LedgerClient.backup`)."""
        return self.client.backup(target_dir)

    def _close(self) -> None:
        if self._close_session:
            self.client.session.close()


def open_remote_ledger(holder: LedgerHolder, *, timeout_s: float = DEFAULT_TIMEOUT_S,
                       page_records: int = DEFAULT_PAGE_RECORDS) -> RemoteLedger:
    """A :class:`RemoteLedger` on the service a holder file names (its own Zenoh session,
    in client mode, connected to the holder's endpoints; closed with the store).

    Raises
    ------
    LedgerUnavailable
        The holder names no endpoint, or the service does not answer.
    """
    if not holder.endpoints:
        raise LedgerUnavailable(f"{holder.describe()} listens on no fixed endpoint, so "
                                "nothing can read through it (start it with --listen)")
    try:
        session = open_session(ZenohOptions(mode="client", connect=holder.endpoints))
    except OSError as exc:
        raise LedgerUnavailable(f"cannot reach {holder.describe()} at "
                                f"{', '.join(holder.endpoints)}: {exc}") from None
    try:
        client = LedgerClient(session, holder.site, timeout_s=timeout_s)
        return RemoteLedger(client, close_session=True, page_records=page_records)
    except BaseException:
        session.close()
        raise

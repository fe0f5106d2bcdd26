"""Read a running ledger service over Zenoh (never the DuckDB file).

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
from typing import Any, Callable, Sequence

import zenoh

from ledger.errors import LedgerError, OperationalError
from ledger.records import RecordedEvent
from ledger.wire import decode_records
from services.ledger_service import CHUNK_ATTACHMENT, head_key, query_key

DEFAULT_TIMEOUT_S = 30.0


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
             sources: Sequence[str] | None = None) -> list[RecordedEvent]:
        """Events with ``start <= global_seq < stop`` in global order (catch-up)."""
        return self._records("events", {"start": start, "stop": stop,
                                        "types": list(types) if types else None,
                                        "sources": list(sources) if sources else None})

    def as_of(self, valid_time_ns: int, known_time_ns: int, *,
              types: Sequence[str] | None = None) -> list[RecordedEvent]:
        """Events with valid time <= V recorded at or before K, in (valid, global seq) order."""
        return self._records("as_of", {"valid_time_ns": int(valid_time_ns),
                                       "known_time_ns": int(known_time_ns),
                                       "types": list(types) if types else None})

    def stats(self) -> dict[str, Any]:
        """The ledger's stats as JSON (as ``stockpile ledger stats --json``)."""
        return self._json("stats")

    def head(self) -> dict[str, Any]:
        """``{"global_seq", "recorded_time_ns", "chain_sha256"}`` of the committed end."""
        return self._json("head")

    def gaps(self, *, open_only: bool = False) -> list[dict[str, Any]]:
        """Sequence gaps (``source, epoch, first_seq, last_seq, ...``)."""
        return self._json("gaps", {"open_only": open_only})

    # -- following ------------------------------------------------------------------------

    def follow_head(self, callback: Callable[[dict[str, Any]], None]):
        """Call ``callback(head)`` after every committed batch; returns the subscriber."""

        def on_sample(sample) -> None:
            callback(json.loads(sample.payload.to_bytes()))

        return self.session.declare_subscriber(head_key(self.site), on_sample)

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

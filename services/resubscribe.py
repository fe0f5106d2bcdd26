"""Ask a publisher's cache again whenever its liveliness token (re)appears.

An ``AdvancedPublisher`` with publisher detection declares a liveliness token
``<key>/@adv/pub/<zid>/<eid>/...``.  Zenoh's own ``detect_late_publishers`` cannot use
it on the site's keys: its parser reads the part before ``@adv`` as ``**``, which never
matches the ``@v1`` chunk, so it drops every token of ``stockpile/<site>/@v1/...``
("malformed liveliness token").  A subscriber then learns of what it missed only from the
next live sample (a sample miss); when nothing more is published after a router outage,
it never does.

:class:`CacheRecall` does that job for a subscriber: it follows the publishers' tokens
under ``<key>/@adv/pub/**`` and, for every token that appears while it runs (a new
publisher, or one coming back after its link or the router was lost: the router
re-announces the tokens it learns again), queries that token's cache and hands every
reply to ``on_sample``, the subscriber's own callback.  A token's Delete and Put are not
always seen across a router restart, so it also checks the session's router every
``ROUTER_CHECK_S``: once linked to a new one (a restarted router has a new id), it asks
every present publisher's cache that it has not asked in the last ``RECENT_S``.  Replies are samples the
subscriber may hold already: its handler must treat a duplicate as a no-op.  Queries run
on one worker thread, never in zenoh's callback.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Callable

import zenoh

from services.logfmt import log
from services.pump import DEFAULT_CAPACITY

#: how long one cache query may take before zenoh ends it, s
QUERY_TIMEOUT_S = 60.0

#: how long the query for the publishers present at the start may take, s
PRESENT_TIMEOUT_S = 5.0

#: a query that brought nothing is asked once more this much later, s
RETRY_AFTER_S = 1.0

#: how often the session's router is checked, s
ROUTER_CHECK_S = 1.0
#: after a new router is seen, how long to wait for the publishers to reach it too, s
ROUTER_SETTLE_S = 5.0
#: a recall that ended this recently is not repeated for a new router, s
RECENT_S = 30.0

#: how long close() waits for the worker to see it, s
CLOSE_WAIT_S = 5.0

_STOP = object()


class CacheRecall:
    """Queries each (re)appearing publisher's cache under ``key`` (a subscriber's key
    expression, e.g. ``stockpile/<site>/@v1/**``); replies go to ``on_sample``.

    The publishers whose tokens are present when it starts are not queried (the
    subscriber's history query covers them); a token that goes (its publisher's link or
    the router was lost) and comes back is.  ``on_recall(token_key, replies)`` is called
    after each recall ends (for a log line); a recall whose query brings nothing asks once
    more after ``RETRY_AFTER_S``.  ``recalls`` counts the queries made.
    """

    def __init__(self, session: Any, key: str, on_sample: Callable[[Any], None], *,
                 on_recall: Callable[[str, int], None] | None = None,
                 query_timeout_s: float = QUERY_TIMEOUT_S,
                 present_timeout_s: float = PRESENT_TIMEOUT_S) -> None:
        self.session, self.key, self.on_sample = session, key, on_sample
        self.on_recall = on_recall
        self.query_timeout_s = float(query_timeout_s)
        self.recalls = 0
        self._closed = False
        self._stop = threading.Event()
        self._recalled: dict[str, float] = {}   # token -> monotonic s its last recall ended
        self._present: set[str] = set()   # tokens whose first Put is the subscriber's history
        self._work: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="cache-recall", daemon=True)
        self._thread.start()
        tokens = f"{key}/@adv/pub/**"
        # the publishers present now are the subscriber's own history query's business
        for reply in session.liveliness().get(tokens, timeout=present_timeout_s):
            if reply.ok is not None:
                self._present.add(str(reply.ok.key_expr))
        self._subscriber = session.liveliness().declare_subscriber(
            tokens, self._on_token, history=True)
        self._routers = self._router_ids()
        self._watch = threading.Thread(target=self._watch_router, name="cache-recall-router",
                                       daemon=True)
        self._watch.start()

    @classmethod
    def of_events(cls, session: Any, site: str, on_sample: Callable[[Any], None],
                  service: str, enabled: bool = True) -> "CacheRecall | _Off":
        """For a subscriber of all the site's events (``stockpile/<site>/@v1/**``);
        logs one ``publisher back`` line per query.  Not ``enabled``: does nothing."""
        if not enabled:
            return _Off()
        return cls(session, f"stockpile/{site}/@v1/**", on_sample,
                   on_recall=lambda token, n: log(service, "publisher back: cache asked",
                                                  token=token, replies=n))

    def _on_token(self, sample: Any) -> None:
        token = str(sample.key_expr)
        if sample.kind == zenoh.SampleKind.DELETE or token in self._present:
            self._present.discard(token)
        else:   # a publisher appears, or comes back (its Delete may come late or never)
            self._work.put(("token", token))

    def _router_ids(self) -> frozenset[str]:
        try:
            return frozenset(str(z) for z in self.session.info.routers_zid())
        except zenoh.ZError:
            return frozenset()

    def _watch_router(self) -> None:
        """When the session is linked to a new router (a restarted one has a new id),
        recall every publisher present: a token's Delete and Put are not always seen."""
        while not self._stop.wait(ROUTER_CHECK_S):
            routers = self._router_ids()
            if not routers or routers == self._routers:
                continue
            self._routers = routers
            self._stop.wait(ROUTER_SETTLE_S)   # let the publishers come back too
            try:
                present = list(self.session.liveliness().get(f"{self.key}/@adv/pub/**",
                                                             timeout=PRESENT_TIMEOUT_S))
            except zenoh.ZError:
                return
            for reply in present:
                if reply.ok is not None:
                    self._work.put(("router", str(reply.ok.key_expr)))

    def _run(self) -> None:
        while True:
            item = self._work.get()
            if item is _STOP:
                return
            why, token = item
            last = self._recalled.get(token)
            if why == "router" and last is not None and time.monotonic() - last < RECENT_S:
                continue   # its token came back with the router: asked already
            self._recall(token)
            self._recalled[token] = time.monotonic()

    def _recall(self, token: str) -> None:
        replies = self._query(token)
        if replies == 0 and not self._closed:
            # its cache may answer only once its queryable is known again: ask once more
            self._stop.wait(RETRY_AFTER_S)
            replies = self._query(token)
        if self.on_recall is not None:
            self.on_recall(token, replies)

    def _query(self, token: str) -> int:
        """Ask ``token``'s cache; hand its samples over; return how many.  The replies
        wait in a FIFO channel (:mod:`services.pump`), so Zenoh's threads never wait for
        ``on_sample``'s thread."""
        try:
            handler = self.session.get(token, zenoh.handlers.FifoChannel(DEFAULT_CAPACITY),
                                       consolidation=zenoh.ConsolidationMode.NONE,
                                       accept_replies=zenoh.ReplyKeyExpr.ANY,
                                       timeout=self.query_timeout_s)
        except zenoh.ZError:
            return 0   # the session is closing
        self.recalls += 1
        replies = 0
        for reply in handler:   # ends with the query (its timeout, or every answer in)
            if self._closed:
                break
            if reply.ok is not None:
                replies += 1
                self.on_sample(reply.ok)
        return replies

    def close(self) -> None:
        """Stop following tokens and handing replies over (a query under way is left to
        end by itself)."""
        self._closed = True
        self._stop.set()
        try:
            self._subscriber.undeclare()
        except zenoh.ZError:
            pass
        self._work.put(_STOP)
        self._thread.join(CLOSE_WAIT_S)
        self._watch.join(CLOSE_WAIT_S)


class _Off:
    """A :class:`CacheRecall` that is switched off (a subscriber without history)."""

    recalls = 0

    def close(self) -> None:
        pass

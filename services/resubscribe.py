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
reply to ``on_sample``, the subscriber's own callback.  Replies are samples the
subscriber may hold already: its handler must treat a duplicate as a no-op.  Queries run
on one worker thread, never in zenoh's callback.
"""

from __future__ import annotations

import queue
import threading
from typing import Any, Callable

import zenoh

from services.logfmt import log

#: how long one cache query may take before zenoh ends it, s
QUERY_TIMEOUT_S = 60.0

#: how long the query for the publishers present at the start may take, s
PRESENT_TIMEOUT_S = 5.0

#: how long close() waits for the worker to see it, s
CLOSE_WAIT_S = 5.0

_STOP = object()


class CacheRecall:
    """Queries each (re)appearing publisher's cache under ``key`` (a subscriber's key
    expression, e.g. ``stockpile/<site>/@v1/**``); replies go to ``on_sample``.

    The publishers whose tokens are present when it starts are not queried (the
    subscriber's history query covers them); a token that goes (its publisher's link or
    the router was lost) and comes back is.  ``on_recall(token_key, replies)`` is called
    after each query ends (for a log line).
    ``recalls`` counts the queries made.
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
        self._alive: set[str] = set()
        self._work: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="cache-recall", daemon=True)
        self._thread.start()
        tokens = f"{key}/@adv/pub/**"
        # the publishers present now are the subscriber's own history query's business
        for reply in session.liveliness().get(tokens, timeout=present_timeout_s):
            if reply.ok is not None:
                self._alive.add(str(reply.ok.key_expr))
        self._subscriber = session.liveliness().declare_subscriber(
            tokens, self._on_token, history=True)

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
        if sample.kind == zenoh.SampleKind.DELETE:
            self._alive.discard(token)
        elif token not in self._alive:
            self._alive.add(token)
            self._work.put(token)

    def _run(self) -> None:
        while True:
            token = self._work.get()
            if token is _STOP:
                return
            self._recall(token)

    def _recall(self, token: str) -> None:
        done = threading.Event()
        replies = [0]

        def on_reply(reply: Any) -> None:
            if reply.ok is not None and not self._closed:
                replies[0] += 1
                self.on_sample(reply.ok)

        try:
            self.session.get(token, zenoh.handlers.Callback(on_reply, done.set),
                             consolidation=zenoh.ConsolidationMode.NONE,
                             accept_replies=zenoh.ReplyKeyExpr.ANY,
                             timeout=self.query_timeout_s)
        except zenoh.ZError:
            return   # the session is closing
        self.recalls += 1
        while not (done.wait(0.5) or self._closed):
            pass
        if self.on_recall is not None:
            self.on_recall(token, replies[0])

    def close(self) -> None:
        """Stop following tokens and handing replies over (a query under way is left to
        end by itself)."""
        self._closed = True
        try:
            self._subscriber.undeclare()
        except zenoh.ZError:
            pass
        self._work.put(_STOP)
        self._thread.join(CLOSE_WAIT_S)


class _Off:
    """A :class:`CacheRecall` that is switched off (a subscriber without history)."""

    recalls = 0

    def close(self) -> None:
        pass

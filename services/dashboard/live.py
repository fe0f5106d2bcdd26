"""``stockpile service dashboard``: the live dashboard service.

:func:`main` follows the ledger service over Zenoh like the projector service: it
catches up on everything committed (updates at recorded-time boundaries, then "as known
now" at the head), then goes live (:class:`Follower`): each committed head is read,
updates come at most every ``update_period_s`` of wall time, and the ledger's gaps and
quarantine counts are polled.  ``--serve`` hosts the web viewer, ``--out`` archives the
stream.  Several ``--pile`` share the reading and the recording
(:class:`~services.dashboard.piles.PileSet`): each pile keeps its own fold and its own
update cadence, its entities under ``/piles/<id>`` (one pile: the usual paths).
"""

from __future__ import annotations

import time

from services.dashboard.config import READ_CHUNK, SERVICE, Config
from services.dashboard.core import Dashboard, rebuild_from
from services.dashboard.piles import PileSet
from services.dashboard.viewer import WebViewer, close_recording, make_recording
from services.ledger_client import LedgerClient, LedgerUnavailable, RemoteLedger
from services.projector_service import newest_head
from services.service import Inbox, ServiceRuntime, Stopper

#: live: wall seconds between two polls of the ledger's gaps and quarantine
POLL_PERIOD_S = 5.0
#: live: wall seconds to wait for a new head before the next round of the loop
HEAD_WAIT_S = 0.05
#: live: wall seconds to wait after a failed read or update
RETRY_WAIT_S = 0.5


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the live dashboard until SIGINT/SIGTERM (or ``stopper``); return the exit code."""
    if not config.piles:
        raise ValueError("--pile is required")
    if not config.serve and not config.rrd:
        raise ValueError("give --serve and/or --out PATH.rrd")
    heads = Inbox()
    # the liveliness token's name: the pile, or the piles joined by "+"
    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, name="+".join(config.piles),
                             status_period_s=config.status_period_s, stopper=stopper)
    rec, uri = make_recording(config)
    runtime.open(backlog=lambda: heads.qsize(), error_keys=("errors",), announce=False)
    with runtime:
        status = runtime.status
        assert status is not None and runtime.stopper is not None
        for name in ("records", "updates", "rebuilds", "errors"):
            status.add(name, 0)
        viewer = subscriber = None
        try:
            if config.serve and uri:
                viewer = WebViewer(config, uri)
                runtime.log("serving", web=viewer.url, grpc=uri)
            # a wait for the ledger inside Zenoh runs no signal handler: the client polls
            # the stopper, so SIGTERM ends it at once rather than after a query's timeout
            client = LedgerClient(runtime.session, config.site, stop=runtime.stopper.event)
            subscriber = client.follow_head(lambda head: heads.put(head["global_seq"]))
            Follower(config, runtime, client, rec).run(heads)
        except LedgerUnavailable:
            if not runtime.stopper.is_set():   # given up because the service stops: fine
                raise
        finally:
            if subscriber is not None:
                try:
                    subscriber.undeclare()
                except Exception:  # noqa: BLE001 - the session may be closing
                    pass
            if viewer is not None:
                viewer.close()
            close_recording(rec)
    return 0


class Follower:
    """The live loop of the piles' dashboards: catch up, go live, update until stopped.

    The records are read once and fed to every pile's dashboard (:attr:`piles`); each is
    rebuilt when its own fold goes stale and updated at most every ``update_period_s``
    of its own.  The status counters sum over the piles (``records``: records read).

    Parameters
    ----------
    config : Config
    runtime : services.service.ServiceRuntime
        Opened: its status counters, log and stopper.
    client : services.ledger_client.LedgerClient
    rec : rerun.RecordingStream
    """

    def __init__(self, config: Config, runtime, client, rec) -> None:
        self.config, self.runtime, self.client = config, runtime, client
        self.status = runtime.status
        self.piles = PileSet(rec, config)
        for dash in self.piles:
            dash.surveys.source = lambda: RemoteLedger(client)
        self.seen_gaps: set = set()
        self.quarantined = 0

    @property
    def dash(self) -> Dashboard:
        """The first pile's dashboard."""
        return self.piles.first

    def rebuild(self, dash: Dashboard | None = None) -> None:
        """Refold a stale projection (default: the first pile's) from the ledger service."""
        rebuild_from(self.client, dash or self.dash)
        self.status.add("rebuilds")

    def read_to(self, head_seq: int, *, updates: bool) -> int:
        """Read records up to ``head_seq`` once and add them to every pile (``updates``:
        updating when due); returns the records read."""
        piles = self.piles
        n = 0
        while piles.seq < head_seq and not self.runtime.stopper.is_set():
            stop = min(head_seq + 1, piles.seq + 1 + READ_CHUNK)
            records = self.client.read(piles.seq + 1, stop)
            if not records:
                break
            n += piles.feed(records, updates=updates, rebuild=self.rebuild)
        self.status.add("records", n)
        return n

    def poll_gaps(self) -> None:
        """Log gaps opened or closed and inputs quarantined since the last poll."""
        try:
            self._log_gaps(self.client.gaps())
            self._log_quarantine(self.client.stats())
        except Exception as exc:  # noqa: BLE001 - retried at the next poll
            if self.runtime.stopper.is_set():   # given up because the service stops
                return
            self.status.add("errors")
            self.runtime.log("poll failed", level="warning", error=f"{type(exc).__name__}: {exc}")

    def _log_gaps(self, gaps) -> None:
        for g in gaps:
            key = (g.get("gap_id"), g.get("closed_recorded_ns") is not None)
            if key in self.seen_gaps:
                continue
            self.seen_gaps.add(key)
            level = "INFO" if key[1] else "WARN"
            self.piles.log_text(f"gap {g.get('gap_id')} {'closed' if key[1] else 'open'}: "
                                f"{g.get('source')} epoch {g.get('epoch')} seq "
                                f"{g.get('first_seq')}..{g.get('last_seq')}", level)

    def _log_quarantine(self, stats) -> None:
        q = int(stats.get("quarantined", 0))
        if q > self.quarantined:
            self.piles.log_text(f"{q - self.quarantined} input(s) quarantined (total {q}: "
                                + ", ".join(f"{k} {v}" for k, v in
                                            (stats.get("quarantine_by_code") or {}).items())
                                + ")", "ERROR")
            self.quarantined = q

    def catch_up(self) -> None:
        """Everything committed, updating on the way; then "as known now" at the head."""
        head = self.client.head()["global_seq"]
        n = self.read_to(head, updates=True)
        for dash in self.piles:
            if dash.projection.stale:
                self.rebuild(dash)
            dash.update()
        self.status.add("updates", self.piles.updates)
        self.piles.flush_known_now()   # the history as known at the head; live from here on
        self.poll_gaps()
        self.runtime.log("caught up", records=n, head=head, updates=self.piles.updates,
                         **({"piles": ",".join(self.config.piles)} if len(self.piles) > 1
                            else {}))

    def run(self, heads: Inbox) -> None:
        """Catch up, announce, then follow the committed ``heads`` until stopped."""
        self.catch_up()
        self.runtime.announce()
        last_update = {dash.pile_id: time.monotonic() for dash in self.piles}
        last_poll = time.monotonic()
        stop = self.runtime.stopper
        while not stop.is_set():
            target = newest_head(heads, HEAD_WAIT_S)
            try:
                if target is not None and target > self.piles.seq:
                    self.read_to(target, updates=False)
                now = time.monotonic()
                if now - last_poll >= POLL_PERIOD_S:
                    self.poll_gaps()
                    last_poll = now
                for dash in self.piles:   # each pile at its own cadence
                    if (now - last_update[dash.pile_id] >= self.config.update_period_s
                            and self._update(dash)):
                        last_update[dash.pile_id] = now
            except Exception as exc:  # noqa: BLE001 - a failed read is retried later
                if stop.is_set():     # a read given up because the service stops
                    break
                self.status.add("errors")
                self.runtime.log("update failed", level="warning",
                                 error=f"{type(exc).__name__}: {exc}")
                stop.wait(RETRY_WAIT_S)

    def _update(self, dash: Dashboard) -> bool:
        """A live update of one pile (after a rebuild if its projection is stale)."""
        if dash.projection.stale:
            self.rebuild(dash)
        if dash.update():
            self.status.add("updates")
            return True
        return False

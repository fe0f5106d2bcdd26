"""``stockpile service hq``: the head office's mirror of every site's ledger.

Data flow, per site S of ``--sites``::

    stockpile/S/@ledger/head  --subscriber (live, over the mesh)-->  wake S's follower
    every --recheck: the follower asks anyway (a link that came back, a late start)
    follower:  q/head, then q/quarantine and q/gaps, then q/events from the mirror's
               head + 1 by the site's global seq, a page of --page-records at a time
           --> LedgerStore.mirror (ledger.mirror: the chain checked, one atomic batch)
           --> arrivals: (hq_seq, site, site_global_seq, arrived_ns) of every row

- **Mirrors.** Each site has an exact mirror (:mod:`ledger.mirror`) opened with
  :func:`ledger.open_ledger` at :func:`ledger.mirror.site_ledger` of ``--ledger``: a
  directory gives ``DIR/<site>.duckdb``, a ``postgresql://`` URL the schema
  ``site_<site>``.  A mirror's rows keep the site's own global seq; ``verify``,
  ``project`` and ``audit`` of a mirror answer as at the site.
- **No loss across an outage.** Catching up always reads the site ledger's queryables
  by the site's global seq, never a publisher's cache, so after a WAN outage of any
  length or a late start the mirror ends equal to the site ledger.  A site answer that
  was tampered with or does not continue the mirror is refused, logged, and asked again
  at the next re-check (nothing of it stored).
- **Behind.** Per site, the exact range of site global seqs the site holds and the mirror
  does not yet (``behind=first..last``, as far as the site's latest head known here
  says), logged when it changes and published with the status on
  ``stockpile/<hq site>/@hq/status`` (JSON ``{"sites": {S: {...}}}``).
- **Arrivals.** The head office's own order: one record per mirrored batch,
  ``(hq_seq_first, site, site_seq_first, rows, arrived_ns)`` in the table
  ``hq.arrivals`` (``DIR/hq/arrivals.duckdb`` for a directory, the schema ``hq`` of a
  PostgreSQL database), and the view ``hq.arrival_rows`` with one row per mirrored row:
  ``(hq_seq, site, site_global_seq, arrived_ns)``.
- **Isolation and memory.** One follower thread per site, each with its own queries and
  timeout: an unreachable site never holds the others up.  One page of rows in memory
  per site at a time (the quarantine and gap tables are read whole).  SIGTERM stops
  the followers between two pages.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

from ledger import open_ledger
from ledger.errors import LedgerError
from ledger.mirror import check_site, is_database_url, site_ledger
from ledger.records import Gap, QuarantineEntry
from ledger.store import LedgerStore
from ledger.wire import gap_from_json, head_from_json, quarantine_from_json
from services.ledger_client import LedgerClient, LedgerQueryError, LedgerUnavailable
from services.service import ServiceRuntime, Stopper, ZenohOptions, log

SERVICE = "hq"
DEFAULT_PAGE_RECORDS = 5_000
DEFAULT_RECHECK_S = 10.0
DEFAULT_QUERY_TIMEOUT_S = 30.0

_ARRIVALS_DDL = (
    "CREATE SCHEMA IF NOT EXISTS hq",
    "CREATE TABLE IF NOT EXISTS hq.arrivals (hq_seq_first BIGINT NOT NULL, "
    "site VARCHAR NOT NULL, site_seq_first BIGINT NOT NULL, rows BIGINT NOT NULL, "
    "arrived_ns BIGINT NOT NULL)",
    "CREATE OR REPLACE VIEW hq.arrival_rows AS SELECT hq_seq_first + i AS hq_seq, site, "
    "site_seq_first + i AS site_global_seq, arrived_ns FROM hq.arrivals "
    "CROSS JOIN LATERAL generate_series(0, rows - 1) AS t(i)",
)
_NEXT_HQ_SEQ = "SELECT coalesce(max(hq_seq_first + rows), 0) FROM hq.arrivals"
_LAST_OF_SITE = ("SELECT coalesce(max(site_seq_first + rows - 1), -1) FROM hq.arrivals "
                 "WHERE site = {p}")
_INSERT = "INSERT INTO hq.arrivals VALUES ({p}, {p}, {p}, {p}, {p})"


def status_key(site: str) -> str:
    """Where the head office publishes its status (``site``: the head office's own)."""
    return f"stockpile/{site}/@hq/status"


@dataclass(frozen=True)
class Config:
    """Options of the head-office service.

    Attributes
    ----------
    ledger_base : str
        A directory (a DuckDB mirror per site) or a ``postgresql://`` URL (a schema per
        site).
    sites : tuple of str
        The sites mirrored.
    page_records : int
        Most rows asked of a site ledger in one query.
    recheck_s : float
        Seconds between two checks of a site's head besides its publications.
    query_timeout_s : float
        Longest wait for a site ledger's answer, seconds.
    """

    site: str
    zenoh: ZenohOptions
    ledger_base: str
    sites: tuple[str, ...]
    page_records: int = DEFAULT_PAGE_RECORDS
    recheck_s: float = DEFAULT_RECHECK_S
    query_timeout_s: float = DEFAULT_QUERY_TIMEOUT_S
    status_period_s: float = 5.0

    def __post_init__(self) -> None:
        if not self.sites:
            raise ValueError("--sites names no site")
        for site in self.sites:
            check_site(site)
        if len(set(self.sites)) != len(self.sites):
            raise ValueError(f"--sites names a site twice: {','.join(self.sites)}")
        if self.site in self.sites:
            raise ValueError(f"the head office's own --site {self.site!r} is also in --sites")
        if self.page_records < 1:
            raise ValueError(f"--page-records must be >= 1, got {self.page_records}")
        if not (self.recheck_s > 0 and self.query_timeout_s > 0):
            raise ValueError("--recheck and --query-timeout must be > 0 s")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--ledger", required=True, metavar="DIR|URL",
                        help="the head office's ledgers: a directory (DIR/<site>.duckdb per "
                        "site) or a postgresql:// URL (a schema site_<site> per site)")
    parser.add_argument("--sites", required=True, metavar="S1,S2",
                        help="the sites to mirror, comma-separated")
    parser.add_argument("--page-records", type=int, default=DEFAULT_PAGE_RECORDS, metavar="N",
                        help=f"most rows per query of a site ledger (default "
                        f"{DEFAULT_PAGE_RECORDS})")
    parser.add_argument("--recheck", type=float, default=DEFAULT_RECHECK_S, metavar="S",
                        help="seconds between checks of each site's head besides its "
                        f"publications (default {DEFAULT_RECHECK_S:g})")
    parser.add_argument("--query-timeout", type=float, default=DEFAULT_QUERY_TIMEOUT_S,
                        metavar="S", help="longest wait for a site ledger's answer, seconds "
                        f"(default {DEFAULT_QUERY_TIMEOUT_S:g})")


def config_from_args(args: argparse.Namespace) -> Config:
    sites = tuple(s.strip() for s in args.sites.split(",") if s.strip())
    return Config(site=args.site, zenoh=ZenohOptions.from_args(args), ledger_base=args.ledger,
                  sites=sites, page_records=args.page_records, recheck_s=args.recheck,
                  query_timeout_s=args.query_timeout, status_period_s=args.status_period)


# -- arrivals ---------------------------------------------------------------------------------


def _without_schema(url: str) -> str:
    """A PostgreSQL URL without the ``schema`` parameter (the ledger's, not libpq's)."""
    parts = urlsplit(url)
    query = [(k, v) for k, v in parse_qsl(parts.query) if k != "schema"]
    return urlunsplit(parts._replace(query=urlencode(query)))


class Arrivals:
    """The head office's arrival order (``hq.arrivals``; see the module docstring).

    Written after each mirrored batch; a batch mirrored but not yet recorded (the process
    killed between the two) is recorded at the next start with that start's time
    (:meth:`reconcile`).  Thread-safe.
    """

    def __init__(self, base: str) -> None:
        self._lock = threading.Lock()
        if is_database_url(base):
            # deferred: psycopg is the PostgreSQL backend's dependency, not every install's
            import psycopg

            self._con = psycopg.connect(_without_schema(base), autocommit=True)
            self._p = "%s"
        else:
            # deferred: duckdb is heavy, and only a directory head office needs it here
            import duckdb

            path = Path(base) / "hq" / "arrivals.duckdb"
            path.parent.mkdir(parents=True, exist_ok=True)
            self._con = duckdb.connect(str(path))
            self._p = "?"
        for ddl in _ARRIVALS_DDL:
            self._con.execute(ddl)
        self._next = self._one(_NEXT_HQ_SEQ)

    def _one(self, sql: str, params: tuple = ()) -> int:
        return int(self._con.execute(sql.format(p=self._p), params).fetchone()[0])

    def record(self, site: str, site_seq_first: int, rows: int, arrived_ns: int) -> int:
        """Record ``rows`` rows of ``site`` from ``site_seq_first``; their first hq_seq."""
        with self._lock:
            first = self._next
            self._con.execute(_INSERT.format(p=self._p),
                              (first, site, site_seq_first, rows, arrived_ns))
            self._next += rows
            return first

    def reconcile(self, site: str, mirror_head: int) -> int:
        """Record what the mirror holds beyond the last recorded arrival of ``site`` (a
        batch mirrored just before a kill); the rows recorded now."""
        with self._lock:
            last = self._one(_LAST_OF_SITE, (site,))
        if mirror_head > last:
            self.record(site, last + 1, mirror_head - last, time.time_ns())
        return max(0, mirror_head - last)

    def close(self) -> None:
        with self._lock:
            self._con.close()


# -- one site ---------------------------------------------------------------------------------


class SiteFollower:
    """Keeps one site's mirror up with the site ledger (its own thread, :meth:`run`)."""

    def __init__(self, site: str, store: LedgerStore, client: LedgerClient,
                 arrivals: Arrivals, config: Config, stopper: Stopper, runtime: ServiceRuntime,
                 on_change) -> None:
        self.site, self.store, self.client, self.arrivals = site, store, client, arrivals
        self.config, self.stopper, self.runtime, self.on_change = config, stopper, runtime, on_change
        self.wake = threading.Event()
        self.site_head: int | None = None      # the site's latest head known here
        self.reachable: bool | None = None
        self.problem: str | None = None
        self.mirrored = 0
        self._behind: tuple[int, int] | None = None
        self._reported_head: int | None = None     # none yet: the first round reports
        self._next_quarantine_id = len(store.quarantine())

    # -- what others see ----------------------------------------------------------------

    def behind(self) -> tuple[int, int] | None:
        """The site global seqs the site holds and the mirror does not, as far as known."""
        mine = self.store.head().global_seq
        if self.site_head is None or self.site_head <= mine:
            return None
        return (mine + 1, self.site_head)

    def status(self) -> dict[str, Any]:
        behind = self.behind()
        return {"mirror_head": self.store.head().global_seq, "site_head": self.site_head,
                "behind": None if behind is None else list(behind),
                "reachable": self.reachable, "problem": self.problem,
                "mirrored": self.mirrored}

    def on_head(self, head: dict[str, Any]) -> None:
        """A head the site published (a Zenoh callback: note it and wake the thread)."""
        try:
            seq = int(head["global_seq"])
        except (KeyError, TypeError, ValueError):
            return
        if self.site_head is None or seq > self.site_head:
            self.site_head = seq
        self.wake.set()

    # -- the thread ---------------------------------------------------------------------

    def run(self) -> None:
        while not self.stopper.is_set():
            try:
                self.catch_up()
            except LedgerError as exc:       # the mirror refused the answer, or its database failed
                self._problem(f"{type(exc).__name__}: {exc}")
            except Exception as exc:  # noqa: BLE001 - logged; the follower asks again later
                self._problem(f"unexpected {type(exc).__name__}: {exc}")
            self._report()
            self.wake.wait(self.config.recheck_s)
            self.wake.clear()

    def catch_up(self) -> None:
        """Mirror everything the site holds beyond the mirror's head, page by page."""
        try:
            head = head_from_json(self.client.head()).global_seq
            pending = [q for q in map(quarantine_from_json, self.client.quarantine())
                       if q.quarantine_id >= self._next_quarantine_id]
            gaps = [gap_from_json(g) for g in self.client.gaps()]
        except (LedgerUnavailable, LedgerQueryError, ValueError) as exc:
            self._unreachable(exc)
            return
        self._reached()
        if self.site_head is None or head > self.site_head:
            self.site_head = head
        mine = self.store.head().global_seq
        if head < mine:
            self._problem(f"the site's head {head} is behind this mirror's {mine} (a site "
                          "ledger restored with a loss?); nothing mirrored")
            return
        self._report()                  # the range about to be fetched, before the pages
        while mine < head and not self.stopper.is_set():
            try:
                rows = self.client.read(mine + 1, head + 1, limit=self.config.page_records)
            except (LedgerUnavailable, LedgerQueryError) as exc:
                self._unreachable(exc)
                return
            if not rows:
                self._problem(f"the site answered no rows after {mine} below its head {head}")
                return
            pending = self._mirror(rows, pending, gaps)
            mine = rows[-1].global_seq
        if pending and not self.stopper.is_set() and mine == head:
            self._mirror([], [q for q in pending if q.after_global_seq <= mine], gaps)
        self.problem = None

    def _mirror(self, rows: list, pending: list[QuarantineEntry],
                gaps: list[Gap]) -> list[QuarantineEntry]:
        """Mirror one page and the entries placed up to its last row; the entries left."""
        last = rows[-1].global_seq if rows else self.store.head().global_seq
        n = 0
        while n < len(pending) and pending[n].after_global_seq <= last:
            n += 1
        self.store.mirror(rows, pending[:n], gaps)
        self._next_quarantine_id += n
        if rows:
            first = self.arrivals.record(self.site, rows[0].global_seq, len(rows), time.time_ns())
            self.mirrored += len(rows)
            assert self.runtime.status is not None
            self.runtime.status.add("mirrored", len(rows))
            log(SERVICE, "mirrored", site=self.site, first=rows[0].global_seq, last=last,
                rows=len(rows), quarantined=n, hq_seq_first=first)
        return pending[n:]

    # -- state changes ------------------------------------------------------------------

    def _reached(self) -> None:
        if self.reachable is not True:
            log(SERVICE, "site reachable", site=self.site)
        self.reachable = True

    def _unreachable(self, exc: Exception) -> None:
        if self.reachable is not False:
            log(SERVICE, "site unreachable", level="warning", site=self.site,
                error=str(exc).splitlines()[0])
            assert self.runtime.status is not None
            self.runtime.status.add("unreachable")
        self.reachable = False

    def _problem(self, text: str) -> None:
        if text != self.problem:
            log(SERVICE, "site refused", level="error", site=self.site, problem=text)
            assert self.runtime.status is not None
            self.runtime.status.add("refused")
        self.problem = text

    def _report(self) -> None:
        """Log the ``behind`` range when it changed, and ``caught up`` when the mirror
        reached the site's head (again); publish the status."""
        behind = self.behind()
        mine = self.store.head().global_seq
        if behind is None:
            if self.reachable and (self._behind is not None or mine != self._reported_head):
                log(SERVICE, "caught up", site=self.site, head=mine)
                self._reported_head = mine
        elif behind != self._behind:
            log(SERVICE, "behind", site=self.site, behind=f"{behind[0]}..{behind[1]}",
                head=mine)
        self._behind = behind
        self.on_change()


# -- main ---------------------------------------------------------------------------------


def _open_mirrors(config: Config) -> dict[str, LedgerStore]:
    """Every site's mirror opened for writing (a directory is created when missing)."""
    if not is_database_url(config.ledger_base):
        Path(config.ledger_base).mkdir(parents=True, exist_ok=True)
    elif importlib.util.find_spec("ledger.postgres_store") is None:
        raise ValueError("a postgresql:// head office needs the PostgreSQL ledger backend "
                         "(ledger/postgres_store.py), which this install does not have")
    stores: dict[str, LedgerStore] = {}
    try:
        for site in config.sites:
            stores[site] = open_ledger(site_ledger(config.ledger_base, site))
    except BaseException:
        for store in stores.values():
            store.close()
        raise
    return stores


def main(config: Config, *, stopper: Stopper | None = None) -> int:
    """Run the head office until SIGINT/SIGTERM (or ``stopper``); return an exit code."""
    try:
        stores = _open_mirrors(config)
    except (LedgerError, OSError, ValueError) as exc:
        log(SERVICE, "cannot open the mirrors", level="error", ledger=config.ledger_base,
            error=str(exc).splitlines()[0])
        return 2
    try:
        arrivals = Arrivals(config.ledger_base)
    except Exception as exc:  # noqa: BLE001 - any database's error is one line here
        log(SERVICE, "cannot open the arrivals table", level="error", ledger=config.ledger_base,
            error=str(exc).splitlines()[0])
        for store in stores.values():
            store.close()
        return 2
    runtime = ServiceRuntime(SERVICE, config.site, config.zenoh, status_period_s=config.status_period_s,
                             stopper=stopper)
    try:
        runtime.open(rate_of="mirrored", error_keys=("refused", "unreachable"), announce=False)
        return _serve(config, stores, arrivals, runtime)
    finally:
        runtime.close()
        arrivals.close()
        for store in stores.values():
            store.close()


def _serve(config: Config, stores: dict[str, LedgerStore], arrivals: Arrivals,
           runtime: ServiceRuntime) -> int:
    session, stopper, status = runtime.session, runtime.stopper, runtime.status
    assert stopper is not None and status is not None
    publisher = session.declare_publisher(status_key(config.site))
    lock = threading.Lock()
    followers: dict[str, SiteFollower] = {}

    def publish() -> None:
        with lock:
            data = {"sites": {s: f.status() for s, f in followers.items()}}
        publisher.put(json.dumps(data).encode())

    for site, store in stores.items():
        late = arrivals.reconcile(site, store.head().global_seq)
        if late:
            log(SERVICE, "arrivals recorded late", level="warning", site=site, rows=late)
        client = LedgerClient(session, site, timeout_s=config.query_timeout_s, stop=stopper.event)
        followers[site] = SiteFollower(site, store, client, arrivals, config, stopper, runtime,
                                       publish)
    subscribers = [LedgerClient(session, site).follow_head(f.on_head)
                   for site, f in followers.items()]
    status.on_status = lambda _fields: publish()
    threads = [threading.Thread(target=f.run, name=f"hq-{site}", daemon=True)
               for site, f in followers.items()]
    for thread in threads:
        thread.start()
    runtime.log("mirroring", ledger=config.ledger_base, sites=",".join(config.sites),
                heads=",".join(f"{s}:{st.head().global_seq}" for s, st in stores.items()),
                pid=os.getpid())
    runtime.announce()
    stopper.wait()
    for follower in followers.values():
        follower.wake.set()
    for thread in threads:
        thread.join(config.query_timeout_s + 5.0)
    status.on_status = None
    for subscriber in subscribers:
        subscriber.undeclare()
    for site, follower in followers.items():
        behind = follower.behind()
        runtime.log("final", site=site, head=follower.store.head().global_seq,
                    site_head=follower.site_head if follower.site_head is not None else "-",
                    behind="-" if behind is None else f"{behind[0]}..{behind[1]}")
    publish()
    publisher.undeclare()
    return 0

"""Shared parts of the fault-injection cases: a real yard, countable producers, the check.

A :class:`Yard` is what a site runs, as real processes on loopback (scouting off, free
ports), over mutual TLS with the access control generated from a throw-away site PKI (as
``stockpile run`` and the demo run): a ``stockpile service router`` process (so a case can
SIGKILL and restart it), ``stockpile run --config yard.toml`` supervising the ledger
service and the other services named, and producers (``python -m services.loadgen``, or
the wall-clock producer of ``tests/faults/wall_producer.py``) publishing as PLCs.

Every producer writes a report of exactly what it published: per stream ``source``,
``epoch`` and ``count`` (sequences ``0..count-1``) and the monotonic publish moment of
every ``STAMP_EVERY``-th event.  :meth:`Yard.finish` waits until the ledger holds every
published event or an open gap for it, stops everything (the ledger last), runs
``stockpile ledger verify`` on the file and checks it against the reports
(:func:`check_ledger`): every published event present exactly once or inside exactly one
open gap record, nothing else missing, nothing duplicated.  The case's row (fault, events
published, events ledgered, events in gaps, seconds to recover) is printed and appended
to ``build/faults/results.jsonl`` (``$STOCKPILE_FAULTS_RESULTS``); ``tests/faults/table.py``
prints the rows as a markdown table.

Seconds to recover: from the fault's end until the ledger is caught up again, i.e. holds
(stored or as a gap) every event its producers published more than ``CAUGHT_UP_LAG_S``
before, and stays so for ``STAY_CAUGHT_UP_S``; measured from a poller that asks the
ledger service for its per-source counts and open gaps every ``POLL_PERIOD_S`` (its polls
are written to ``polls.jsonl`` in the case's directory).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from bisect import bisect_right
from dataclasses import dataclass, field
from pathlib import Path

from ledger import open_ledger
from services.ledger_client import LedgerClient, LedgerQueryError, LedgerUnavailable
from services.service import ZenohOptions, open_session
from zenoh_helpers import PYTHON, free_port, log_lines, site_pki, stockpile, stop, wait_until

SITE = "faults"
ROOT = Path(__file__).resolve().parents[2]
RESULTS_ENV = "STOCKPILE_FAULTS_RESULTS"
DEFAULT_RESULTS = ROOT / "build" / "faults" / "results.jsonl"
#: producers stamp the monotonic publish moment of every STAMP_EVERY-th event
STAMP_EVERY = 20
#: the ledger counts as caught up when it holds what was published this long before, s
CAUGHT_UP_LAG_S = 1.0
#: ... and stays so for this long after it caught up (or to the end of the run), s
STAY_CAUGHT_UP_S = 5.0
#: period of the poller that follows the ledger's counts, s
POLL_PERIOD_S = 0.25
#: how long the ledger may take to account for everything once the producers are done, s
DRAIN_TIMEOUT_S = 180.0
#: the localizer's machine and certificate in every yard
MACHINE = "bwr1"
SERVICE_CERTS = {"ledger": ("ledger", "ledger"), "localizer": (f"{MACHINE}.localizer", "localizer"),
                 "recorder": ("recorder", "recorder"), "projector": ("projector", "projector"),
                 "dashboard": ("dashboard", "dashboard"),
                 "scanner": (f"{MACHINE}.scanner", "scanner"), "gnss": (f"{MACHINE}.gnss", "gnss")}
#: the pile the projector and the dashboard of a yard follow
PILE = "P1"


def results_path() -> Path:
    return Path(os.environ.get(RESULTS_ENV) or DEFAULT_RESULTS)


@dataclass
class Stream:
    """What one producer published on one (source, epoch): sequences ``0..count-1``."""

    source: str
    epoch: int
    count: int
    stamps: list[tuple[int, float]] = field(default_factory=list)  # (seq, monotonic s)

    def published_by(self, t_s: float) -> int:
        """Events published at or before monotonic time ``t_s`` (to ``STAMP_EVERY``)."""
        if not self.stamps:
            return self.count
        i = bisect_right([t for _n, t in self.stamps], t_s)
        return 0 if i == 0 else min(self.count, self.stamps[i - 1][0] + 1)


@dataclass
class Producer:
    """One producer process and its report file."""

    name: str
    process: subprocess.Popen
    report_path: Path
    log_path: Path

    def streams(self) -> list[Stream]:
        data = json.loads(self.report_path.read_text())
        items = data["streams"] if "streams" in data else [data]
        return [Stream(d["source"], int(d["epoch"]), int(d["count"]),
                       [(int(n), float(t)) for n, t in d.get("stamps", [])]) for d in items]


class RouterProcess:
    """``stockpile service router`` on a fixed TLS endpoint; SIGKILL and restart."""

    def __init__(self, base: Path, pki: Path, endpoint: str) -> None:
        self.base, self.pki, self.endpoint = base, pki, endpoint
        self.starts = 0
        self.process: subprocess.Popen | None = None

    def start(self) -> None:
        self.starts += 1
        log = self.base / f"router{self.starts}.log"
        self.process = stockpile("service", "router", "--site", SITE, "--listen", self.endpoint,
                                 "--tls-dir", str(self.pki), "--tls-name", "router",
                                 stderr_path=log)
        wait_until(lambda: any(r.get("msg") == "routing" for r in log_lines(log))
                   or self.process.poll() is not None, 60, "the router to listen")
        assert self.process.poll() is None, log.read_text()[-2000:]

    def kill(self) -> None:
        assert self.process is not None and self.process.poll() is None
        self.process.kill()
        assert self.process.wait(30) == -signal.SIGKILL


class Poller:
    """Asks the ledger service for its per-source counts and open gaps every
    ``period_s``; keeps ``(monotonic s at the query, {source: stored + in gaps})``."""

    def __init__(self, client: LedgerClient, period_s: float = POLL_PERIOD_S) -> None:
        self.client, self.period_s = client, period_s
        self.samples: list[tuple[float, dict[str, int]]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ledger-poller", daemon=True)

    def accounted(self) -> dict[str, int] | None:
        """``{source: events stored + events in open gaps}``; None while unavailable or
        while a query times out (a ledger busy catching up)."""
        try:
            stats = self.client.stats()
            gaps = self.client.gaps(open_only=True)
        except (LedgerUnavailable, LedgerQueryError):
            return None
        out = {s: int(n) for s, n in stats["per_source"].items()}
        for g in gaps:
            out[g["source"]] = out.get(g["source"], 0) + g["last_seq"] - g["first_seq"] + 1
        return out

    def _run(self) -> None:
        while not self._stop.is_set():
            t = time.monotonic()
            counts = self.accounted()
            if counts is not None:
                self.samples.append((t, counts))
            self._stop.wait(self.period_s)   # the poll period, not a synchronisation

    def start(self) -> "Poller":
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(30)

    def recovered_at(self, fault_end_s: float, streams: list[Stream]) -> float | None:
        """The first poll at or after ``fault_end_s`` from which the ledger stays caught
        up for ``STAY_CAUGHT_UP_S`` (or to the last poll): at each poll it holds every
        event published ``CAUGHT_UP_LAG_S`` before it, per source.  None if never.  (A
        producer that was stopped publishes what its schedule owes just after the fault's
        end: the ledger is caught up only once it holds that too.)"""
        by_source: dict[str, list[Stream]] = {}
        for s in streams:
            by_source.setdefault(s.source, []).append(s)

        def caught_up(t: float, counts: dict[str, int]) -> bool:
            return all(counts.get(src, 0) >= sum(s.published_by(t - CAUGHT_UP_LAG_S)
                                                 for s in group)
                       for src, group in by_source.items())

        start = None
        for t, counts in self.samples:
            if t < fault_end_s:
                continue
            if not caught_up(t, counts):
                start = None
                continue
            if start is None:
                start = t
            if t - start >= STAY_CAUGHT_UP_S:
                return start
        return start


class Yard:
    """A router process, ``stockpile run`` with ``services``, producers; see the module doc.

    ``ledger_clock`` is the ledger's ``--clock`` (``wall`` or ``events``); the recorder
    splits its recording hourly (``PATH-0000.mcap``, ...) unless ``recorder_split`` is
    false (one file, ``record/site.mcap``).  ``devices`` gives the serial paths of the
    ``scanner`` and ``gnss`` services (``tests/faults/serial_feeder.py``); the projector
    and the dashboard follow pile :data:`PILE` (the dashboard into ``dashboard.rrd``).
    """

    def __init__(self, base: Path, *, services: tuple[str, ...] = ("ledger",),
                 producers: int = 2, ledger_clock: str = "wall",
                 restart_delay_s: float = 0.5, recorder_split: bool = True,
                 poll_period_s: float = POLL_PERIOD_S,
                 devices: dict[str, str] | None = None) -> None:
        self.poll_period_s = poll_period_s
        self.base = Path(base)
        self.base.mkdir(parents=True, exist_ok=True)
        self.services = services
        self.producer_names = [f"load{i}" for i in range(producers)]
        members = {"watch": "auditor", "tap": "recorder",
                   **{n: "plc" for n in self.producer_names}}
        members.update({cert: role for cert, role in
                        (SERVICE_CERTS[s] for s in services)})
        self.pki = site_pki(self.base / "pki", SITE, members)
        self.endpoint = f"tls/127.0.0.1:{free_port()}"
        self.ledger_path = self.base / "ledger.duckdb"
        self.run_log = self.base / "run.log"
        self.router = RouterProcess(self.base, self.pki, self.endpoint)
        self.devices = devices or {}
        self.config = self._write_config(ledger_clock, restart_delay_s, recorder_split)
        self.run: subprocess.Popen | None = None
        self.producers: list[Producer] = []
        self.session = None
        self.client: LedgerClient | None = None
        self.poller: Poller | None = None

    def _write_config(self, ledger_clock: str, restart_delay_s: float,
                      recorder_split: bool) -> Path:
        tables = {
            "ledger": f'[services.ledger]\nledger = "{self.ledger_path}"\nclock = '
                      f'"{ledger_clock}"\nstatus_period = 1\n',
            "localizer": f'[services.localizer]\nmachine = "{MACHINE}"\n'
                         f'tls_name = "{MACHINE}.localizer"\nstatus_period = 1\n',
            "recorder": f'[services.recorder]\nout = "{self.base / "record" / "site.mcap"}"\n'
                        + ('split_duration = "1h"\n' if recorder_split else "")
                        + "status_period = 1\n",
            "projector": f'[services.projector]\npile = "{PILE}"\nstatus_period = 1\n',
            "dashboard": f'[services.dashboard]\npile = "{PILE}"\n'
                         f'out = "{self.base / "dashboard.rrd"}"\nstatus_period = 1\n',
            "scanner": f'[services.scanner]\ndevice = "{self.devices.get("scanner")}"\n'
                       f'source = "{MACHINE}.scanner"\ntls_name = "{MACHINE}.scanner"\n'
                       "status_period = 1\n",
            "gnss": f'[services.gnss]\ndevice = "{self.devices.get("gnss")}"\n'
                    f'source = "{MACHINE}.gnss"\ntls_name = "{MACHINE}.gnss"\n'
                    "status_period = 1\n",
        }
        (self.base / "record").mkdir(exist_ok=True)
        text = (f'site = "{SITE}"\nrestart_delay_s = {restart_delay_s}\n[zenoh]\nmode = "client"\n'
                f'connect = ["{self.endpoint}"]\n[tls]\ndir = "{self.pki}"\n'
                + "".join(tables[s] for s in self.services))
        path = self.base / "yard.toml"
        path.write_text(text)
        return path

    # -- starting ------------------------------------------------------------------------

    def start(self) -> "Yard":
        self.router.start()
        self.run = stockpile("run", "--config", str(self.config), stderr_path=self.run_log)
        self.session = open_session(ZenohOptions(mode="client", connect=(self.endpoint,),
                                                 tls_dir=str(self.pki), tls_name="watch"))
        self.client = LedgerClient(self.session, SITE, timeout_s=5)
        wait_until(lambda: self._answers() or self.run.poll() is not None, 90,
                   "the ledger service to answer")
        assert self.run.poll() is None, self.run_log.read_text()[-3000:]
        for service in self.services:
            wait_until(lambda: self.ready_count(service) >= 1, 90, f"the {service} to be ready")
        self.poller = Poller(self.client, self.poll_period_s).start()
        return self

    def _answers(self) -> bool:
        try:
            self.client.head()
            return True
        except LedgerUnavailable:
            return False

    def start_loadgens(self, *, rate_hz: float, duration_s: float,
                       cache: int = 50_000) -> list[Producer]:
        """One ``services.loadgen`` per producer name, each ``rate_hz`` for ``duration_s``."""
        out = []
        for i, name in enumerate(self.producer_names):
            report, log = self.base / f"{name}.json", self.base / f"{name}.log"
            process = subprocess.Popen(
                [PYTHON, "-m", "services.loadgen", "--site", SITE, "--source", name,
                 "--rate", str(rate_hz), "--duration", str(duration_s), "--cache", str(cache),
                 "--linger", "900", "--wait-subscriber", "60", "--report", str(report),
                 "--stamp-every", str(STAMP_EVERY), "--seed", str(i),
                 *self.client_args(name)],
                stderr=open(log, "w"), stdout=subprocess.DEVNULL)
            out.append(Producer(name, process, report, log))
        self.producers += out
        return out

    def client_args(self, name: str) -> list[str]:
        return ZenohOptions(mode="client", connect=(self.endpoint,), tls_dir=str(self.pki),
                            tls_name=name).to_argv()

    # -- what `stockpile run` says ---------------------------------------------------------

    def started_pids(self, name: str) -> list[int]:
        return [int(r["pid"]) for r in log_lines(self.run_log)
                if r.get("service") == "run" and r.get("msg") == "started"
                and r.get("name") == name]

    def ready_count(self, service: str) -> int:
        """``ready`` lines of ``service`` (each start of it logs one) in the run's log."""
        return sum(1 for r in log_lines(self.run_log)
                   if r.get("service") == service and r.get("msg") == "ready")

    def kill_service(self, name: str, timeout_s: float = 90.0) -> tuple[float, float]:
        """SIGKILL service ``name``; wait until ``stockpile run`` restarted it and it is
        ready again.  Returns (monotonic s of the kill, seconds until ready again)."""
        pids, ready = self.started_pids(name), self.ready_count(name)
        t_kill = time.monotonic()
        os.kill(pids[-1], signal.SIGKILL)
        wait_until(lambda: len(self.started_pids(name)) > len(pids)
                   and self.ready_count(name) > ready, timeout_s,
                   f"`stockpile run` to restart the {name} and the new one to be ready")
        return t_kill, time.monotonic() - t_kill

    # -- the end -------------------------------------------------------------------------

    def reports(self, timeout_s: float = 600.0) -> list[Stream]:
        wait_until(lambda: all(p.report_path.exists() or p.process.poll() is not None
                               for p in self.producers), timeout_s, "the producers' reports")
        for p in self.producers:
            assert p.report_path.exists(), (f"{p.name} exited {p.process.returncode}: "
                                            + p.log_path.read_text()[-2000:])
        return [s for p in self.producers for s in p.streams()]

    def finish(self, fault: str, fault_ends_s: list[float], *, extra: dict | None = None,
               drain_timeout_s: float = DRAIN_TIMEOUT_S) -> dict:
        """Wait for the producers' reports and the ledger to account for them; stop all;
        check the file (:func:`check_ledger`); write and return the case's row."""
        streams = self.reports()
        expected: dict[str, int] = {}
        for s in streams:
            expected[s.source] = expected.get(s.source, 0) + s.count
        wait_until(lambda: all(self.poller.samples and self.poller.samples[-1][1].get(src, 0)
                               >= n for src, n in expected.items()), drain_timeout_s,
                   "the ledger to hold every published event or a gap for it", interval_s=0.5)
        with open(self.base / "polls.jsonl", "w", encoding="utf-8") as f:   # for a post-mortem
            for t, counts in self.poller.samples:
                published: dict[str, int] = {}
                for s in streams:
                    published[s.source] = published.get(s.source, 0) + s.published_by(t)
                f.write(json.dumps({"t_s": t, "accounted": counts, "published": published})
                        + "\n")
        recover = []
        for end in fault_ends_s:
            at = self.poller.recovered_at(end, streams)
            assert at is not None, f"the ledger never caught up after the fault ending at {end}"
            recover.append(at - end)
        self.close()
        counts = check_ledger(self.ledger_path, streams)
        row = {"fault": fault, "published": counts["published"], "ledgered": counts["ledgered"],
               "gap_events": counts["gap_events"], "gaps": counts["gaps"],
               "recover_s": round(max(recover), 2) if recover else None,
               "recover_s_each": [round(r, 2) for r in recover], **(extra or {})}
        write_row(row)
        return row

    def close(self) -> None:
        """Stop the poller, the producers, ``stockpile run`` (ledger last) and the router;
        every exit must be clean."""
        if self.poller is not None:
            self.poller.close()
            self.poller = None
        if self.session is not None:
            self.session.close()
            self.session = None
        codes = {}
        for p in self.producers:
            codes[p.name] = stop(p.process, 60)
        if self.run is not None:
            codes["run"] = stop(self.run, 120)
        if self.router.process is not None:
            codes["router"] = stop(self.router.process, 30)
        bad = {k: c for k, c in codes.items() if c != 0}
        assert not bad, f"unclean exits {bad}; see {self.base}"

    def kill_all(self) -> None:
        """On a failing case: kill whatever still runs (no clean stop to wait for)."""
        procs = [p.process for p in self.producers] + [self.run, self.router.process]
        for proc in procs:
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in procs:
            if proc is not None:
                try:
                    proc.wait(60)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        if self.poller is not None:
            self.poller.close()
        if self.session is not None:
            self.session.close()

    def __enter__(self) -> "Yard":
        return self

    def __exit__(self, exc_type, *rest) -> None:
        if exc_type is not None:
            self.kill_all()


def check_ledger(path: Path, streams: list[Stream]) -> dict[str, int]:
    """The closing check: ``stockpile ledger verify`` passes, and each stream's events
    are in the file exactly once or inside exactly one open gap of that (source, epoch);
    nothing else of these sources is stored.  Streams the file row by row (a bitmap per
    stream), so a soak's millions of events fit.  Returns the counts of the row."""
    done = subprocess.run([PYTHON, "-m", "stockpile.cli", "ledger", "verify", "--ledger",
                           str(path)], capture_output=True, text=True, timeout=3600)
    assert done.returncode == 0, f"ledger verify failed: {done.stdout}{done.stderr}"
    published = ledgered = gap_events = gaps = 0
    with open_ledger(path, read_only=True) as store:
        open_gaps = store.gaps(open_only=True)
        for source in sorted({s.source for s in streams}):
            epochs = {s.epoch: s.count for s in streams if s.source == source}
            assert len(epochs) == sum(s.source == source for s in streams), \
                f"{source}: two producers on one epoch"
            seen = {epoch: bytearray(count) for epoch, count in epochs.items()}
            for r in store.read(sources=[source]):
                assert r.epoch in seen, f"{source}: an unknown epoch {r.epoch}"
                assert 0 <= r.seq < epochs[r.epoch], f"{source}/{r.epoch}: seq {r.seq} out of range"
                assert not seen[r.epoch][r.seq], f"{source}/{r.epoch}: seq {r.seq} twice"
                seen[r.epoch][r.seq] = 1
            for epoch, count in epochs.items():
                marks = seen[epoch]
                in_gap = bytearray(count)
                for g in open_gaps:
                    if (g.source, g.epoch) != (source, epoch):
                        continue
                    assert 0 <= g.first_seq <= g.last_seq < count, f"{source}: gap {g} out of range"
                    for q in range(g.first_seq, g.last_seq + 1):
                        assert not in_gap[q], f"{source}: overlapping gaps at {q}"
                        assert not marks[q], f"{source}: gap {g} over a stored event {q}"
                        in_gap[q] = 1
                    gaps += 1
                stored, gapped = sum(marks), sum(in_gap)
                assert stored + gapped == count, (f"{source}/{epoch}: {count - stored} missing, "
                                                  f"{gapped} in gaps: lost silently")
                published += count
                ledgered += stored
                gap_events += gapped
    return {"published": published, "ledgered": ledgered, "gap_events": gap_events,
            "gaps": gaps}


def write_row(row: dict) -> None:
    """Print the case's row and append it to the results file."""
    print("fault row: " + json.dumps(row))
    path = results_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(row) + "\n")

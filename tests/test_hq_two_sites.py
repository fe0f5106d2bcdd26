"""Two yards and a head office: every site's ledger mirrored across a WAN outage.

Real processes over mutual TLS on loopback (scouting off, free ports): per site a
``stockpile service router`` (its own site PKI, linked to the head office's router with
``--uplink`` and an uplink certificate the head office issued) and a ``stockpile service
ledger``; the head office's router (its own PKI) and ``stockpile service hq``.  Each site
is fed a short simulated yard (the demo scenario cut down to one lot, two passes and three
cuts, a seed per site; the sensor streams left out) by a producer with one AdvancedPublisher per key, in
three parts:

1. both sites linked: the head office catches up with both;
2. the first site's link cut (its router restarted without ``--uplink``) while both keep
   appending (the first one also a malformed input, quarantined): the head office reports
   the site unreachable and mirrors nothing of it, the second site goes on;
3. the link restored (the router restarted with ``--uplink``): the head office catches up.

At the end the mirrors hold exactly the site ledgers (export lines, quarantine and gaps
identical, ``verify`` ok), the head office's last status has no ``behind`` range, and
``project`` of each pile at the head office (``--site``) equals the site's answer.  Then a
second head office, started after both sites finished, catches up fully from nothing.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
import uuid
from dataclasses import replace
from pathlib import Path

import pytest
import zenoh

from ledger import open_ledger
from ledger.mirror import is_database_url, site_ledger
from schemas.events import encode_attachment, key_expr
from schemas.jsonl import decode_line, event_line
from security.pki import init_ca, issue
from services.ledger_client import LedgerClient, LedgerQueryError, LedgerUnavailable
from services.publishing import declare_ledger_publisher
from services.acl import access_control
from services.router import Uplink, load_members, site_router_config
from services.service import ZenohOptions, open_session
from sim.runner import Simulation
from sim.scenario import demo
from stockpile.run_config import ConfigError, load_config
from zenoh_helpers import PYTHON, free_port, log_lines, site_pki, stockpile, stop, wait_until
from zenoh_helpers import stop_all as stop_each

#: site -> seed of its simulated yard
SITES = {"mine": 11, "port": 12}
HQ = "hq"
#: sensor streams left out of the fed events (thousands an hour; the piles' passes, cuts,
#: lots and assays are what the head office's reads are about)
LEFT_OUT = {"joint_reading", "location_fix", "joint_estimate", "frame_transform", "scan"}
WAIT_S = 90.0


@pytest.fixture(scope="module")
def yard_events(tmp_path_factory) -> dict[str, list]:
    """Each site's events: a short demo yard with its own seed (one lot in two passes,
    three cuts, the lab's assays; sensors at low rates), run to its last assay."""
    base = demo()
    scenario = replace(base, lots=base.lots[:1], passes_per_lot=2, pass_duration_s=200.0,
                       scan_hz=1.0, encoder_hz=1.0, gnss_hz=0.2, idle_hz=0.01,
                       cuts_per_bench=(3,))
    out = {}
    for site, seed in SITES.items():
        folder = tmp_path_factory.mktemp(f"sim-{site}")
        Simulation(scenario, seed, folder).run()
        events = [decode_line(line) for line in (folder / "events.jsonl").open()]
        out[site] = [e for e in events if e.type not in LEFT_OUT]
        types = {e.type for e in out[site]}
        assert {"reclaim_cut", "assay", "stack_started"} <= types, types
    return out


class Feeder:
    """A site's producers: one AdvancedPublisher (cache, BLOCK) per key, on a replay
    certificate's session."""

    def __init__(self, session, site: str) -> None:
        self.session, self.site = session, site
        self.publishers: dict[str, object] = {}

    def publish(self, events) -> None:
        for e in events:
            key = key_expr(self.site, e.type, e.source)
            if key not in self.publishers:
                self.publishers[key] = declare_ledger_publisher(self.session, key)
            self.publishers[key].put(e.payload, attachment=encode_attachment(
                e.epoch, e.seq, e.valid_time_ns, e.signer, e.signature))

    def close(self) -> None:
        for publisher in self.publishers.values():
            publisher.undeclare()


class Network:
    """The PKIs, routers, ledgers and head offices of the test (real processes)."""

    def __init__(self, base: Path) -> None:
        self.base = base
        self.hq_pki = base / "hq-pki"
        init_ca(HQ, self.hq_pki)
        issue(self.hq_pki, "router", "hq.router")
        issue(self.hq_pki, "hq", "hq")
        self.hq_endpoint = f"tls/127.0.0.1:{free_port()}"
        self.endpoints, self.pkis, self.links = {}, {}, {}
        for site in SITES:
            self.pkis[site] = site_pki(base / f"{site}-pki", site,
                                       {"ledger": "ledger", "feeder": "replay", "audit": "auditor"})
            self.links[site] = base / f"{site}-uplink"
            issue(self.hq_pki, "uplink", f"{site}.router", out_dir=self.links[site])
            self.endpoints[site] = f"tls/127.0.0.1:{free_port()}"
        self.processes: list[subprocess.Popen] = []
        self.routers: dict[str, subprocess.Popen] = {}
        self.starts = 0

    def _start(self, name: str, *args: str) -> tuple[subprocess.Popen, Path]:
        self.starts += 1
        log = self.base / f"{self.starts:02d}-{name}.log"
        process = stockpile(*args, stderr_path=log)
        self.processes.append(process)
        return process, log

    def _router(self, site: str, pki: Path, name: str, endpoint: str, *extra: str):
        process, log = self._start(f"router-{site}", "service", "router", "--site", site,
                                   "--listen", endpoint, "--tls-dir", str(pki), "--tls-name",
                                   name, *extra)
        wait_until(lambda: any(r.get("msg") == "routing" for r in log_lines(log))
                   or process.poll() is not None, 60, f"the {site} router to listen")
        assert process.poll() is None, log.read_text()[-3000:]
        return process

    def hq_router(self) -> None:
        self._router(HQ, self.hq_pki, "hq.router", self.hq_endpoint)

    def site_router(self, site: str, *, linked: bool) -> None:
        uplink = ["--uplink", self.hq_endpoint, "--uplink-tls", str(self.links[site])]
        self.routers[site] = self._router(site, self.pkis[site], "router", self.endpoints[site],
                                          *(uplink if linked else []))

    def cut(self, site: str, *, linked: bool) -> None:
        """Restart a site's router, with or without its link to the head office."""
        assert stop(self.routers[site]) == 0
        self.site_router(site, linked=linked)

    def ledger(self, site: str) -> None:
        self._start(f"ledger-{site}", "service", "ledger", "--site", site, "--ledger",
                    str(self.base / f"{site}.duckdb"), "--mode", "client", "--connect",
                    self.endpoints[site], "--tls-dir", str(self.pkis[site]), "--tls-name",
                    "ledger")

    def head_office(self, ledgers: str) -> tuple[subprocess.Popen, Path]:
        return self._start("hq", "service", "hq", "--site", HQ, "--ledger", str(ledgers),
                           "--sites", ",".join(SITES), "--recheck", "1", "--query-timeout",
                           "5", "--status-period", "1", "--page-records", "700", "--mode", "client", "--connect",
                           self.hq_endpoint, "--tls-dir", str(self.hq_pki), "--tls-name", "hq")

    def session(self, site: str, name: str):
        return open_session(ZenohOptions(mode="client", connect=(self.endpoints[site],),
                                         tls_dir=str(self.pkis[site]), tls_name=name))

    def stop_all(self) -> list[int]:
        """Stop what still runs: the services (newest first), then the routers."""
        routers = [p for p in self.processes if "router" in p.args]
        ordered = [p for p in reversed(self.processes) if p not in routers] + routers[::-1]
        return stop_each(*[p for p in ordered if p.poll() is None])


def _head(client: LedgerClient) -> int | None:
    try:
        return int(client.head()["global_seq"])
    except (LedgerUnavailable, LedgerQueryError):
        return None


def _site_holds(client: LedgerClient, rows: int, quarantined: int) -> bool:
    try:
        return (_head(client) == rows - 1 and len(client.quarantine()) == quarantined)
    except (LedgerUnavailable, LedgerQueryError):
        return False


def _lines(log: Path, msg: str, site: str, after: int = 0) -> list[dict]:
    return [r for r in log_lines(log)[after:] if r.get("msg") == msg and r.get("site") == site]


def _caught_up(log: Path, site: str, head: int) -> bool:
    return any(int(r["head"]) == head for r in _lines(log, "caught up", site))


def _export(path: str) -> list[str]:
    with open_ledger(path, read_only=True) as store:
        return [event_line(row) for row in store.read()]


def _cli(*args: str) -> str:
    done = subprocess.run([PYTHON, "-m", "stockpile.cli", *args], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def _check_mirrors(network: Network, ledgers: str, *, reads: bool = True) -> None:
    """Every mirror holds exactly its site's ledger; with ``reads``, ``project`` and
    ``audit assays`` at the head office answer as at the site."""
    for site in SITES:
        site_path = str(network.base / f"{site}.duckdb")
        mirror_path = site_ledger(ledgers, site)
        assert _export(mirror_path) == _export(site_path)
        with open_ledger(site_path, read_only=True) as a, \
                open_ledger(mirror_path, read_only=True) as b:
            assert b.head() == a.head() and b.quarantine() == a.quarantine()
            assert b.gaps() == a.gaps() and not a.gaps(open_only=True)
            report = b.verify()
            assert report.ok and report.rows_checked == a.head().global_seq + 1, report
        if not reads:
            continue
        at_site = _cli("project", "--ledger", site_path, "--pile", "P1", "--json")
        at_hq = _cli("project", "--ledger", str(ledgers), "--site", site, "--pile", "P1",
                     "--json")
        assert json.loads(at_hq) == json.loads(at_site)
    if not reads:
        return
    together = json.loads(_cli("audit", "assays", "--ledger", str(ledgers), "--json"))
    alone = {site: json.loads(_cli("audit", "assays", "--ledger",
                                   str(network.base / f"{site}.duckdb"), "--json"))
             for site in SITES}
    assert together["assays"] == sum(a["assays"] for a in alone.values()) > 0
    for key in ("superseded", "provisional", "lots_without_assays"):
        assert together[key] == [{"site": s, **row} for s in SITES for row in alone[s][key]]


@pytest.fixture(params=["duckdb", "postgresql"])
def hq_bases(request, tmp_path) -> tuple[str, str]:
    """The head-office ledgers of a test (the live one, the late one): two directories,
    or two fresh databases on the tests' PostgreSQL server (one schema per site each)."""
    if request.param == "duckdb":
        return str(tmp_path / "hq"), str(tmp_path / "hq-late")
    server = request.getfixturevalue("pg_server")
    import psycopg  # noqa: PLC0415 - only the PostgreSQL case needs it

    names = [f"hq_{uuid.uuid4().hex[:10]}", f"hqlate_{uuid.uuid4().hex[:10]}"]
    with psycopg.connect(server.url(), autocommit=True) as con:
        for name in names:
            con.execute(f"CREATE DATABASE {name}")
    return server.url(database=names[0]), server.url(database=names[1])


def test_head_office_mirrors_two_sites_across_an_outage(yard_events, tmp_path, hq_bases):
    hq_base, late_base = hq_bases
    network = Network(tmp_path)
    parts = {site: [events[i * len(events) // 3:(i + 1) * len(events) // 3] for i in range(3)]
             for site, events in yard_events.items()}
    cut_site, other = list(SITES)
    sessions, feeders, clients, feeder_sessions = [], {}, {}, {}
    try:
        network.hq_router()
        for site in SITES:
            network.site_router(site, linked=True)
            network.ledger(site)
        hq, hq_log = network.head_office(hq_base)
        for site in SITES:
            feeder_session, audit_session = network.session(site, "feeder"), network.session(
                site, "audit")
            sessions += [feeder_session, audit_session]
            feeder_sessions[site] = feeder_session
            feeders[site] = Feeder(feeder_session, site)
            clients[site] = LedgerClient(audit_session, site, timeout_s=5)
        fed = {site: 0 for site in SITES}

        def feed(part: int) -> None:
            for site in SITES:
                feeders[site].publish(parts[site][part])
                fed[site] += len(parts[site][part])

        # 1. both linked
        feed(0)
        for site in SITES:
            wait_until(lambda: _site_holds(clients[site], fed[site], 0), WAIT_S,
                       f"{site}'s ledger to hold part 1")
            wait_until(lambda: _caught_up(hq_log, site, fed[site] - 1), WAIT_S,
                       f"the head office to mirror {site}'s part 1")
        # 2. the first site's link cut while both sites append
        cut_from = len(log_lines(hq_log))
        network.cut(cut_site, linked=False)
        wait_until(lambda: _head(clients[cut_site]) is not None, WAIT_S,
                   f"{cut_site}'s ledger back behind its own router")
        wait_until(lambda: _lines(hq_log, "site unreachable", cut_site, cut_from), WAIT_S,
                   f"the head office to find {cut_site} unreachable")
        feed(1)
        wait_until(lambda: _site_holds(clients[cut_site], fed[cut_site], 0), WAIT_S,
                   f"{cut_site}'s ledger to hold part 2")
        feeder_sessions[cut_site].put(key_expr(cut_site, "assay", "lab9"), b"\xff not an assay",
                                      attachment=encode_attachment(1, 0, 1_790_000_000 * 10**9),
                                      congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: _site_holds(clients[cut_site], fed[cut_site], 1), WAIT_S,
                   f"{cut_site}'s ledger to quarantine the malformed input")
        wait_until(lambda: _caught_up(hq_log, other, fed[other] - 1), WAIT_S,
                   f"the head office to mirror {other}'s part 2 during the outage")
        during = _lines(hq_log, "mirrored", cut_site, cut_from)
        assert during == [], during
        # 3. the link restored
        network.cut(cut_site, linked=True)
        feed(2)
        for site in SITES:
            wait_until(lambda: _site_holds(clients[site], fed[site], int(site == cut_site)),
                       WAIT_S, f"{site}'s ledger to hold part 3")
            wait_until(lambda: _caught_up(hq_log, site, fed[site] - 1), WAIT_S,
                       f"the head office to mirror all of {site}")
        assert stop(hq) == 0
        finals = {r["site"]: r for r in log_lines(hq_log) if r.get("msg") == "final"}
        assert {s: (finals[s]["head"], finals[s]["behind"]) for s in SITES} == {
            s: (str(fed[s] - 1), "-") for s in SITES}
        assert _lines(hq_log, "site reachable", cut_site, cut_from)
        # a head office started after both sites finished catches up from nothing
        late, late_log = network.head_office(late_base)
        for site in SITES:
            wait_until(lambda: _caught_up(late_log, site, fed[site] - 1), WAIT_S,
                       f"the late head office to mirror {site}")
        assert stop(late) == 0
    finally:
        for feeder in feeders.values():
            feeder.close()
        for session in sessions:
            session.close()
        codes = network.stop_all()
    assert codes == [0] * len(codes)
    _check_mirrors(network, hq_base)
    _check_mirrors(network, late_base, reads=False)   # reads: as for the first
    arrivals = _arrival_rows(hq_base)
    assert sorted(arrivals) == list(range(len(arrivals)))
    assert {s: sorted(seq for site_, seq in arrivals.values() if site_ == s) for s in SITES} == {
        s: list(range(fed[s])) for s in SITES}


class _Routers:
    """In-process routers for the trust test: the head office's, and a site's with a
    stand-in ledger (its queryable answers with the site events it was sent)."""

    def __init__(self, base: Path, *, uplink_head_office: str = "hq.router",
                 site_cert_uplink: bool = False) -> None:
        hq_pki, link = base / "hq", base / "link"
        init_ca(HQ, hq_pki)
        issue(hq_pki, "router", "hq.router")
        issue(hq_pki, "hq", "hq")
        issue(hq_pki, "uplink", "mine.router", out_dir=link)
        pki = site_pki(base / "mine", "mine", {"ledger": "ledger"})
        hq_endpoint, site_endpoint = (f"tls/127.0.0.1:{free_port()}" for _ in range(2))
        self.sessions = [zenoh.open(site_router_config(HQ, ZenohOptions(
            mode="router", listen=(hq_endpoint,), tls_dir=str(hq_pki), tls_name="hq.router"),
            load_members(hq_pki)))]
        options = ZenohOptions(mode="router", listen=(site_endpoint,), tls_dir=str(pki),
                               tls_name="router",
                               connect=(hq_endpoint,) if site_cert_uplink else ())
        uplink = None if site_cert_uplink else Uplink(hq_endpoint, str(link), "mine.router",
                                                      uplink_head_office)
        self.sessions.append(zenoh.open(site_router_config("mine", options, load_members(pki),
                                                           uplink)))
        ledger = open_session(ZenohOptions(mode="client", connect=(site_endpoint,),
                                           tls_dir=str(pki), tls_name="ledger"))
        self.seen: list[str] = []
        ledger.declare_subscriber("stockpile/mine/@v1/**",
                                  lambda sample: self.seen.append(str(sample.key_expr)))
        for what in ("head", "backup"):
            key = f"stockpile/mine/@ledger/q/{what}"
            ledger.declare_queryable(key, lambda query, key=key: query.reply(
                key, json.dumps({"seen": self.seen}).encode()))
        self.head = ledger.declare_publisher("stockpile/mine/@ledger/head")
        self.hq = open_session(ZenohOptions(mode="client", connect=(hq_endpoint,),
                                            tls_dir=str(hq_pki), tls_name="hq"))
        self.sessions += [ledger, self.hq]

    def ask(self, what: str = "head") -> list[str] | None:
        """The site events the stand-in ledger saw, asked from the head office on
        ``q/<what>`` (None: no answer)."""
        for reply in self.hq.get(f"stockpile/mine/@ledger/q/{what}", timeout=1.0):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())["seen"]
        return None

    def close(self) -> None:
        for session in reversed(self.sessions):
            session.close()


def test_an_uplink_carries_ledger_reads_and_nothing_that_writes(tmp_path):
    """The head office reads a site's ledger and follows its head over the uplink; what it
    puts on the site's event keys never reaches the site; without the uplink's own
    credentials (the site router's certificate on a plain connect) or with the head office
    not granted (another name), its queries go unanswered."""
    routers = _Routers(tmp_path / "linked")
    try:
        heads: list[bytes] = []
        routers.hq.declare_subscriber("stockpile/mine/@ledger/head",
                                      lambda sample: heads.append(sample.payload.to_bytes()))
        wait_until(lambda: routers.ask() == [], 30, "the head office's first answer")
        routers.hq.put("stockpile/mine/@v1/assay/lab1", b"forged",
                       congestion_control=zenoh.CongestionControl.BLOCK)
        assert routers.ask() == []     # asked after the put, on the same links, in order
        assert routers.ask("backup") is None      # a backup request writes at the site

        def head_seen() -> bool:
            routers.head.put(b'{"global_seq": 8}')
            return bool(heads)

        wait_until(head_seen, 30, "the site's head at the head office", interval_s=0.2)
    finally:
        routers.close()
    for case, kwargs in (("site-cert", {"site_cert_uplink": True}),
                         ("not-granted", {"uplink_head_office": "other.router"})):
        routers = _Routers(tmp_path / case, **kwargs)
        try:
            deadline = time.monotonic() + 5.0       # answered within 1 s when linked (above)
            while time.monotonic() < deadline:
                assert routers.ask() is None, case
        finally:
            routers.close()


def test_uplink_names_grants_and_yard_config(tmp_path):
    """An uplink certificate's name says its site, and it is granted that site's ledger
    keys only; a site router grants the head office reads only; ``[router] uplink`` in a
    yard config."""
    acl = access_control(HQ, {"mine.router": "uplink", "hq": "hq"})
    mine = [r for r in acl["rules"] if r["id"].startswith("mine.router:")]
    assert {k for r in mine for k in r["key_exprs"]} == {
        "stockpile/mine/@ledger/head", *(f"stockpile/mine/@ledger/q/{q}" for q in (
            "events", "as_of", "stats", "head", "gaps", "quarantine", "streams"))}
    for bad in ("mine", ".router", "*.router"):
        with pytest.raises(ValueError, match="uplink certificate is named"):
            access_control(HQ, {bad: "uplink"})
    site = access_control("mine", {"ledger": "ledger"}, head_office="hq.router")
    granted = [r for r in site["rules"] if r["id"].startswith("hq.router:")]
    assert {(f, m) for r in granted for f in r["flows"] for m in r["messages"]} == {
        ("egress", "declare_queryable"), ("ingress", "query"), ("egress", "reply"),
        ("ingress", "declare_subscriber"), ("egress", "put")}
    with pytest.raises(ValueError, match="also a certificate of this site"):
        access_control("mine", {"hq.router": "auditor"}, head_office="hq.router")
    toml = tmp_path / "yard.toml"
    body = ('site = "mine"\n[tls]\ndir = "/srv/pki"\n[router]\nlisten = ["tls/127.0.0.1:7447"]\n'
            'uplink = "tls/hq.example.com:7447"\n{extra}[services.ledger]\nledger = "x.duckdb"\n')
    toml.write_text(body.format(extra='uplink_tls = "/srv/hq-link"\n'))
    assert load_config(toml).router_uplink == Uplink("tls/hq.example.com:7447", "/srv/hq-link",
                                                     "mine.router", "hq.router")
    toml.write_text(body.format(extra=""))
    with pytest.raises(ConfigError, match="uplink needs uplink_tls"):
        load_config(toml)
    with pytest.raises(ValueError, match="tls/HOST:PORT"):
        Uplink("tcp/hq.example.com:7447", "/srv/hq-link", "mine.router")


def test_bad_head_office_options_are_one_line_errors(tmp_path):
    for args, needle in ((["--sites", "mine,mine"], "names a site twice"),
                         (["--sites", "hq,mine"], "also in --sites"),
                         (["--sites", "a/b"], "site must be"),
                         (["--sites", "mine", "--page-records", "0"], "--page-records"),
                         (["--sites", "mine", "--ledger", "postgresql://127.0.0.1/x"],
                          "postgresql")):
        ledger = [] if "--ledger" in args else ["--ledger", str(tmp_path / "hq")]
        done = subprocess.run([PYTHON, "-m", "stockpile.cli", "service", "hq", "--site", HQ,
                               *ledger, *args], capture_output=True, text=True, timeout=120)
        assert done.returncode == 2, done.stderr
        lines = [line for line in done.stderr.splitlines() if "level=status" not in line]
        problem = [line for line in lines if "error" in line]
        assert len(problem) == 1 and needle in problem[0], lines
        assert "Traceback" not in done.stderr


def _arrival_rows(ledgers: str) -> dict[int, tuple[str, int]]:
    """``hq_seq -> (site, site_global_seq)`` from the head office's arrivals."""
    query = "SELECT hq_seq, site, site_global_seq FROM hq.arrival_rows"
    if is_database_url(ledgers):
        import psycopg  # noqa: PLC0415 - only the PostgreSQL case needs it

        with psycopg.connect(ledgers) as con:
            rows = con.execute(query).fetchall()
    else:
        import duckdb  # noqa: PLC0415 - deferred like the service's: a heavy import

        with duckdb.connect(str(Path(ledgers) / "hq" / "arrivals.duckdb"), read_only=True) as con:
            rows = con.execute(query).fetchall()
    return {hq_seq: (site, seq) for hq_seq, site, seq in rows}


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-x", "-q"]))

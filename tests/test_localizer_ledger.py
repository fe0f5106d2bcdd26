"""A localizer started after its declarations' publishers left takes them from the ledger.

The declarations are in a real DuckDB ledger served by a real ledger service, and no
publisher's cache holds them (they were appended, never published).  The localizer
process runs over mutual TLS with the router's generated access control (role
``localizer``), so the test also proves the role may ask the ledger.  Without the
ledger's declarations the localizer has no datum and no machine, and publishes nothing.
"""

from __future__ import annotations

import queue

import numpy as np

from ledger import open_ledger
from schemas.events import event_from_sample, make_event
from schemas.times import NS_PER_S as NS
from services.localizer import Config, Localizer
from services.localizer_declarations import latest_declarations
from services.service import EventPublisher
from test_localizer import (SEED, _declarations, _fix, _reading, reclaim_joints,
                            sensor_data)
from zenoh_helpers import (client_args, log_lines, open_router, site_pki, stockpile,
                           stop_all, wait_until)

SITE = "locledger"


def _events(messages, source: str = "yard.config", first_seq: int = 0) -> list:
    return [make_event(m, source=source, epoch=1, seq=first_seq + i)
            for i, m in enumerate(messages)]


def test_latest_declarations_keeps_the_last_of_each_and_only_this_machine():
    first = _declarations()                       # site, bwr1, st1
    later = _declarations()
    later[0].datum_alt_m += 5.0
    later[1].l5_m += 1.0
    events = _events(first) + _events(later, first_seq=3)
    got = latest_declarations(events, "bwr1")
    assert [e.seq for e in got] == [3, 4]         # the later site and the later bwr1
    assert [e.seq for e in latest_declarations(events, "st1")] == [3, 5]
    assert [e.seq for e in latest_declarations(events[:1], "bwr1")] == [0]
    assert latest_declarations([], "bwr1") == []


def test_a_declaration_from_the_ledger_never_replaces_one_already_known():
    loc = Localizer(Config(smooth_lag_s=0.0), lambda m: None, lambda *a, **k: None,
                    lambda *a, **k: None)
    live = _events(_declarations(), source="cfg.live")
    old = _declarations()
    old[0].datum_alt_m += 5.0
    old[1].l5_m += 1.0
    stale = _events(old, source="cfg.old")
    assert loc.needs_declarations
    loc.fill_declaration(stale[0])                # the datum was missing: taken
    assert loc.datum[2] == old[0].datum_alt_m and loc.needs_declarations
    loc.handle(live[0])                           # live declarations always apply
    loc.handle(live[1])
    assert not loc.needs_declarations
    datum, l5_m = loc.datum, loc.geometry.l5_m
    loc.fill_declaration(stale[0])
    loc.fill_declaration(stale[1])
    assert loc.datum == datum and loc.geometry.l5_m == l5_m


def test_localizer_takes_the_declarations_from_the_ledger_over_tls(tmp_path):
    n = 20
    t_ns, joints = reclaim_joints(float(n - 1))
    t_ns = t_ns + 200 * NS
    readings, fixes, _cov = sensor_data(SEED + 7, t_ns, joints)
    path = tmp_path / "yard.duckdb"
    with open_ledger(path) as store:
        outcomes = store.append(_events(_declarations())).outcomes
        assert [o.status for o in outcomes] == ["appended"] * 3
    pki = site_pki(tmp_path / "pki", SITE, {"ledger": "ledger",
                                             "bwr1.localizer": "localizer"})
    router, endpoint = open_router(pki, SITE)
    got: queue.Queue = queue.Queue()

    def on_sample(sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
        got.put(event_from_sample(str(sample.key_expr), sample.payload.to_bytes(), attachment))

    subs = [router.declare_subscriber(f"stockpile/{SITE}/@v1/{t}/**", on_sample)
            for t in ("joint_estimate", "frame_transform")]
    ledger = localizer = None
    log = tmp_path / "localizer.log"
    try:
        ledger = stockpile("service", "ledger", "--ledger", str(path), "--site", SITE,
                           *client_args(endpoint, pki, "ledger"),
                           stderr_path=tmp_path / "ledger.log")
        localizer = stockpile("service", "localizer", "--site", SITE, "--smooth-lag", "0",
                              "--status-period", "1",
                              *client_args(endpoint, pki, "bwr1.localizer"),
                              stderr_path=log)
        # it may ask before the ledger service is up: it retries until one answers
        wait_until(lambda: any(ln.get("msg") == "declarations from the ledger"
                               for ln in log_lines(log)), 60, "the ledger's declarations")
        answer = [ln for ln in log_lines(log) if ln.get("msg") == "declarations from the ledger"]
        assert answer[0]["found"] == "2", answer
        assert answer[0]["types"] == "site_declared,machine_declared"
        wait_until(lambda: any(ln.get("msg") == "machine declared" for ln in log_lines(log)),
                   30, "the machine declared from the ledger's record")
        enc = EventPublisher(router, SITE, "bwr1.encoders")
        gnss = EventPublisher(router, SITE, "bwr1.gnss")
        for k in range(n):
            enc.publish(_reading(t_ns[k], readings[k]))
            gnss.publish(_fix(t_ns[k], fixes, k))
        events = []          # each released within the reorder hold (0.5 s wall)
        wait_until(lambda: _drain(got, events) >= 3 * n, 30, "every estimate")
        codes = stop_all(localizer)
        localizer = None
        assert codes == [0]
        enc.close()
        gnss.close()
    finally:
        stop_all(localizer, ledger)
        for s in subs:
            s.undeclare()
        router.close()
    estimates = sorted(e.valid_time_ns for e in events if e.type == "joint_estimate")
    assert estimates == [int(t) for t in t_ns]
    assert {e.source for e in events} == {"bwr1.localizer"}
    assert np.all(np.diff(estimates) > 0)


def _drain(q: queue.Queue, into: list) -> int:
    while True:
        try:
            into.append(q.get_nowait())
        except queue.Empty:
            return len(into)


def test_the_localizer_role_may_ask_the_ledger_for_events_only():
    from services.acl import access_control

    block = access_control(SITE, {"bwr1.localizer": "localizer"})
    keys = {(tuple(r["messages"]), k) for r in block["rules"] for k in r["key_exprs"]
            if "@ledger" in k}
    assert keys == {(("query",), f"stockpile/{SITE}/@ledger/q/events"),
                    (("reply",), f"stockpile/{SITE}/@ledger/q/events")}

"""``LedgerStore.mirror``: another ledger's rows, quarantine and gaps appended verbatim.

A site ledger is built by normal appends (gaps opened and later closed in part, refused
input in the quarantine, a conflict, signed key declarations and assays, an assay of a
lot not declared yet, clock events) in batches split at random; it is then mirrored in
pages split at random, with the site's final gap table given at each page (as a head office
fetches it), into the memory and the DuckDB stores.  The mirror's export lines, head,
quarantine, gaps and streams equal the site's, ``verify`` holds, a DuckDB mirror's writer
state is what a re-open gives, and the mirror appends on exactly as the site does.
Tampered or non-contiguous input is refused with nothing stored.
"""

from __future__ import annotations

import dataclasses
import random
from pathlib import Path

import pytest

from ledger import open_ledger
from ledger.clock import ManualClock
from ledger.mirror import MirrorRefused, ledger_for, mirrored_sites, site_ledger
from ledger.signing import sign_event
from ledger.store import LedgerStore
from ledger.testing import TAMPER_FIELDS, joint_event, tampered_rows
from ledger.testing_signing import assay, key_declared, make_keys
from schemas import pb
from schemas.events import Malformed, make_event, set_timestamp_ns
from schemas.jsonl import event_line

T0_NS = 1_790_000_000 * 10**9
S_NS = 10**9


def _lot(lot_id: str, seq: int, valid_ns: int):
    m = pb.LotDeclared(lot_id=lot_id, origin="pit 3", planned_tonnes=1000.0,
                       planned_grade={"Fe": 62.0})
    set_timestamp_ns(m.time, valid_ns)
    return make_event(m, source="planner", epoch=1, seq=seq)


def _clock(seq: int, valid_ns: int):
    m = pb.Clock()
    set_timestamp_ns(m.time, valid_ns)
    return make_event(m, source="sim.clock", epoch=1, seq=seq)


def _site_input(rng: random.Random, keys: dict) -> list:
    """Every input of the site, in arrival order (events, refused input, a conflict)."""
    admin, lab = keys["admin"], keys["lab1"]
    items: list = [key_declared(admin, admin, "admin", "site admin", 0, T0_NS),
                   key_declared(admin, lab, "lab", "lab one", 1, T0_NS)]
    # the PLC's joint readings arrive out of order: some late (closing gaps), some never
    seqs = list(range(60))
    never = set(rng.sample(seqs[5:], 4))
    late = rng.sample([s for s in seqs[5:] if s not in never], 8)
    order = [s for s in seqs if s not in never and s not in late]
    for s in late:      # after at least one higher seq: a gap opens, and this closes it
        higher = next((i for i, x in enumerate(order) if x > s), len(order) - 1)
        order.insert(rng.randrange(higher + 1, len(order) + 1), s)
    items += [joint_event("plc1", s, T0_NS + s * S_NS, travel_m=s * 0.5) for s in order]
    items.insert(3, assay(0, T0_NS + 5 * S_NS))          # an assay of L1 before L1 is declared
    items.insert(rng.randrange(len(items) // 2, len(items)), _lot("L1", 0, T0_NS + 2 * S_NS))
    items += [assay(i, T0_NS + (10 + i) * S_NS) for i in range(1, 5)]
    items += [_clock(i, T0_NS + i * 30 * S_NS) for i in range(5)]
    items.insert(rng.randrange(len(items)), Malformed(b"\xff\x00 not an event", "malformed: bad",
                                                      "scan", "bwr1.scanner", 1, 0, None))
    items.insert(rng.randrange(len(items)), joint_event("plc1", order[0], T0_NS, travel_m=99.0))
    return [sign_event(it, lab) if getattr(it, "type", "") == "assay" else it for it in items]


def _splits(rng: random.Random, n: int, most: int) -> list[tuple[int, int]]:
    """``[0, n)`` cut into consecutive pieces of 1..``most`` (a random batch split)."""
    out, start = [], 0
    while start < n:
        stop = min(n, start + rng.randint(1, most))
        out.append((start, stop))
        start = stop
    return out


def _site(rng: random.Random, tmp_path: Path) -> LedgerStore:
    """The site ledger: every input appended in random batches, recorded time advancing."""
    keys = make_keys(tmp_path, "admin", "lab1")
    items = _site_input(rng, keys)
    clock = ManualClock(T0_NS)
    store = open_ledger(":memory:", clock)
    for start, stop in _splits(rng, len(items), 9):
        clock.advance_ns(rng.randint(0, 3) * S_NS)
        store.append(items[start:stop])
    return store


def _export(store: LedgerStore) -> list[str]:
    return [event_line(row) for row in store.read()]


def _mirror_in_pages(rng: random.Random, site: LedgerStore, mirror: LedgerStore) -> int:
    """Mirror ``site`` page by page as a head office does; the number of pages."""
    rows = list(site.read())
    entries = site.quarantine()
    gaps = site.gaps()
    pages = _splits(rng, len(rows), 11)
    for start, stop in pages:
        last = rows[stop - 1].global_seq
        given = [q for q in entries if q.quarantine_id >= len(mirror.quarantine())
                 and q.after_global_seq <= last]
        head = mirror.mirror(rows[start:stop], given, gaps)
        assert head.global_seq == last
    return len(pages)


def _open(kind: str, path: Path) -> LedgerStore:
    return open_ledger(":memory:" if kind == "memory" else path, ManualClock(T0_NS))


@pytest.fixture
def rng(seed):
    return random.Random(seed)


@pytest.mark.parametrize("kind", ["memory", "duckdb"])
def test_a_mirror_holds_exactly_the_site_ledger(kind, rng, tmp_path):
    site = _site(rng, tmp_path)
    assert site.gaps(open_only=True) and [g for g in site.gaps() if not g.is_open]
    assert site.quarantine() and any(r.signer for r in site.read())
    assert any(r.flags for r in site.read())
    mirror = _open(kind, tmp_path / "mirror.duckdb")
    pages = _mirror_in_pages(rng, site, mirror)
    assert pages > 1
    assert _export(mirror) == _export(site)
    assert mirror.head() == site.head()
    assert mirror.quarantine() == site.quarantine()
    assert mirror.gaps() == site.gaps()
    assert mirror.streams() == site.streams()
    report = mirror.verify()
    assert report.ok, report
    assert report.rows_checked == site.head().global_seq + 1
    if kind == "duckdb":
        state = mirror._state
        mirror.close()
        mirror = open_ledger(tmp_path / "mirror.duckdb", ManualClock(T0_NS))
        assert mirror._state == state
        assert mirror.verify().ok
    mirror.close()


def test_a_mirror_appends_on_exactly_as_its_site(rng, tmp_path):
    site = _site(rng, tmp_path)
    mirror = open_ledger(":memory:", ManualClock(T0_NS))
    _mirror_in_pages(rng, site, mirror)
    later = [joint_event("plc1", s, T0_NS + s * S_NS) for s in (60, 75, 64)]
    later += [_lot("L2", 1, T0_NS), joint_event("plc1", 60, T0_NS, travel_m=5.0)]
    for store in (site, mirror):
        store.clock.set_ns(T0_NS + 10**6 * S_NS)
    results = [store.append(later) for store in (site, mirror)]
    assert results[0] == results[1]
    assert _export(mirror) == _export(site)
    assert mirror.gaps() == site.gaps() and mirror.quarantine() == site.quarantine()
    assert mirror.head() == site.head()


def _refused(mirror: LedgerStore, rows, entries=(), gaps=(), match: str | None = None) -> None:
    head = mirror.head()
    exported = _export(mirror)
    with pytest.raises(MirrorRefused, match=match):
        mirror.mirror(rows, entries, gaps)
    assert mirror.head() == head and _export(mirror) == exported


@pytest.mark.parametrize("kind", ["memory", "duckdb"])
def test_tampered_or_discontinuous_input_is_refused_with_nothing_stored(kind, rng, tmp_path):
    site = _site(rng, tmp_path)
    rows = list(site.read())
    entries, gaps = site.quarantine(), site.gaps()
    mirror = _open(kind, tmp_path / "mirror.duckdb")
    split = rng.randrange(5, len(rows) - 10)
    print(f"first page: rows 0..{split - 1}")
    before = [q for q in entries if q.after_global_seq < split - 1]
    mirror.mirror(rows[:split], before, gaps)
    rest = rows[split:]
    after = [q for q in entries if q.quarantine_id >= len(before)]
    for field in TAMPER_FIELDS:
        target = split + rng.randrange(len(rest) - 2)
        bad = tampered_rows(rows, target, field)[split:]
        _refused(mirror, bad, after, gaps)
    # A row skipped: refused at the next row, or at a quarantine entry placed after the
    # skipped row, whichever the mirror meets first.
    _refused(mirror, rest[1:], after, gaps, "where .* was expected|this mirror's head is")
    _refused(mirror, rows[:split], before, gaps, "where .* was expected")    # again from 0
    if after:
        edited = dataclasses.replace(after[0], detail=after[0].detail + "!")
        _refused(mirror, rest, [edited] + after[1:], gaps, "quarantine entry")
    if after and after[0].after_global_seq < rows[-1].global_seq:
        _refused(mirror, rest, after[1:], gaps)                               # one left out
    moved = [dataclasses.replace(g, last_seq=g.last_seq + 1) if i == 0 else g
             for i, g in enumerate(gaps)]
    _refused(mirror, rest, after, moved, "gap 0")
    _refused(mirror, rest, after, gaps[1:], "gap")                           # one deleted
    (tmp_path / "other").mkdir()
    other = _site(random.Random(rng.random()), tmp_path / "other")
    _refused(mirror, list(other.read())[split:])                             # another ledger
    mirror.mirror(rest, after, gaps)                                         # the truth goes in
    assert _export(mirror) == _export(site) and mirror.verify().ok
    mirror.close()


def test_site_ledgers_under_a_head_office(tmp_path):
    assert site_ledger(tmp_path, "port") == str(tmp_path / "port.duckdb")
    url = "postgresql://hq@127.0.0.1:5432/ledger?sslmode=require&schema=public"
    assert site_ledger(url, "mine_2") == ("postgresql://hq@127.0.0.1:5432/ledger?"
                                          "sslmode=require&schema=site_mine_2")
    for not_a_schema in ("mine-2", "Port"):   # a schema name is a plain identifier
        with pytest.raises(ValueError, match="lower-case letters"):
            site_ledger(url, not_a_schema)
    for bad in ("", "a/b", "../x", "@v1", "x" * 64):
        with pytest.raises(ValueError, match="site must be"):
            site_ledger(tmp_path, bad)
    for site in ("port", "mine-2"):
        open_ledger(site_ledger(tmp_path, site)).close()
    (tmp_path / "hq").mkdir()
    assert mirrored_sites(tmp_path) == ["mine-2", "port"]
    with pytest.raises(ValueError, match="cannot list the sites"):
        mirrored_sites(url)
    # what the read commands open for --ledger and --site
    port = str(tmp_path / "port.duckdb")
    assert ledger_for(port, None) == port and ledger_for(str(tmp_path), "port") == port
    assert ledger_for(url, "port").endswith("schema=site_port")
    with pytest.raises(ValueError, match=r"head office's ledgers: give --site \(mirrored: "
                       r"mine-2, port\)"):
        ledger_for(str(tmp_path), None)
    with pytest.raises(ValueError, match="no mirror of site 'quay'"):
        ledger_for(str(tmp_path), "quay")
    with pytest.raises(ValueError, match="--site needs --ledger to be a head office"):
        ledger_for(port, "port")


def test_gaps_compare_as_the_site_closes_them_later(rng, tmp_path):
    """A gap the site closed with a row the mirror does not hold yet is open in the mirror
    until that row comes; a gap closed at a time before the mirror's head is refused."""
    site = _site(rng, tmp_path)
    closed = [g for g in site.gaps() if not g.is_open]
    rows = list(site.read())
    mirror = open_ledger(":memory:", ManualClock(T0_NS))
    closing_row = next(r for r in rows if r.recorded_time_ns == closed[0].closed_recorded_ns
                       and r.source == closed[0].source
                       and closed[0].first_seq <= r.seq <= closed[0].last_seq)
    cut = closing_row.global_seq
    entries = [q for q in site.quarantine() if q.after_global_seq < cut - 1]
    mirror.mirror(rows[:cut], entries, site.gaps())
    mine = {g.gap_id: g for g in mirror.gaps()}
    assert mine[closed[0].gap_id].is_open
    early = [dataclasses.replace(g, closed_recorded_ns=T0_NS - 1) if g.gap_id == closed[0].gap_id
             else g for g in site.gaps()]
    _refused(mirror, [], (), early, f"gap {closed[0].gap_id}")

"""Mirrors: another ledger's rows, quarantine entries and gaps appended verbatim.

A head office keeps, per site, an exact **mirror** of that site's ledger: the same rows
(global seq, identity, times, payload, hashes, chain, flags, signer, signature), the same
quarantine entries and the same gap table, so ``verify``, ``project`` and ``audit`` answer
on the mirror exactly as on the site.  :meth:`ledger.store.LedgerStore.mirror` appends a
piece of the other ledger after the mirror's head in one atomic batch; :func:`plan_mirror`
(here) decides that batch, checking everything the rows allow before anything is stored:

- global seqs dense from the mirror's head + 1, quarantine ids dense from its next id,
  each entry placed after the row stored just before it;
- each row's payload hash, its chain value recomputed from the previous link (a row's or
  a quarantine entry's), each entry's link, recorded time never going backwards;
- no (source, epoch, seq) stored twice, the flags recomputed from the payloads, every
  signature against the keys the rows before it declare;
- the gap table the rows give (the writer's rule, :class:`ledger.store.StreamState`)
  against the other ledger's gap table, where a gap it closed with a row not mirrored yet
  is still open here (it closes when that row is mirrored).

Rows are not validated as new input (the site did when it stored them); the JSON bodies
the SQL views read are filled as appends fill them.  The first problem raises
:class:`MirrorRefused` naming the row, entry or gap; nothing of the batch is stored.

:func:`site_ledger` says where a site's mirror lives under a head office's ledger base:
``DIR/<site>.duckdb`` for a directory, the same ``postgresql://`` URL with
``schema=site_<site>`` for a PostgreSQL database; :func:`ledger_for` is what the read
commands' ``--ledger`` and ``--site`` open.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path
from typing import Any, Sequence
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

from schemas.events import decode_payload
from schemas.jsonl import body_json

from ledger.chain import chain_hash, payload_hash
from ledger.errors import IntegrityError
from ledger.records import FLAG_UNKNOWN_LOT, AppendOutcome, Gap, QuarantineEntry, RecordedEvent
from ledger.signing import KEY_TYPES, signature_block
from ledger.verifying import quarantine_link

#: URL schemes of a PostgreSQL head office
PG_SCHEMES = ("postgresql", "postgres")
#: a site name usable as a file name and a PostgreSQL schema suffix
_SITE_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,62}")
#: a site whose mirror is a PostgreSQL schema (site_<site>, a plain identifier)
_SCHEMA_SITE_RE = re.compile(r"[a-z0-9][a-z0-9_]{0,57}")
#: the file of a site's mirror in a head office's directory
MIRROR_SUFFIX = ".duckdb"


class MirrorRefused(IntegrityError):
    """Rows offered to a mirror were tampered with or do not continue it (nothing stored)."""


# -- where a site's mirror lives ------------------------------------------------------------


def check_site(site: str) -> str:
    """``site`` if it can name a mirror (letters, digits, ``_``, ``-``), else ValueError."""
    if not isinstance(site, str) or not _SITE_RE.fullmatch(site):
        raise ValueError(f"site must be 1-63 letters, digits, '_' or '-' starting with a letter "
                         f"or digit, got {site!r}")
    return site


def is_database_url(base: str | os.PathLike[str]) -> bool:
    """Whether a ledger base is a ``postgresql://`` URL (else a directory)."""
    return urlsplit(str(base)).scheme in PG_SCHEMES


def site_ledger(base: str | os.PathLike[str], site: str) -> str:
    """What :func:`ledger.open_ledger` opens for ``site``'s mirror under a head office's
    ledger ``base``: ``DIR/<site>.duckdb`` for a directory, the URL with
    ``schema=site_<site>`` for a PostgreSQL database."""
    check_site(site)
    text = str(base)
    if is_database_url(text):
        if not _SCHEMA_SITE_RE.fullmatch(site):
            raise ValueError(f"site {site!r}: a PostgreSQL head office names each site's "
                             "schema site_<site>, so site names are lower-case letters, "
                             "digits and _ there")
        parts = urlsplit(text)
        query = [(k, v) for k, v in parse_qsl(parts.query) if k != "schema"]
        query.append(("schema", f"site_{site}"))
        return urlunsplit(parts._replace(query=urlencode(query)))
    return str(Path(text) / f"{site}{MIRROR_SUFFIX}")


def mirrored_sites(base: str | os.PathLike[str]) -> list[str]:
    """The sites with a mirror under a head office's ledger, sorted: the ``<site>.duckdb``
    files of a directory, or the ``site_<site>`` schemas of a PostgreSQL database
    (ValueError for a directory that does not exist or a database that cannot be read)."""
    if is_database_url(base):
        return _database_sites(str(base))
    folder = Path(base)
    if not folder.is_dir():
        raise ValueError(f"no head-office ledger directory at {folder}")
    return sorted(p.name[:-len(MIRROR_SUFFIX)] for p in folder.glob(f"*{MIRROR_SUFFIX}")
                  if _SITE_RE.fullmatch(p.name[:-len(MIRROR_SUFFIX)]))


def _database_sites(url: str) -> list[str]:
    """The ``site_<site>`` schemas of a PostgreSQL head office, as site names."""
    try:
        # deferred: psycopg is the PostgreSQL backend's dependency, not every install's
        import psycopg
    except ImportError as exc:
        raise ValueError(f"a PostgreSQL head office needs psycopg: {exc}") from None
    parts = urlsplit(url)
    query = [(k, v) for k, v in parse_qsl(parts.query) if k != "schema"]
    try:
        with psycopg.connect(urlunsplit(parts._replace(query=urlencode(query))),
                             connect_timeout=10) as con:
            names = [r[0] for r in con.execute(
                "SELECT nspname FROM pg_namespace WHERE nspname LIKE 'site\\_%' "
                "ORDER BY nspname").fetchall()]
    except psycopg.Error as exc:
        raise ValueError(f"cannot list the sites of the head office: "
                         f"{str(exc).strip().splitlines()[0]}") from None
    return [n[len("site_"):] for n in names if _SITE_RE.fullmatch(n[len("site_"):])]


def ledger_for(ledger: str, site: str | None) -> str:
    """What a read command opens for ``--ledger`` and ``--site``: the ledger itself, or
    that site's mirror under a head office's ledgers; ValueError (one line) for a site
    without a mirror there, or a head office's directory without a site."""
    text = str(ledger)
    if site is None:
        if not is_database_url(text) and Path(text).is_dir():
            raise ValueError(f"{text} is a head office's ledgers: give --site (mirrored: "
                             f"{', '.join(mirrored_sites(text)) or 'none'})")
        return text
    target = site_ledger(text, site)
    if not is_database_url(text):
        if not Path(text).is_dir():
            raise ValueError(f"--site needs --ledger to be a head office's directory of "
                             f"mirrors or a postgresql:// URL, not {text}")
        if not Path(target).exists():
            raise ValueError(f"no mirror of site {site!r} in {text} (mirrored: "
                             f"{', '.join(mirrored_sites(text)) or 'none'})")
    return target


# -- planning a mirror batch ----------------------------------------------------------------


def plan_mirror(planner: Any, rows: Sequence[RecordedEvent],
                quarantine: Sequence[QuarantineEntry], gaps: Sequence[Gap],
                stored_gaps: Sequence[Gap], body_types: frozenset[str]):
    """The :class:`ledger.store.BatchPlan` appending ``rows`` and the ``quarantine``
    entries between them after the head of ``planner``'s state.

    ``planner`` is the store's batch planner (its copy-on-write writer state, its plan and
    its sequence tracking); ``gaps`` is the other ledger's whole gap table (empty: not
    compared) and ``stored_gaps`` this ledger's.  Raises :class:`MirrorRefused`.
    """
    entries = list(quarantine)
    taken = 0
    for row in rows:
        taken = _entries_before(planner, entries, taken, row.global_seq)
        _row(planner, row, body_types)
    taken = _entries_before(planner, entries, taken, planner.state.head_seq + 1)
    if taken < len(entries):
        entry = entries[taken]
        raise MirrorRefused(f"quarantine entry {entry.quarantine_id} is placed after global_seq "
                            f"{entry.after_global_seq}, beyond the last row given "
                            f"({planner.state.head_seq})")
    if gaps:
        _check_gaps(planner, gaps, stored_gaps)
    planner.plan.state = planner.state
    return planner.plan


def _entries_before(planner: Any, entries: list[QuarantineEntry], taken: int,
                    global_seq: int) -> int:
    """Take the entries placed before row ``global_seq``; the index of the next one."""
    s = planner.state
    while taken < len(entries) and entries[taken].after_global_seq < global_seq:
        entry = entries[taken]
        where = f"quarantine entry {entry.quarantine_id}"
        if entry.quarantine_id != s.next_quarantine_id:
            raise MirrorRefused(f"{where} where {s.next_quarantine_id} was expected (the "
                                "entries do not continue this mirror)")
        if entry.after_global_seq != s.head_seq:
            raise MirrorRefused(f"{where} is placed after global_seq {entry.after_global_seq}, "
                                f"this mirror's head is {s.head_seq}")
        if s.last_recorded_ns is not None and entry.recorded_time_ns < s.last_recorded_ns:
            raise MirrorRefused(f"{where}: recorded time goes backwards")
        if quarantine_link(s.link_chain, entry) != entry.chain_sha256:
            raise MirrorRefused(f"{where}: chain hash mismatch (the entry was edited, or does "
                                "not continue this mirror's chain)")
        s.link_chain = entry.chain_sha256
        s.next_quarantine_id += 1
        planner.plan.quarantine.append(entry)
        taken += 1
    return taken


def _row(planner: Any, row: RecordedEvent, body_types: frozenset[str]) -> None:
    """Check one row against the mirror's state and add it to the plan."""
    s = planner.state
    where = f"global_seq {row.global_seq}"
    if row.global_seq != s.head_seq + 1:
        raise MirrorRefused(f"{where} where {s.head_seq + 1} was expected (the rows do not "
                            "continue this mirror)")
    if payload_hash(row.payload) != row.payload_sha256:
        raise MirrorRefused(f"{where}: payload does not match its sha256")
    if s.last_recorded_ns is not None and row.recorded_time_ns < s.last_recorded_ns:
        raise MirrorRefused(f"{where}: recorded time goes backwards")
    chain = chain_hash(s.link_chain, row.global_seq, row.type, row.source, row.epoch, row.seq,
                       row.valid_time_ns, row.recorded_time_ns, row.payload_sha256,
                       signature_block(row.signer, row.signature))
    if chain != row.chain_sha256:
        raise MirrorRefused(f"{where}: chain hash mismatch (the row was edited, or does not "
                            "continue this mirror's chain)")
    stream = s.streams.get((row.source, row.epoch))
    if stream is not None and stream.is_stored(row.seq):
        raise MirrorRefused(f"{where}: seq {row.seq} of {row.source} epoch {row.epoch} is "
                            "stored twice")
    message = _decoded(row, body_types)
    flags = _flags(planner, row, message)
    if tuple(row.flags) != flags:
        raise MirrorRefused(f"{where}: flags {list(row.flags)} where the payloads before it "
                            f"give {list(flags)}")
    if row.signer is not None or row.type in KEY_TYPES:
        refused = s.keys.problem(row.type, row.source, row.epoch, row.seq, row.valid_time_ns,
                                 row.payload_sha256, message, row.signer, row.signature, None)
        if refused:
            raise MirrorRefused(f"{where}: signature: {refused[0]}: {refused[1]}")
    _learn(planner, row, message)
    s.head_seq, s.head_chain, s.link_chain = row.global_seq, chain, chain
    s.last_recorded_ns = row.recorded_time_ns
    planner._track_sequence(row.source, row.epoch, row.seq, row.recorded_time_ns)
    planner.plan.rows.append(row._replace(flags=flags))
    planner.plan.bodies.append(body_json(message) if row.type in body_types else None)
    planner.plan.outcomes.append(AppendOutcome("appended", row.global_seq, None, None, flags))


def _decoded(row: RecordedEvent, body_types: frozenset[str]) -> Any:
    """The row's decoded payload where the mirror reads it (bodies, lots, keys, signed
    rows), else None."""
    if row.type not in body_types and row.type not in KEY_TYPES and row.signer is None:
        return None
    try:
        return decode_payload(row.type, row.payload)
    except Exception:  # noqa: BLE001 - a stored payload always decoded; say so if not
        raise MirrorRefused(f"global_seq {row.global_seq}: payload does not decode") from None


def _flags(planner: Any, row: RecordedEvent, message: Any) -> tuple[str, ...]:
    """The row's flags as the writer set them: an assay of a lot not declared before it."""
    if row.type == "assay" and message.lot_id not in planner.state.known_lots:
        return (FLAG_UNKNOWN_LOT,)
    return ()


def _learn(planner: Any, row: RecordedEvent, message: Any) -> None:
    """What the writer state learns from a stored row: lots, keys, the site clock."""
    s = planner.state
    if row.type == "lot_declared" and message.lot_id not in s.known_lots:
        if not planner._lots_copied:
            s.known_lots = set(s.known_lots)
            planner._lots_copied = True
        s.known_lots.add(message.lot_id)
    elif row.type in KEY_TYPES:
        if not planner._keys_copied:
            s.keys = s.keys.copy()
            planner._keys_copied = True
        s.keys.learn(row.type, message)
    elif row.type == "clock" and (s.latest_clock_event_ns is None
                                  or row.valid_time_ns > s.latest_clock_event_ns):
        s.latest_clock_event_ns = row.valid_time_ns


def _check_gaps(planner: Any, given: Sequence[Gap], stored: Sequence[Gap]) -> None:
    """The other ledger's gap table against the one this mirror holds after the plan."""
    s = planner.state
    table = {g.gap_id: g for g in stored}
    table.update((g.gap_id, g) for g in planner.plan.closed_gaps + planner.plan.opened_gaps)
    seen = set()
    for gap in given:
        seen.add(gap.gap_id)
        if gap.gap_id >= s.next_gap_id:
            continue          # opened by a row this mirror does not hold yet
        mine = table.get(gap.gap_id)
        if mine == gap or (mine is not None and mine.is_open and not gap.is_open
                           and dataclasses.replace(gap, closed_recorded_ns=None) == mine
                           and gap.closed_recorded_ns >= (s.last_recorded_ns or 0)):
            continue          # the same, or closed later by a row not mirrored yet
        raise MirrorRefused(f"gap {gap.gap_id} of {gap.source} epoch {gap.epoch} seq "
                            f"{gap.first_seq}..{gap.last_seq} is not the gap the rows give "
                            f"({mine})")
    missing = sorted(set(range(s.next_gap_id)) - seen)
    if missing:
        raise MirrorRefused(f"the gap table given lacks gap {missing[0]}, which the rows give")

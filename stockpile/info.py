"""``stockpile info FILE``: what an MCAP session or a ledger holds (as ``mcap info`` does).

The kind of file is told by its content: the MCAP magic bytes make it a recording or
an export, a DuckDB header makes it a ledger (opened read-only); a ``postgresql://`` URL
is a PostgreSQL ledger (shown with its password masked, without a size).  For both: path,
size, time span (valid time first..last; a ledger's recorded times, an MCAP file's
log times), events per type and per source, gaps.  A ledger adds its quarantine and
flags; an MCAP file adds its schemas and channels (topic, schema name, messages),
its metadata records, kept malformed samples, and what a damaged or cut-short file
lost (one linear pass with :class:`~replay.mcap_scan.McapScan`, which reads a
truncated file up to its last complete record).  ``--json`` prints one JSON object.

Only what a base install has is imported: the ledger (DuckDB), protobuf and the
MCAP reader; no numpy, scipy, zenoh or rerun.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, TextIO

from common.options import describe_ledger, is_ledger_url
from ledger import open_ledger
from ledger.wire import stats_to_json
from ledger.errors import LedgerError
from ledger.sql import created_by_version, is_duckdb_file, one_line
from replay.mcap_entries import read_entries
from replay.mcap_format import MAGIC, McapFormatError
from replay.mcap_records import MetadataRecord
from replay.mcap_scan import McapScan
from schemas.times import format_time_ns

EXIT_OK, EXIT_USAGE = 0, 2
#: gaps listed one by one (the rest are counted)
MAX_LISTED_GAPS = 20


class InfoError(ValueError):
    """A file ``info`` cannot describe (missing, neither MCAP nor ledger); one line."""


def file_kind(path: str | Path) -> str:
    """``"mcap"`` or ``"ledger"`` by the file's first bytes (a ``postgresql://`` URL is a
    ledger); :class:`InfoError` otherwise."""
    if is_ledger_url(path):
        return "ledger"
    path = Path(path)
    if not path.exists():
        raise InfoError(f"no such file: {path}")
    if not path.is_file():
        raise InfoError(f"{path} is not a file")
    with open(path, "rb") as handle:
        head = handle.read(len(MAGIC))
    if head == MAGIC:
        return "mcap"
    if is_duckdb_file(path):
        return "ledger"
    raise InfoError(f"{path} is neither an MCAP file nor a ledger")


def _span(lo_hi: tuple[int, int] | None) -> dict[str, Any] | None:
    if lo_hi is None:
        return None
    lo, hi = lo_hi
    return {"first_ns": lo, "last_ns": hi, "first": format_time_ns(lo),
            "last": format_time_ns(hi), "duration_s": (hi - lo) / 1e9}


# -- ledger -------------------------------------------------------------------------------


def ledger_info(path: str | Path) -> dict[str, Any]:
    """A ledger's summary as a JSON-ready dict (``kind`` = ``"ledger"``; ``backend``
    ``duckdb`` with the file's size and DuckDB version, or ``postgresql`` without)."""
    url = is_ledger_url(path)
    where = str(path) if url else Path(path)
    try:
        with open_ledger(where, read_only=True) as store:
            stats = store.stats()
            gaps = store.gaps()
    except LedgerError as exc:
        raise InfoError(f"{describe_ledger(path)} is not a readable ledger: "
                        f"{one_line(exc)}") from None
    data = stats_to_json(stats)
    open_gaps = [g for g in gaps if g.closed_recorded_ns is None]
    return {
        "kind": "ledger",
        "backend": "postgresql" if url else "duckdb",
        "path": describe_ledger(path) if url else str(where),
        "size_bytes": None if url else where.stat().st_size,
        "duckdb_created_by": None if url else created_by_version(where),
        "events": stats.events,
        "head": data["head"],
        "valid_time": _span(stats.valid_time_range_ns),
        "recorded_time": _span(stats.recorded_time_range_ns),
        "per_type": dict(stats.per_type),
        "per_source": dict(stats.per_source),
        "gaps": {
            "open": stats.open_gaps, "closed": stats.closed_gaps,
            "missing_events": stats.missing_events,
            "listed": [{"source": g.source, "epoch": g.epoch, "first_seq": g.first_seq,
                        "last_seq": g.last_seq} for g in open_gaps[:MAX_LISTED_GAPS]],
        },
        "quarantine": {"count": stats.quarantined, "by_code": dict(stats.quarantine_by_code)},
        "flagged": dict(stats.flagged),
    }


# -- MCAP -----------------------------------------------------------------------------------


def _sequence_gaps(seqs: list[int]) -> list[tuple[int, int]]:
    """Missing ``first..last`` ranges between the lowest and highest sequence seen."""
    out: list[tuple[int, int]] = []
    previous: int | None = None
    for seq in sorted(set(seqs)):
        if previous is not None and seq > previous + 1:
            out.append((previous + 1, seq - 1))
        previous = seq
    return out


class _CountingScan(McapScan):
    """:class:`McapScan` that also counts the metadata records it passes, by name."""

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        self.metadata: Counter[str] = Counter()

    def records(self):  # type: ignore[override]
        for record in super().records():
            if type(record) is MetadataRecord:
                self.metadata[record.name] += 1
            yield record


def mcap_info(path: str | Path) -> dict[str, Any]:
    """An MCAP file's summary from one damage-tolerant pass (``kind`` = ``"mcap"``)."""
    path = Path(path)
    per_type: Counter[str] = Counter()
    per_source: Counter[str] = Counter()
    per_topic: Counter[str] = Counter()
    seqs: dict[tuple[str, int], list[int]] = defaultdict(list)
    valid = [None, None]
    logged = [None, None]
    malformed: list = []
    try:
        scan = _CountingScan(path)
    except McapFormatError as exc:
        raise InfoError(one_line(exc)) from None
    with scan:
        for entry in read_entries(scan, malformed=malformed):
            per_type[entry.type] += 1
            per_source[entry.source] += 1
            per_topic[entry.topic] += 1
            seqs[(entry.source, entry.epoch)].append(entry.seq)
            for span, t in ((valid, entry.valid_time_ns), (logged, entry.log_time_ns)):
                if span[0] is None or t < span[0]:
                    span[0] = t
                if span[1] is None or t > span[1]:
                    span[1] = t
        report = scan.report
        schemas = scan.schemas
        channels = scan.channels
        metadata = scan.metadata
    gaps = []
    for (source, epoch), values in sorted(seqs.items()):
        for first, last in _sequence_gaps(values):
            gaps.append({"source": source, "epoch": epoch, "first_seq": first, "last_seq": last})
    channel_rows: dict[tuple[str, str], dict[str, Any]] = {}
    for channel in channels.values():
        schema = schemas.get(channel.schema_id)
        key = (channel.topic, schema.name if schema else "")
        row = channel_rows.setdefault(key, {"topic": key[0], "schema": key[1], "channels": 0,
                                            "messages": per_topic.get(channel.topic, 0)})
        row["channels"] += 1
    for (topic, schema_name, why), n in report.unknown.items():
        row = channel_rows.setdefault((topic, schema_name), {
            "topic": topic, "schema": schema_name, "channels": 0, "messages": 0})
        row["messages"] += n
        row["not_events"] = why
    return {
        "kind": "mcap",
        "path": str(path),
        "size_bytes": path.stat().st_size,
        "events": sum(per_type.values()),
        "messages": report.messages,
        "valid_time": _span(tuple(valid) if valid[0] is not None else None),
        "log_time": _span(tuple(logged) if logged[0] is not None else None),
        "per_type": dict(sorted(per_type.items())),
        "per_source": dict(sorted(per_source.items())),
        "schemas": sorted({(s.name, s.encoding) for s in schemas.values()}),
        "channels": sorted(channel_rows.values(), key=lambda r: r["topic"]),
        "metadata": dict(sorted(metadata.items())),
        "malformed_samples": len(malformed),
        "gaps": {"count": len(gaps),
                 "missing_events": sum(g["last_seq"] - g["first_seq"] + 1 for g in gaps),
                 "listed": gaps[:MAX_LISTED_GAPS]},
        "damage": {
            "complete": report.complete, "damaged": report.damaged, "lost": report.lost,
            "lost_unknown": report.lost_unknown, "salvaged": report.salvaged,
            "bad_chunks": report.bad_chunks, "summary_total": report.total,
            "problems": list(report.problems), "summary": report.loss_text(),
            "not_events": report.unknown_messages,
        },
    }


# -- text -----------------------------------------------------------------------------------


def _span_text(span: dict[str, Any] | None) -> str:
    if span is None:
        return "-"
    return f"{span['first']} .. {span['last']} ({span['duration_s'] / 3600:,.2f} h)"


def format_info(info: dict[str, Any]) -> str:
    """The human-readable ``stockpile info`` text for :func:`ledger_info`/:func:`mcap_info`."""
    postgres = info.get("backend") == "postgresql"
    kind = ("ledger (PostgreSQL)" if postgres else "ledger (DuckDB)") \
        if info["kind"] == "ledger" else "MCAP"
    lines = [f"path:         {info['path']}", f"kind:         {kind}"]
    if info["size_bytes"] is not None:
        size_mib = info["size_bytes"] / (1 << 20)
        lines.append(f"size:         {info['size_bytes']:,} bytes ({size_mib:.2f} MiB)")
    if info["kind"] == "ledger":
        head = info["head"]
        if not postgres:
            lines.append(f"created by:   DuckDB {info['duckdb_created_by'] or '?'}")
        lines += [f"events:       {info['events']:,} (head global_seq {head['global_seq']})",
                  f"valid time:   {_span_text(info['valid_time'])}",
                  f"recorded:     {_span_text(info['recorded_time'])}"]
    else:
        lines += [f"events:       {info['events']:,} ({info['messages']:,} messages read)",
                  f"valid time:   {_span_text(info['valid_time'])}",
                  f"log time:     {_span_text(info['log_time'])}"]
    lines.append("per type:")
    lines += [f"  {name:<20} {n:>10,}" for name, n in info["per_type"].items()]
    lines.append("per source:")
    lines += [f"  {name:<20} {n:>10,}" for name, n in info["per_source"].items()]
    gaps = info["gaps"]
    if info["kind"] == "ledger":
        lines.append(f"gaps:         {gaps['open']} open ({gaps['missing_events']:,} events "
                     f"missing), {gaps['closed']} closed")
    else:
        lines.append(f"gaps:         {gaps['count']} in the sequences "
                     f"({gaps['missing_events']:,} events missing)")
    lines += [f"  {g['source']} epoch {g['epoch']}: seq {g['first_seq']}..{g['last_seq']}"
              for g in gaps["listed"]]
    if info["kind"] == "ledger":
        q = info["quarantine"]
        codes = ", ".join(f"{c} {n}" for c, n in q["by_code"].items()) or "-"
        lines.append(f"quarantine:   {q['count']} ({codes})")
        flags = ", ".join(f"{f} {n}" for f, n in info["flagged"].items()) or "-"
        lines.append(f"flagged:      {flags}")
        return "\n".join(lines)
    lines.append(f"schemas:      {len(info['schemas'])}")
    lines += [f"  {name} ({encoding})" for name, encoding in info["schemas"]]
    lines.append(f"channels:     {len(info['channels'])} topics")
    width = max((len(r["topic"]) for r in info["channels"]), default=0)
    for r in info["channels"]:
        extra = f"  (not events: {r['not_events']})" if "not_events" in r else ""
        lines.append(f"  {r['topic']:<{width}}  {r['schema']:<28} {r['messages']:>9,}{extra}")
    meta = ", ".join(f"{name} {n}" for name, n in info["metadata"].items()) or "-"
    lines.append(f"metadata:     {meta}")
    lines.append(f"malformed:    {info['malformed_samples']} kept samples")
    damage = info["damage"]
    state = "complete" if damage["complete"] else "DAMAGED" if damage["damaged"] else "incomplete"
    lines.append(f"integrity:    {state}: {damage['summary']}")
    return "\n".join(lines)


def describe(path: str | Path) -> dict[str, Any]:
    """:func:`ledger_info` or :func:`mcap_info`, by the file's content."""
    return mcap_info(path) if file_kind(path) == "mcap" else ledger_info(path)


def cmd_info(args: argparse.Namespace, *, stdout: TextIO | None = None,
             stderr: TextIO | None = None) -> int:
    """``stockpile info``: errors are one line on stderr and exit 2."""
    out = stdout or sys.stdout
    err = stderr or sys.stderr
    try:
        info = describe(args.file)
    except (InfoError, LedgerError, OSError) as exc:
        print(f"stockpile info: error: {one_line(exc)}", file=err)
        return EXIT_USAGE
    if args.json:
        out.write(json.dumps(info, indent=2) + "\n")
    else:
        out.write(format_info(info) + "\n")
    return EXIT_OK


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``info`` to the ``stockpile`` parser."""
    p = subparsers.add_parser(
        "info", help="summarise an MCAP session or a ledger (counts, time span, gaps, damage)",
        description="Describe an MCAP file or a ledger (told apart by content): size, time "
        "span, events per type and source, gaps; a ledger's quarantine; an MCAP file's "
        "schemas, channels and what a damaged file lost.")
    p.add_argument("file", metavar="FILE", help="an MCAP file, a ledger (DuckDB) file or a "
                   "PostgreSQL ledger's postgresql:// URL")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_info)

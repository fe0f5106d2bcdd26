"""``stockpile export-mcap``: a ledger's events as an MCAP file.

The events go out in global order with the conventions of :mod:`replay.mcap_format`:
``log_time`` = the ledger's recorded time, ``publish_time`` = valid time, topic =
``stockpile/<site>/@v1/<type>/<source>``.  A ``stockpile.export`` metadata record
names the ledger, its head and chain hash.  The file is written beside its final
name and renamed into place when complete, so a failed export leaves no half file.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from common.progress import Progress
from replay.mcap_format import DEFAULT_CHUNK_BYTES
from replay.mcap_writer import EventWriter
from schemas.events import key_expr


@dataclass
class ExportResult:
    path: str
    events: int
    wall_s: float
    head_global_seq: int


def export_ledger(store, out_path: str | Path, *, site: str, types: list[str] | None = None,
                  progress: Progress | None = None,
                  chunk_size_bytes: int = DEFAULT_CHUNK_BYTES) -> ExportResult:
    """Write ``store``'s events (optionally only ``types``) to ``out_path``."""
    key_expr(site, "clock", "x")  # a bad site id fails here, before any file is made
    started = time.monotonic()
    out_path = Path(out_path)
    head = store.head()
    if progress is not None and progress.total is None and types is None:
        progress.total = head.global_seq + 1
    partial = out_path.with_name(out_path.name + ".partial")
    writer = EventWriter(partial, chunk_size_bytes=chunk_size_bytes)
    n = 0
    try:
        for row in store.read(types=types):
            writer.write_event(site, row, row.recorded_time_ns)
            n += 1
            if progress is not None and n % 1_000 == 0:
                progress.update_to(n)
        writer.close(("stockpile.export", {
            "ledger": str(getattr(store, "path", "")), "site": site, "events": n,
            "types": types or "all", "head_global_seq": head.global_seq,
            "head_chain_sha256": head.chain_sha256.hex()}))
        os.replace(partial, out_path)
    except BaseException:
        try:
            writer.close()
        finally:
            partial.unlink(missing_ok=True)
        raise
    if progress is not None:
        progress.update_to(n)
    return ExportResult(str(out_path), n, time.monotonic() - started, head.global_seq)

"""Print the fault-injection rows (``build/faults/results.jsonl``) as a markdown table.

``python tests/faults/table.py [RESULTS.jsonl]`` (default: ``$STOCKPILE_FAULTS_RESULTS``,
else ``build/faults/results.jsonl``); ``make faults`` runs it at the end.  Columns: the
fault, events published, events ledgered, events in open gaps (and gap records), and the
seconds from the fault's end until the ledger was caught up again (the largest over the
case's faults).  Exit 0, or 2 with one line on stderr when the file cannot be read.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

DEFAULT = Path(__file__).resolve().parents[2] / "build" / "faults" / "results.jsonl"


def table(rows: list[dict]) -> str:
    lines = ["| fault | events published | events ledgered | events in gaps (gaps) "
             "| seconds to recover |", "|---|---:|---:|---:|---:|"]
    for r in rows:
        recover = "-" if r.get("recover_s") is None else f"{r['recover_s']:.1f}"
        lines.append(f"| {r['fault']} | {r['published']:,} | {r['ledgered']:,} | "
                     f"{r['gap_events']:,} ({r.get('gaps', 0)}) | {recover} |")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    path = Path(argv[0]) if argv else Path(os.environ.get("STOCKPILE_FAULTS_RESULTS") or DEFAULT)
    try:
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, ValueError) as exc:
        print(f"faults table: cannot read {path}: {exc}", file=sys.stderr)
        return 2
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

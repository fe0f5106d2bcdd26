"""``stockpile ledger import`` on a full disk (issue: reliability, "a full disk is a pause").

A real full disk: a small tmpfs holding the ledger, the rest of it taken by a filler
file.  The import must fail with the operating system's own words on one line, exit 2,
and leave what was committed before committed and verifying; once space returns the
same file imports.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cli_in_process import run
from disk_helpers import fill, small_disk
from schemas.events import make_event
from schemas.jsonl import event_line
from services.loadgen import make_message

#: tmpfs size: room for the first import and DuckDB's file, not for the filler as well
DISK_MB = 16
#: space the filler leaves: a batch or two of the second import commits, then the disk fills
KEEP_FREE_BYTES = 2_000_000


def _events_file(path: Path, source: str, count: int, rng: np.random.Generator) -> Path:
    """``count`` scan events of ``source`` as canonical JSON lines (about 2 kB each)."""
    with open(path, "w", encoding="utf-8") as out:
        for seq in range(count):
            message = make_message("scan", seq, rng, 401)
            out.write(event_line(make_event(message, source=source, epoch=1, seq=seq)) + "\n")
    return path


def test_import_on_a_full_disk_reports_the_os_error_and_keeps_what_was_committed(
        tmp_path, capsys, seed):
    rng = np.random.default_rng(seed)
    first = _events_file(tmp_path / "first.jsonl", "lab.a", 1_000, rng)
    second = _events_file(tmp_path / "second.jsonl", "lab.b", 3_000, rng)
    with small_disk(tmp_path / "disk", DISK_MB) as disk:
        ledger = str(disk / "ledger.duckdb")
        code, out, err = run(capsys, "ledger", "import", str(first), "--ledger", ledger)
        assert code == 0, err
        filler = disk / "filler"
        assert fill(filler, keep_free_bytes=KEEP_FREE_BYTES) > 0    # fills mid-import

        code, out, err = run(capsys, "ledger", "import", str(second), "--ledger", ledger)
        assert code == 2, (out, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1, err
        assert "No space left on device" in lines[0], err
        assert "rollback" not in lines[0].lower(), err
        assert "Traceback" not in err

        filler.unlink()
        code, out, err = run(capsys, "ledger", "verify", "--ledger", ledger)
        assert code == 0, err
        head = int(out.split("head global_seq ")[1].split(",")[0])
        # the first file whole, then whole batches (1,000 lines) of the second, no part batch
        assert head in (999, 1_999, 2_999), out

        code, out, err = run(capsys, "ledger", "import", str(second), "--ledger", ledger,
                             "--json")
        assert code == 0, err
        counts = json.loads(out)
        assert (counts["appended"], counts["duplicate"]) == (3_999 - head, head - 999), counts
        code, out, err = run(capsys, "ledger", "verify", "--ledger", ledger)
        assert code == 0 and "head global_seq 3999," in out, (out, err)

"""``stockpile`` run in the test's own process, its output captured by pytest's capsys."""

from __future__ import annotations

from stockpile.cli import main as stockpile


def run(capsys, *args: str) -> tuple[int, str, str]:
    """``stockpile ARGS`` in this process: (exit code, stdout, stderr)."""
    capsys.readouterr()
    try:
        code = stockpile(list(args))
    except SystemExit as exc:  # argparse usage errors
        code = int(exc.code or 0)
    out = capsys.readouterr()
    return code, out.out, out.err

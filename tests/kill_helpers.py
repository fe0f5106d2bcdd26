"""Run a writer process that prints one ``ack N`` line per committed batch, and SIGKILL it."""

from __future__ import annotations

import os
import signal
import subprocess


def run_until_killed(argv: list[str], acks_before_kill: int) -> list[int]:
    """Start ``argv``, SIGKILL it right after ``acks_before_kill`` acks; return every ack
    it wrote (those it wrote after we stopped reading, before it died, included)."""
    child = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True)
    acked: list[int] = []
    try:
        while len(acked) < acks_before_kill:
            line = child.stdout.readline()
            assert line, "the writer exited before being killed"
            acked.append(int(line.split()[1]))
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=30)
        acked += [int(line.split()[1]) for line in child.stdout.read().splitlines() if line]
    finally:
        if child.poll() is None:
            child.kill()
        child.stdout.close()
    assert child.returncode == -signal.SIGKILL
    return acked

"""A real full disk for tests: a small tmpfs mounted for one test, and a filler file.

The tests run as root (here and in CI), so they can ``mount -t tmpfs``; where the
mount is refused the test is skipped with the reason.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from pathlib import Path
from typing import Iterator

import pytest

from common.disk import free_bytes

#: chunk sizes the filler writes, largest first, so it leaves no free byte behind
_FILL_CHUNKS_BYTES = (1 << 20, 1 << 12, 1)


@contextlib.contextmanager
def small_disk(directory: Path, size_mb: int) -> Iterator[Path]:
    """Mount a tmpfs of ``size_mb`` MiB on ``directory`` for the block; unmounted after,
    also when the block fails.  Skips the test when the mount is refused."""
    directory.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_mb}M", "tmpfs",
                              str(directory)], capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs for a real full disk: "
                    f"{(mounted.stderr or mounted.stdout).strip() or mounted.returncode}")
    try:
        yield directory
    finally:
        if subprocess.run(["umount", str(directory)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(directory)], capture_output=True)


def fill(path: Path, keep_free_bytes: int = 0) -> int:
    """Write ``path`` until its file system has at most ``keep_free_bytes`` free; return
    the bytes written."""
    written = 0
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        for chunk_bytes in _FILL_CHUNKS_BYTES:
            chunk = b"\0" * chunk_bytes
            while free_bytes(path.parent) - chunk_bytes >= keep_free_bytes:
                try:
                    written += os.write(fd, chunk)
                except OSError:
                    break
    finally:
        os.close(fd)
    return written


"""Writing the PKI's files: private keys with mode 0600 from the moment they are created,
public files (certificates, CRLs, the index) with mode 0644, each through a temporary
file renamed over the target so that a reader never sees half of one."""

from __future__ import annotations

import os
from pathlib import Path

PUBLIC_MODE = 0o644
PRIVATE_MODE = 0o600


def write_private(path: Path, data: bytes, *, force: bool) -> None:
    """Write a private key with mode 0600 from creation: a new file is created exclusively;
    with ``force`` a temporary file (also created 0600) replaces the old one."""
    if not force:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, PRIVATE_MODE)
        try:
            write_fd(fd, data)
        except BaseException:
            path.unlink(missing_ok=True)     # no half-written key left to refuse later
            raise
        return
    replace_atomically(path, data, PRIVATE_MODE)


def write_public(path: Path, data: bytes) -> None:
    """Write a public file (certificate, CRL, index) atomically: a temporary file, then
    rename."""
    replace_atomically(path, data, PUBLIC_MODE)


def replace_atomically(path: Path, data: bytes, mode: int) -> None:
    """Write ``data`` to a temporary file created exclusively with ``mode``, then rename it
    over ``path`` (a reader never sees half of it; a failure leaves no temporary file)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        write_fd(fd, data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_fd(fd: int, data: bytes) -> None:
    with os.fdopen(fd, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())

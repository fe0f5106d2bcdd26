"""Free space on the file system that holds a path.

The ledger service compares it with its watermark (``--min-free-mb``) after batches.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["BYTES_PER_MB", "free_bytes"]

#: bytes in one MiB, the unit of ``--min-free-mb``
BYTES_PER_MB = 1 << 20


def free_bytes(path: str | os.PathLike[str]) -> int:
    """Bytes an unprivileged writer may still use on the file system holding ``path``
    (``statvfs``'s available blocks); ``path`` may be a file that does not exist yet,
    in which case its nearest existing parent folder is asked."""
    where = Path(path)
    while not where.exists() and where != where.parent:
        where = where.parent
    st = os.statvfs(where)
    return st.f_bavail * st.f_frsize

"""The ledger service's checkpoints of the chain head (:mod:`ledger.checkpoint`): written
to a directory and published on ``stockpile/<site>/@ledger/checkpoint``."""

from __future__ import annotations

import time
from pathlib import Path

from ledger.checkpoint import make_checkpoint, write_checkpoint
from ledger.store import LedgerStore
from services.logfmt import log

SERVICE = "ledger"


def checkpoint_key(site: str) -> str:
    """Where each checkpoint of the chain head is published (its file's JSON)."""
    return f"stockpile/{site}/@ledger/checkpoint"


class Checkpointer:
    """Writes (and publishes) a checkpoint of the chain head when it moved, signed with
    the service's site certificate when it has one (``NAME.pem``, key ``NAME.key``).
    ``directory`` None: no checkpoints (an in-memory ledger)."""

    def __init__(self, store: LedgerStore, session, site: str, certificate: Path | None,
                 directory: str | None) -> None:
        self.store, self.site, self.directory = store, site, directory
        self.cert_path = certificate
        self.key_path = None if certificate is None else certificate.with_suffix(".key")
        self.publisher = session.declare_publisher(checkpoint_key(site))
        self.last_seq: int | None = None

    def take(self) -> None:
        head = self.store.head().global_seq
        if self.directory is None or head == self.last_seq:
            return
        try:
            checkpoint = make_checkpoint(self.store, self.site, time.time_ns(),
                                         key_path=self.key_path, certificate_path=self.cert_path)
            path = write_checkpoint(checkpoint, self.directory)
        except (OSError, ValueError) as exc:
            log(SERVICE, "checkpoint failed", level="error", error=str(exc).splitlines()[0])
            return
        self.last_seq = head
        self.publisher.put(path.read_bytes())
        log(SERVICE, "checkpoint", global_seq=head, path=str(path),
            signer=checkpoint.signer or "(unsigned)")

    def close(self) -> None:
        self.publisher.undeclare()

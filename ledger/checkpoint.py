"""Checkpoints of the chain head, kept outside the ledger file.

The hash chain shows that no stored row was changed *given the last row*, but someone
who can write the file can also delete its last rows, or rewrite a payload and
recompute every chain value after it.  A checkpoint records the head at a moment
(global seq, chain value, recorded time), signed with the ledger service's site
certificate, and is kept where the ledger file is not (another directory, the MCAP
recording, head office).  :func:`check_checkpoint` then proves that a ledger still holds
the checkpointed prefix, or names what happened to it:

- ``contains``: the row at the checkpoint's global seq has the checkpointed chain value,
  so every row up to it is the one checkpointed (``ledger verify`` checks the rest);
- ``truncated``: the ledger ends before the checkpoint's global seq;
- ``rewritten``: the row is there with another chain value;
- ``bad-signature``: the checkpoint itself was altered, or its certificate is not the
  site CA's.

A checkpoint file is one JSON object: the signed fields (``site``, ``global_seq``,
``chain_sha256`` hex, ``recorded_time_ns``, ``made_ns``), then ``signer`` (the
certificate's common name), ``signature`` (base64 DER, ECDSA-SHA256 over the canonical
JSON of the signed fields) and ``certificate`` (PEM).  An unsigned checkpoint (a yard
without TLS) has ``signature`` null and proves only what the place it is kept proves.

The recorder keeps every checkpoint the ledger service publishes in its MCAP file: one
message per checkpoint, its JSON bytes unchanged, on a schema-less channel with message
encoding ``json`` whose topic is the key it was published on,
``stockpile/<site>/@ledger/checkpoint`` (:func:`is_checkpoint_channel`).
:func:`read_mcap_checkpoints` reads them back with the ``mcap`` library.
"""

from __future__ import annotations

import base64
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator

from mcap.reader import NonSeekingReader, make_reader

from ledger.store import LedgerStore
from security.signing import SignatureInvalid, check, common_name, sign

SIGNED_FIELDS = ("site", "global_seq", "chain_sha256", "recorded_time_ns", "made_ns")
FINDINGS = ("contains", "truncated", "rewritten", "bad-signature", "empty")
#: the message encoding of a checkpoint channel in an MCAP file (schema-less JSON)
MCAP_ENCODING = "json"
_MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class Checkpoint:
    """The chain head at a moment, optionally signed."""

    site: str
    global_seq: int
    chain_sha256: str  # hex
    recorded_time_ns: int | None
    made_ns: int  # wall-clock UTC ns when it was made
    signer: str = ""
    signature: str | None = None  # base64 DER
    certificate: str | None = None  # PEM

    def signed_bytes(self) -> bytes:
        """The canonical JSON of the signed fields."""
        data = {name: getattr(self, name) for name in SIGNED_FIELDS}
        return json.dumps(data, sort_keys=True, separators=(",", ":")).encode()


@dataclass(frozen=True)
class CheckpointReport:
    """What :func:`check_checkpoint` found (``finding`` is one of :data:`FINDINGS`)."""

    ok: bool
    finding: str
    detail: str
    signer: str = ""


def make_checkpoint(store: LedgerStore, site: str, made_ns: int, *,
                    key_path: str | Path | None = None,
                    certificate_path: str | Path | None = None) -> Checkpoint:
    """A checkpoint of ``store``'s head, signed when a key and certificate are given."""
    head = store.head()
    unsigned = Checkpoint(site, head.global_seq, head.chain_sha256.hex(), head.recorded_time_ns,
                          int(made_ns))
    if key_path is None or certificate_path is None:
        return unsigned
    pem = Path(certificate_path).read_bytes()
    signature = sign(unsigned.signed_bytes(), key_path)
    return Checkpoint(**{**asdict(unsigned), "signer": common_name(pem),
                         "signature": base64.b64encode(signature).decode("ascii"),
                         "certificate": pem.decode("ascii")})


def write_checkpoint(checkpoint: Checkpoint, directory: str | Path) -> Path:
    """Write ``checkpoint-<global_seq>-<made_ns>.json`` in ``directory`` atomically."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"checkpoint-{checkpoint.global_seq}-{checkpoint.made_ns}.json"
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(asdict(checkpoint), indent=1) + "\n")
    os.replace(tmp, path)
    return path


def read_checkpoint(path: str | Path) -> Checkpoint:
    """A checkpoint file; ValueError when it is not one."""
    try:
        text = Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"{path} is not a checkpoint: {exc}") from None
    return checkpoint_from_json(text, str(path))


def checkpoint_from_json(text: bytes | str, where: str) -> Checkpoint:
    """A checkpoint from its JSON (a file's or a message's); ValueError naming ``where``."""
    try:
        data = json.loads(text)
        return Checkpoint(site=str(data["site"]), global_seq=int(data["global_seq"]),
                          chain_sha256=str(data["chain_sha256"]),
                          recorded_time_ns=None if data["recorded_time_ns"] is None
                          else int(data["recorded_time_ns"]),
                          made_ns=int(data["made_ns"]), signer=str(data.get("signer", "")),
                          signature=data.get("signature"), certificate=data.get("certificate"))
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{where} is not a checkpoint: {exc}") from None


def checkpoint_topic(site: str) -> str:
    """The MCAP topic (and Zenoh key) of ``site``'s checkpoints."""
    return f"stockpile/{site}/@ledger/checkpoint"


def is_checkpoint_channel(topic: str, message_encoding: str) -> bool:
    """Whether an MCAP channel carries checkpoints (:func:`checkpoint_topic`, JSON)."""
    parts = topic.split("/")
    return (len(parts) == 4 and parts[0] == "stockpile" and parts[2:] == ["@ledger", "checkpoint"]
            and message_encoding == MCAP_ENCODING)


def is_mcap(path: str | Path) -> bool:
    """Whether ``path`` is a file that starts like an MCAP file."""
    try:
        with open(path, "rb") as f:
            return f.read(len(_MCAP_MAGIC)) == _MCAP_MAGIC
    except OSError:
        return False


def read_mcap_checkpoints(path: str | Path) -> tuple[list[tuple[int, Checkpoint]], str | None]:
    """The checkpoints an MCAP file holds, in file order, each with its message's log time
    (ns), and what stopped the reading early (a file cut short or damaged: the checkpoints
    before the damage are returned), or None.  ValueError for a message that is not a
    checkpoint."""
    raw: list[tuple[str, int, bytes]] = []
    problem = None
    try:
        raw.extend(_checkpoint_messages(Path(path)))
    except Exception as exc:  # noqa: BLE001 - the mcap library's errors for a damaged file
        text = str(exc).strip()
        problem = (f"{type(exc).__name__}: {text.splitlines()[0]}" if text else
                   f"it ends early or is damaged ({type(exc).__name__})")
    return [(log_time, checkpoint_from_json(
        data, f"{path}: the message on {topic} logged at {log_time}"))
        for topic, log_time, data in raw], problem


def _checkpoint_messages(path: Path) -> Iterator[tuple[str, int, bytes]]:
    """(topic, log time, bytes) of the checkpoint messages: through the summary's chunk
    indexes when the file has them, else one linear pass."""
    with open(path, "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        try:
            summary = reader.get_summary()
        except Exception:  # noqa: BLE001 - no footer: a file cut short, read linearly
            summary = None
        if summary is not None and summary.chunk_indexes:
            topics = [c.topic for c in summary.channels.values()
                      if is_checkpoint_channel(c.topic, c.message_encoding)]
            if not topics:
                return
            for _schema, channel, message in reader.iter_messages(topics=topics,
                                                                  log_time_order=False):
                yield channel.topic, message.log_time, message.data
            return
        stream.seek(0)
        for _schema, channel, message in NonSeekingReader(stream, validate_crcs=True
                                                          ).iter_messages(log_time_order=False):
            if is_checkpoint_channel(channel.topic, channel.message_encoding):
                yield channel.topic, message.log_time, message.data


def latest_checkpoint(directory: str | Path) -> Path | None:
    """The checkpoint file of ``directory`` with the highest global seq (then the latest)."""
    best, best_key = None, None
    for path in Path(directory).glob("checkpoint-*.json"):
        try:
            cp = read_checkpoint(path)
        except ValueError:
            continue
        key = (cp.global_seq, cp.made_ns)
        if best_key is None or key > best_key:
            best, best_key = path, key
    return best


def check_checkpoint(store: LedgerStore, checkpoint: Checkpoint, *,
                     ca_pem: bytes | None = None) -> CheckpointReport:
    """Whether ``store`` still holds the prefix ``checkpoint`` records (module docstring)."""
    signer = ""
    if checkpoint.signature is not None:
        try:
            signer = check(checkpoint.signed_bytes(), base64.b64decode(checkpoint.signature),
                           (checkpoint.certificate or "").encode(), ca_pem)
        except (SignatureInvalid, ValueError) as exc:
            return CheckpointReport(False, "bad-signature", f"the checkpoint does not hold: {exc}")
        if signer != checkpoint.signer:
            return CheckpointReport(False, "bad-signature",
                                    f"signed by {signer!r}, not by {checkpoint.signer!r}")
    elif ca_pem is not None:
        return CheckpointReport(False, "bad-signature",
                                "the checkpoint is unsigned, and a site CA was given")
    if checkpoint.global_seq < 0:
        return CheckpointReport(True, "empty", "the checkpoint is of an empty ledger", signer)
    head = store.head()
    if head.global_seq < checkpoint.global_seq:
        return CheckpointReport(
            False, "truncated",
            f"the ledger ends at global_seq {head.global_seq}; the checkpoint made at "
            f"{checkpoint.made_ns} holds {checkpoint.global_seq} "
            f"({checkpoint.global_seq - head.global_seq} rows are gone)", signer)
    rows = list(store.read(checkpoint.global_seq, checkpoint.global_seq + 1))
    if not rows or rows[0].chain_sha256.hex() != checkpoint.chain_sha256:
        found = rows[0].chain_sha256.hex() if rows else "no row"
        return CheckpointReport(
            False, "rewritten",
            f"global_seq {checkpoint.global_seq} has chain {found}, the checkpoint "
            f"{checkpoint.chain_sha256}: the rows up to it were changed and re-chained", signer)
    return CheckpointReport(True, "contains",
                            f"the ledger holds the checkpointed prefix up to global_seq "
                            f"{checkpoint.global_seq}", signer)

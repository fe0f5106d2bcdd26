"""The signed-events part of the backend contract (:class:`SigningContract`, a base of
:class:`ledger.testing.LedgerStoreContract`), and helpers that make signed events with
real Ed25519 keys."""

from __future__ import annotations

import abc
import dataclasses
import tempfile
from pathlib import Path

from schemas import pb
from schemas.events import Event, make_event, set_timestamp_ns

from ledger.chain import chain_hash, payload_hash
from ledger.clock import ManualClock
from ledger.signing import (SigningPolicy, key_declaration, key_revocation, sign_event,
                            signature_block)
from ledger.store import LedgerStore
from ledger.verifying import CHAIN_MISMATCH
from security.event_keys import SigningKey, load_signing_key, new_signing_key, sign

YEAR_NS = 365 * 86_400 * 10**9


def make_keys(directory: Path, *names: str) -> dict[str, SigningKey]:
    """A fresh signing key per name, written in ``directory`` and read back."""
    keys = {}
    for name in names:
        new_signing_key(directory, name)
        keys[name] = load_signing_key(directory / f"{name}.sign.key")
    return keys


def key_declared(admin: SigningKey, subject: SigningKey, role: str, name: str, seq: int,
                 time_ns: int, valid_from_ns: int = 0,
                 valid_until_ns: int = 100 * YEAR_NS) -> Event:
    """The admin's signed declaration of ``subject``'s public key."""
    return key_declaration(admin, subject.public_raw, role, name, seq, time_ns, valid_from_ns,
                           valid_until_ns)


def key_revoked(admin: SigningKey, subject: SigningKey, seq: int, from_ns: int) -> Event:
    """The admin's signed revocation of ``subject`` from ``from_ns``."""
    return key_revocation(admin, subject.key_id, seq, from_ns, "key left the lab")


def assay(seq: int, valid_ns: int, fe: float = 62.5, source: str = "lab1") -> Event:
    """An assay of lot L1 with the given Fe."""
    m = pb.Assay(assay_id=f"AS-{seq}", lot_id="L1", analytes={"Fe": fe}, status=pb.FINAL,
                 lab_id="lab1")
    set_timestamp_ns(m.window_start, valid_ns)
    set_timestamp_ns(m.window_end, valid_ns)
    return make_event(m, source=source, epoch=1, seq=seq)


class SigningContract(abc.ABC):
    """Signed events, as every backend must keep and check them."""

    @abc.abstractmethod
    def create_store(self, clock: ManualClock, directory: Path,
                     signing: SigningPolicy | None = None) -> LedgerStore:
        """A new, empty store in ``directory`` with the given signing policy."""

    def _signed_ledger(self, directory: Path):
        keys = make_keys(directory / "keys", "admin", "lab", "scanner", "stranger")
        policy = SigningPolicy(frozenset({"assay"}), keys["admin"].key_id)
        store = self.create_store(ManualClock(1_000), directory, policy)
        a = keys["admin"]
        result = store.append([key_declared(a, a, "admin", "site admin", 0, 10),
                               key_declared(a, keys["lab"], "lab", "lab1", 1, 20),
                               key_declared(a, keys["scanner"], "scanner", "scan-1", 2, 30,
                                            valid_until_ns=YEAR_NS)])
        assert [o.status for o in result.outcomes] == ["appended"] * 3, result
        return store, keys

    def test_signed_events_are_kept_and_unsigned_or_badly_signed_ones_quarantined(
            self, tmp_path):
        store, keys = self._signed_ledger(tmp_path)
        lab, scanner, stranger = keys["lab"], keys["scanner"], keys["stranger"]
        forged = dataclasses.replace(sign_event(assay(5, 1_000, fe=70.0), lab),
                                     signature=sign(stranger, b"something else"))
        moved = dataclasses.replace(assay(6, 1_000, fe=70.0),
                                    signer=lab.key_id, signature=sign_event(assay(0, 1_000), lab).signature)
        batch = [sign_event(assay(0, 1_000), lab),            # appended
                 assay(1, 1_000),                          # unsigned
                 forged,                                   # bad_signature
                 moved,                                    # another event's signature
                 sign_event(assay(2, 1_000), stranger),        # unknown_key
                 sign_event(assay(3, 2 * YEAR_NS), scanner),   # key_not_valid (first: period)
                 sign_event(assay(4, 1_000), scanner)]         # key_role
        result = store.append(batch)
        codes = [o.code if o.status != "appended" else "appended" for o in result.outcomes]
        assert codes == ["appended", "unsigned", "bad_signature", "bad_signature",
                         "unknown_key", "key_not_valid", "key_role"], result
        [row] = list(store.read(types=["assay"]))
        assert (row.signer, row.signature) == (lab.key_id, batch[0].signature)
        assert row.to_event() == dataclasses.replace(batch[0], recorded_time_ns=row.recorded_time_ns)
        assert [q.code for q in store.quarantine()] == codes[1:]
        assert store.verify().ok
        store.close()

    def test_a_revoked_key_signs_nothing_from_its_revocation_on(self, tmp_path):
        store, keys = self._signed_ledger(tmp_path)
        lab = keys["lab"]
        assert store.append([sign_event(assay(0, 5_000), lab)]).appended == 1
        store.append([key_revoked(keys["admin"], lab, 3, 6_000)])
        if getattr(self, "persistent", False):  # the registry is rebuilt from the rows
            store = self.reopen(store, ManualClock(2_000))
        result = store.append([sign_event(assay(1, 5_500), lab), sign_event(assay(2, 6_000), lab)])
        assert [o.status for o in result.outcomes] == ["appended", "rejected"]
        assert result.outcomes[1].code == "revoked_key"
        # a lab key cannot revoke, nor declare keys
        bad = store.append([key_revoked(lab, keys["scanner"], 4, 0)])
        assert bad.outcomes[0].code == "key_role"
        assert store.verify().ok
        store.close()

    def test_only_the_pinned_admin_key_anchors_the_registry(self, tmp_path):
        keys = make_keys(tmp_path / "keys", "admin", "rogue", "lab")
        store = self.create_store(ManualClock(1_000), tmp_path / "l",
                                  SigningPolicy(frozenset({"assay"}), keys["admin"].key_id))
        rogue = keys["rogue"]
        result = store.append([key_declared(rogue, rogue, "admin", "rogue", 0, 10),
                               key_declared(rogue, keys["lab"], "lab", "lab1", 1, 20),
                               sign_event(assay(0, 1_000), keys["lab"])])
        assert [o.code for o in result.outcomes] == ["unknown_key"] * 3
        assert list(store.read()) == []
        store.close()

    def test_verify_rechecks_every_stored_signature(self, tmp_path):
        store, keys = self._signed_ledger(tmp_path)
        store.append([sign_event(assay(0, 1_000), keys["lab"])])
        assert store.verify().ok
        rows = list(store.read())
        # the signature dropped: the chain covers it
        stripped = self.replace_row(store, 3, rows[3]._replace(signer=None, signature=None))
        report = stripped.verify()
        assert (report.ok, report.first_bad_seq, report.problem) == (False, 3, CHAIN_MISMATCH)
        stripped.close()

    def test_verify_names_a_signature_that_does_not_hold_even_when_rechained(self, tmp_path):
        with tempfile.TemporaryDirectory() as directory:
            store, keys = self._signed_ledger(Path(directory))
            store.append([sign_event(assay(0, 1_000, fe=61.0), keys["lab"])])
            rows = list(store.read())
            forged = assay(0, 1_000, fe=70.0)
            row = rows[3]._replace(payload=forged.payload, payload_sha256=payload_hash(forged.payload))
            changed = self.replace_row(store, 3, row, rechain=True)
            report = changed.verify()
            assert not report.ok and report.first_bad_seq == 3
            assert report.problem.startswith("signature: bad_signature"), report
            changed.close()

    def replace_row(self, store: LedgerStore, global_seq: int, row, *,
                    rechain: bool = False) -> LedgerStore:
        """Store ``row`` in place of row ``global_seq`` behind the store's back (with
        ``rechain``, every chain value from it on recomputed); the store to verify."""
        rows = list(store.read())
        rows[global_seq] = row
        if rechain:
            rows = rechained(rows, global_seq)
        return self.replace_rows(store, rows)

    @abc.abstractmethod
    def replace_rows(self, store: LedgerStore, rows: list) -> LedgerStore:
        """Replace every stored row with ``rows`` behind the store's back; return a store
        that reads them."""


def rechained(rows: list, start: int) -> list:
    """``rows`` with every chain value from ``start`` on recomputed (no quarantine links)."""
    previous = rows[start - 1].chain_sha256 if start > 0 else bytes(32)
    out = rows[:start]
    for r in rows[start:]:
        r = r._replace(chain_sha256=chain_hash(
            previous, r.global_seq, r.type, r.source, r.epoch, r.seq, r.valid_time_ns,
            r.recorded_time_ns, r.payload_sha256, signature_block(r.signer, r.signature)))
        out.append(r)
        previous = r.chain_sha256
    return out

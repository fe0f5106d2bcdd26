"""verify's checks beyond the chain (ledger/verifying.py) and the signed-events rules
(ledger/signing.py): what the survivors of `make mutate` showed no test checked.

verify's problem strings are what an auditor reads, so they are pinned exactly; so are the
quarantine codes and details of each signing rule.  Real Ed25519 keys
(security.event_keys), real stores (MemoryStore and a DuckDB file) where a store is needed.
"""

from __future__ import annotations

import dataclasses
import hashlib

import pytest

from ledger.chain import GENESIS, payload_hash, quarantine_hash
from ledger.clock import ManualClock
from ledger.duckdb_store import DuckDBStore
from ledger.memory import MemoryStore
from ledger.records import Gap, QuarantineEntry, RecordedEvent
from ledger.signing import (KeyRecord, KeyRegistry, SigningPolicy, registry_from_rows,
                            sign_event, signature_block)
from ledger.testing_signing import YEAR_NS, assay, key_declared, key_revoked, make_keys
from ledger.verifying import GapHistory, QuarantineLinks, SignatureCheck, flags_problem, quarantine_link
from schemas import pb
from schemas.events import decode_payload, make_event, set_timestamp_ns, signed_message
from security.event_keys import ROLE_TYPES, SigningKey, key_id_of, sign, signature_holds

UNTIL = 100 * YEAR_NS  # key_declared's default end of validity
GARBAGE = b"\xff\xff\xff"  # no protobuf message decodes from it


@pytest.fixture(scope="module")
def keys(tmp_path_factory) -> dict[str, SigningKey]:
    return make_keys(tmp_path_factory.mktemp("keys"), "admin", "other", "lab", "rogue", "aud")


@pytest.fixture(params=["memory", "duckdb"])
def backend(request):
    return request.param


def open_store(backend: str, tmp_path, policy: SigningPolicy | None):
    clock = ManualClock(1_000)
    if backend == "memory":
        return MemoryStore(clock, signing=policy)
    return DuckDBStore(tmp_path / "l.duckdb", clock, signing=policy)


def row(type_name: str = "joint_reading", source: str = "s", epoch: int = 1, seq: int = 0,
        recorded: int = 0, payload: bytes = b"", flags: tuple[str, ...] = (),
        signer: str | None = None, signature: bytes | None = None) -> RecordedEvent:
    """A stored row as verify reads it (the chain value is not looked at here)."""
    return RecordedEvent(0, type_name, source, epoch, seq, 0, recorded, payload,
                         payload_hash(payload), b"", flags, signer, signature)


def as_row(event, global_seq: int = 0) -> RecordedEvent:
    return RecordedEvent(global_seq, event.type, event.source, event.epoch, event.seq,
                         event.valid_time_ns, 0, event.payload, payload_hash(event.payload), b"",
                         (), event.signer, event.signature)


def self_declared(key: SigningKey, role: str = "admin", name: str = "self", *,
                  key_id: str | None = None, public_key: bytes | None = None, seq: int = 0):
    """``key``'s own signed declaration of itself (key id and public key overridable)."""
    m = pb.SourceKeyDeclared(key_id=key_id or key.key_id, public_key=public_key or key.public_raw,
                             role=role, name=name)
    set_timestamp_ns(m.time, 10)
    set_timestamp_ns(m.valid_from, 0)
    set_timestamp_ns(m.valid_until, UNTIL)
    event = make_event(m, source="site-admin", epoch=1, seq=seq)
    if key_id is None:
        return sign_event(event, key)
    message = signed_message(event.type, event.source, event.epoch, event.seq,
                             event.valid_time_ns, payload_hash(event.payload))
    return dataclasses.replace(event, signer=key_id, signature=sign(key, message))


def registry_of(*events) -> KeyRegistry:
    return registry_from_rows([(e.type, e.payload) for e in events])


def check(registry: KeyRegistry, key: SigningKey, type_name: str, valid_ns: int,
          policy: SigningPolicy | None = None):
    """``registry.problem`` of an event of ``type_name`` at ``valid_ns`` signed by ``key``."""
    digest = hashlib.sha256(b"payload").digest()
    signature = sign(key, signed_message(type_name, "src", 1, 7, valid_ns, digest))
    return registry.problem(type_name, "src", 1, 7, valid_ns, digest, None, key.key_id,
                            signature, policy)


# --- the gap table -----------------------------------------------------------------


def test_a_repeat_of_the_highest_seq_is_stored_twice():
    history = GapHistory()
    assert history.row(row(seq=0)) is None
    assert history.row(row(seq=0)) == "seq 0 of s epoch 1 is stored twice"


def test_a_repeat_above_an_open_gap_is_stored_twice_and_leaves_the_gap_open():
    history = GapHistory()
    assert history.row(row(seq=0, recorded=10)) is None
    assert history.row(row(seq=3, recorded=30)) is None
    assert history.row(row(seq=3, recorded=40)) == "seq 3 of s epoch 1 is stored twice"
    assert history.gaps == [Gap(0, "s", 1, 1, 2, 30)]


def _closed_and_reopened() -> GapHistory:
    history = GapHistory()
    for seq, recorded in ((0, 10), (3, 30), (2, 40)):
        assert history.row(row(seq=seq, recorded=recorded)) is None
    assert history.gaps == [Gap(0, "s", 1, 1, 2, 30, 40), Gap(1, "s", 1, 1, 1, 30)]
    return history


def test_gap_problems_name_the_stored_and_the_recomputed_gap():
    history = _closed_and_reopened()
    gaps = history.gaps
    assert history.problem(list(gaps)) is None
    assert history.problem([dataclasses.replace(gaps[0], closed_recorded_ns=41), gaps[1]]) == (
        "gap row 0 is gap 0 of s epoch 1 seq 1..2 opened at 30, closed at 41 where the rows "
        "give gap 0 of s epoch 1 seq 1..2 opened at 30, closed at 40 (a gap row was edited, "
        "deleted or added)")
    assert history.problem([gaps[0], dataclasses.replace(gaps[1], closed_recorded_ns=50)]) == (
        "gap row 1 is gap 1 of s epoch 1 seq 1..1 opened at 30, closed at 50 where the rows "
        "give gap 1 of s epoch 1 seq 1..1 opened at 30, open (a gap row was edited, deleted "
        "or added)")


def test_gap_problems_name_an_added_and_a_deleted_gap_row():
    history = _closed_and_reopened()
    gaps = history.gaps
    assert history.problem(gaps + [Gap(2, "s", 1, 7, 8, 60)]) == (
        "3 gap rows where the rows give 2: gap 2 of s epoch 1 seq 7..8 opened at 60, open is "
        "not implied by the rows (a gap row was added, or rows deleted)")
    assert history.problem(gaps[:1]) == (
        "1 gap rows where the rows give 2: gap 1 of s epoch 1 seq 1..1 opened at 30, open has "
        "no gap row (a gap row was deleted)")


# --- flags ---------------------------------------------------------------------------


def test_flags_of_a_payload_that_does_not_decode_and_of_an_unknown_lot():
    assert flags_problem(row("assay", payload=GARBAGE), set()) == "payload does not decode"
    unknown = as_row(assay(0, 1_000))
    assert flags_problem(unknown, set()) == "flags [] where the payloads before it give ['unknown_lot']"
    assert flags_problem(unknown._replace(flags=("unknown_lot",)), set()) is None


# --- quarantine links ------------------------------------------------------------------


def entry(quarantine_id: int, after: int, previous: bytes, existing: int | None = None,
          chain: bytes | None = None) -> QuarantineEntry:
    e = QuarantineEntry(quarantine_id, 100 + quarantine_id, "assay", "lab1", 1, quarantine_id, 5,
                        "conflict", "stored with another payload", b"raw",
                        existing_global_seq=existing, after_global_seq=after)
    return dataclasses.replace(e, chain_sha256=chain if chain is not None
                               else quarantine_link(previous, e))


def test_quarantine_links_follow_the_chain():
    e0 = entry(0, 2, GENESIS, existing=1)
    e1 = entry(1, 2, e0.chain_sha256)
    links = QuarantineLinks([e0, e1])
    assert links.before(2, GENESIS) == (GENESIS, None)  # placed after row 2: not yet
    assert links.before(3, GENESIS) == (e1.chain_sha256, None)
    assert links.next == 2 and links.problem_after(3) is None


def test_a_quarantine_link_covers_the_existing_global_seq():
    e = entry(0, 4, GENESIS, existing=7)
    assert quarantine_link(GENESIS, e) == quarantine_hash(
        GENESIS, 0, 4, 100, 1, 0, 5, 7, "assay", "lab1", "conflict",
        "stored with another payload", b"raw")
    assert quarantine_link(GENESIS, e) != quarantine_link(
        GENESIS, dataclasses.replace(e, existing_global_seq=None))


def test_verify_accepts_a_ledger_with_a_conflict(backend, tmp_path):
    store = open_store(backend, tmp_path, None)
    store.append([assay(0, 1_000)])
    result = store.append([assay(0, 1_000, fe=70.0)])
    assert [o.code for o in result.outcomes] == ["conflict"]
    [conflict] = store.quarantine()
    assert conflict.existing_global_seq == 0
    head = list(store.read())[0].chain_sha256
    assert conflict.chain_sha256 == quarantine_link(head, conflict)
    assert store.verify().ok
    store.close()


def test_quarantine_link_problems():
    e0 = entry(0, 1, GENESIS)
    assert QuarantineLinks([entry(1, 1, GENESIS)]).before(5, GENESIS) == (
        GENESIS, "quarantine entry 1 where 0 was expected (a quarantine entry was deleted or added)")
    assert QuarantineLinks([e0, entry(1, 0, e0.chain_sha256)]).before(5, GENESIS) == (
        e0.chain_sha256, "quarantine entry 1 is placed before the entry ahead of it")
    assert QuarantineLinks([entry(0, -2, GENESIS)]).before(0, GENESIS) == (
        GENESIS, "quarantine entry 0 is placed before the entry ahead of it")
    assert QuarantineLinks([entry(0, 1, GENESIS, chain=bytes(32))]).before(5, GENESIS) == (
        GENESIS, "quarantine entry 0: chain hash mismatch (the entry was edited, or one before "
        "it deleted)")
    links = QuarantineLinks([e0])
    assert links.before(1, GENESIS) == (GENESIS, None)
    assert links.problem_after(1) == (
        "quarantine entry 0 is placed after global_seq 1, the ledger holds 1 rows")


# --- signatures re-checked by verify -------------------------------------------------


def test_verify_names_an_unsigned_key_declaration(keys):
    unsigned = dataclasses.replace(self_declared(keys["admin"]), signer=None, signature=None)
    assert SignatureCheck(None).row(as_row(unsigned)) == (
        "signature: unsigned: a source_key_declared must be signed by an admin key")


def test_verify_names_a_signed_row_whose_payload_does_not_decode(keys):
    bad = row("assay", payload=GARBAGE, signer=keys["lab"].key_id, signature=bytes(64))
    assert SignatureCheck(None).row(bad) == "payload does not decode"


def test_verify_does_not_reimpose_the_signed_types(keys):
    # a row with a signer and no signature adds no signature block: unsigned to the chain
    half = as_row(assay(0, 1_000))._replace(signer=keys["lab"].key_id)
    assert SignatureCheck(SigningPolicy(frozenset({"assay"}), keys["admin"].key_id)).row(half) is None
    assert SignatureCheck(None).row(as_row(assay(1, 1_000))) is None


def test_verify_holds_a_ledger_to_the_pinned_admin_key(keys, tmp_path):
    rogue, admin = keys["rogue"], keys["admin"]
    store = DuckDBStore(tmp_path / "l.duckdb", ManualClock(1_000))
    assert store.append([self_declared(rogue)]).appended == 1
    assert store.verify().ok
    store.close()
    pinned = DuckDBStore(tmp_path / "l.duckdb", ManualClock(2_000),
                         signing=SigningPolicy(frozenset(), admin.key_id))
    report = pinned.verify()
    assert (report.ok, report.first_bad_seq, report.problem) == (
        False, 0, f"signature: unknown_key: self-declared admin key {rogue.key_id} is not the "
        f"site's admin key {admin.key_id}")
    pinned.close()


# --- the signing rules ----------------------------------------------------------------


def test_signature_block_layout():
    signature = bytes(range(64))
    assert signature_block("ab12", signature) == (
        b"S" + b"\x04\x00" + b"ab12" + b"\x40\x00" + signature)
    long_id = "k" * 300
    assert signature_block(long_id, b"\x01" * 258) == (
        b"S" + b"\x2c\x01" + long_id.encode() + b"\x02\x01" + b"\x01" * 258)
    assert signature_block(None, signature) == b""
    assert signature_block("ab12", None) == b""
    assert signature_block(None, None) == b""


def test_sign_event_signs_the_signed_message(keys):
    lab = keys["lab"]
    event = assay(3, 1_000)
    s = sign_event(event, lab)
    message = signed_message("assay", "lab1", 1, 3, event.valid_time_ns,
                             hashlib.sha256(event.payload).digest())
    assert (s.signer, s.signature) == (lab.key_id, sign(lab, message))
    assert signature_holds(lab.public_raw, s.signature, message)
    assert dataclasses.replace(s, signer=None, signature=None) == event


def test_registry_from_rows_records_each_key(keys):
    admin, lab, other = keys["admin"], keys["lab"], keys["other"]
    registry = registry_of(
        key_declared(admin, admin, "admin", "site admin", 0, 10),
        key_declared(admin, lab, "lab", "lab1", 1, 20, valid_from_ns=500, valid_until_ns=9_000),
        key_revoked(admin, lab, 2, 6_000),
        key_revoked(admin, other, 3, 7_000))  # never declared: nothing to revoke
    assert registry.keys == {
        admin.key_id: KeyRecord(admin.key_id, admin.public_raw, "admin", "site admin", 0, UNTIL),
        lab.key_id: KeyRecord(lab.key_id, lab.public_raw, "lab", "lab1", 500, 9_000, 6_000)}
    assert type(registry.keys[lab.key_id].public_key) is bytes


def test_a_revocation_takes_the_earliest_time_and_survives_a_redeclaration(keys):
    admin, lab = keys["admin"], keys["lab"]
    declared = key_declared(admin, lab, "lab", "lab1", 1, 20)
    registry = registry_of(declared, key_revoked(admin, lab, 2, 6_000),
                           key_revoked(admin, lab, 3, 8_000))
    assert registry.keys[lab.key_id].revoked_from_ns == 6_000
    registry = registry_of(declared, key_revoked(admin, lab, 2, 6_000),
                           key_revoked(admin, lab, 3, 4_000))
    assert registry.keys[lab.key_id].revoked_from_ns == 4_000
    registry = registry_of(declared, key_revoked(admin, lab, 2, 6_000),
                           key_declared(admin, lab, "lab", "lab one", 4, 30, valid_until_ns=YEAR_NS))
    assert registry.keys[lab.key_id] == KeyRecord(lab.key_id, lab.public_raw, "lab", "lab one",
                                                  0, YEAR_NS, 6_000)


def test_a_redeclared_revoked_key_still_signs_nothing_from_its_revocation(backend, tmp_path, keys):
    admin, lab = keys["admin"], keys["lab"]
    store = open_store(backend, tmp_path, SigningPolicy(frozenset({"assay"}), admin.key_id))
    store.append([key_declared(admin, admin, "admin", "site admin", 0, 10),
                  key_declared(admin, lab, "lab", "lab1", 1, 20),
                  key_revoked(admin, lab, 2, 6_000),
                  key_declared(admin, lab, "lab", "lab1", 3, 30)])
    result = store.append([sign_event(assay(0, 5_999), lab), sign_event(assay(1, 6_000), lab)])
    assert [o.status for o in result.outcomes] == ["appended", "rejected"]
    [q] = store.quarantine()
    assert (q.code, q.detail) == ("revoked_key", f"key {lab.key_id} (lab1) is revoked from 6000 ns")
    assert store.verify().ok
    store.close()


def test_unsigned_events(keys):
    registry = KeyRegistry()
    policy = SigningPolicy(frozenset({"assay"}), keys["admin"].key_id)
    digest = bytes(32)

    def unsigned(type_name, policy, signer=None):
        return registry.problem(type_name, "src", 1, 0, 0, digest, None, signer, None, policy)

    for type_name in ("source_key_declared", "source_key_revoked"):
        assert unsigned(type_name, None) == (
            "unsigned", f"a {type_name} must be signed by an admin key")
    assert unsigned("assay", None) is None
    assert unsigned("assay", policy) == ("unsigned", "this site requires assay to be signed")
    assert unsigned("scan", policy) is None
    # a signer without a signature is unsigned
    assert unsigned("assay", policy, signer=keys["lab"].key_id) == (
        "unsigned", "this site requires assay to be signed")
    assert unsigned("scan", None, signer=keys["lab"].key_id) is None


def test_an_unsigned_key_declaration_is_quarantined(backend, tmp_path, keys):
    admin = keys["admin"]
    store = open_store(backend, tmp_path, None)
    event = dataclasses.replace(self_declared(admin), signer=None, signature=None)
    assert [o.code for o in store.append([event]).outcomes] == ["unsigned"]
    assert [(q.code, q.detail) for q in store.quarantine()] == [
        ("unsigned", "a source_key_declared must be signed by an admin key")]
    store.close()


def test_validity_period_from_inclusive_until_exclusive(keys):
    admin, lab = keys["admin"], keys["lab"]
    registry = registry_of(key_declared(admin, lab, "lab", "lab1", 1, 20,
                                        valid_from_ns=1_000, valid_until_ns=2_000))
    outside = "valid time {} ns is outside key " + lab.key_id + "'s period 1000..2000 ns"
    assert check(registry, lab, "assay", 999) == ("key_not_valid", outside.format(999))
    assert check(registry, lab, "assay", 1_000) is None
    assert check(registry, lab, "assay", 1_999) is None
    assert check(registry, lab, "assay", 2_000) == ("key_not_valid", outside.format(2000))


def test_revoked_from_its_time_on(keys):
    admin, lab = keys["admin"], keys["lab"]
    registry = registry_of(key_declared(admin, lab, "lab", "lab1", 1, 20),
                           key_revoked(admin, lab, 2, 1_500))
    assert check(registry, lab, "assay", 1_499) is None
    assert check(registry, lab, "assay", 1_500) == (
        "revoked_key", f"key {lab.key_id} (lab1) is revoked from 1500 ns")


def test_bad_signature_and_unknown_key(keys):
    admin, lab, other = keys["admin"], keys["lab"], keys["other"]
    registry = registry_of(key_declared(admin, lab, "lab", "lab1", 1, 20))
    digest = hashlib.sha256(b"payload").digest()
    forged = sign(other, signed_message("assay", "src", 1, 7, 100, digest))
    assert registry.problem("assay", "src", 1, 7, 100, digest, None, lab.key_id, forged, None) == (
        "bad_signature", f"the signature does not hold for key {lab.key_id} (lab1)")
    assert check(registry, other, "assay", 100) == (
        "unknown_key", f"key {other.key_id} was never declared by an admin")


@pytest.mark.parametrize("role", sorted(ROLE_TYPES))
def test_role_table(keys, role):
    admin, aud = keys["admin"], keys["aud"]
    registry = registry_of(key_declared(admin, aud, role, "k1", 1, 20))
    for type_name in ("assay", "scan", "lot_declared", "source_key_declared", "location_fix",
                      "joint_estimate", "stack_started"):
        expected = None if type_name in ROLE_TYPES[role] else (
            "key_role", f"a {role} key (k1) may not sign {type_name}")
        assert check(registry, aud, type_name, 100) == expected, type_name


def test_a_role_outside_the_table_signs_nothing(keys):
    admin, aud = keys["admin"], keys["aud"]
    registry = registry_of(key_declared(admin, aud, "auditor", "aud1", 1, 20))
    assert check(registry, aud, "assay", 100) == (
        "key_role", "a auditor key (aud1) may not sign assay")


def test_the_first_self_declared_admin_anchors_a_ledger_without_a_pinned_key(
        backend, tmp_path, keys):
    admin, other = keys["admin"], keys["other"]
    store = open_store(backend, tmp_path, None)
    result = store.append([self_declared(admin, seq=0), self_declared(other, seq=1)])
    assert [o.status for o in result.outcomes] == ["appended", "rejected"]
    assert [(q.code, q.detail) for q in store.quarantine()] == [
        ("unknown_key", f"self-declared admin key {other.key_id}: this ledger already has an "
         "admin key")]
    assert store.verify().ok
    store.close()


def test_the_pinned_admin_anchors_even_beside_another_admin_key(keys):
    admin, other = keys["admin"], keys["other"]
    registry = registry_of(key_declared(other, other, "admin", "other admin", 0, 10))
    event = self_declared(admin)
    pinned = SigningPolicy(frozenset(), admin.key_id)
    message = decode_payload(event.type, event.payload)

    def problem(policy):
        return registry.problem(event.type, event.source, event.epoch, event.seq,
                                event.valid_time_ns, payload_hash(event.payload), message,
                                event.signer, event.signature, policy)

    assert problem(pinned) is None
    assert problem(None) == ("unknown_key", f"self-declared admin key {admin.key_id}: this "
                             "ledger already has an admin key")
    assert problem(SigningPolicy(frozenset(), other.key_id)) == (
        "unknown_key", f"self-declared admin key {admin.key_id} is not the site's admin key "
        f"{other.key_id}")


def test_only_a_self_declared_admin_whose_key_id_is_its_key_anchors(backend, tmp_path, keys):
    lab, rogue, admin = keys["lab"], keys["rogue"], keys["admin"]
    store = open_store(backend, tmp_path, None)
    # a self-declared lab key; an admin declaration under rogue's key id with admin's key
    claimed = self_declared(rogue, key_id=rogue.key_id, public_key=admin.public_raw, seq=1)
    assert key_id_of(admin.public_raw) != rogue.key_id
    result = store.append([self_declared(lab, role="lab", seq=0), claimed])
    assert [(q.code, q.detail) for q in store.quarantine()] == [
        ("unknown_key", f"key {lab.key_id} was never declared by an admin"),
        ("unknown_key", f"key {rogue.key_id} was never declared by an admin")]
    assert result.appended == 0
    store.close()


def test_describe_and_copy(keys):
    admin, lab = keys["admin"], keys["lab"]
    registry = registry_of(key_declared(admin, lab, "lab", "lab1", 1, 20))
    assert registry.describe(lab.key_id) == "lab1 (lab)"
    assert registry.describe("0" * 32) == ""
    assert registry.describe(None) == ""
    # an admin may declare any key id: None still names no key
    m = pb.SourceKeyDeclared(key_id="XXXX", public_key=lab.public_raw, role="lab", name="odd")
    set_timestamp_ns(m.valid_until, UNTIL)
    registry.learn("source_key_declared", m)
    assert registry.describe("XXXX") == "odd (lab)"
    assert registry.describe(None) == ""
    copy = registry.copy()
    assert copy.keys == registry.keys and copy.keys is not registry.keys
    copy.learn("source_key_revoked", pb.SourceKeyRevoked(key_id=lab.key_id))
    assert registry.keys[lab.key_id].revoked_from_ns is None
    assert copy.keys[lab.key_id].revoked_from_ns == 0

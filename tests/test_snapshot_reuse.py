"""The snapshot store's reuse rules (projector.query.SnapshotStore.find, _unchanged_since,
_config_key) on real ledgers (DuckDB file and in-memory) and a real snapshot file.

A snapshot serves a query (V, K) only when its position is at or before V, what it folded
was recorded by K, it was folded with the same fold version and config, its file exists,
and no geometry event at or before its position arrived after it by K.  The snapshot
states here are folds of machine declarations (geometry events) with the real fold.
"""

from __future__ import annotations

import pytest

from ledger.clock import ManualClock
from ledger.duckdb_store import DuckDBStore
from ledger.memory import MemoryStore
from ledger.testing import joint_event
from projector import fold as F
from projector.config import FoldConfig
from projector.query import SnapshotStore
from schemas import pb
from schemas.events import decode_payload, make_event, set_timestamp_ns

PILE = "P1"


def machine(seq: int, t: int, name: str | None = None):
    m = pb.MachineDeclared(machine_id=name or f"m{seq}", kind=1, rail_x_m=-20.0, rail_z_m=2.0,
                           l2_m=3.0, l3_m=1.0, l4_m=2.0, l5_m=30.0, cutting_radius_m=4.0)
    set_timestamp_ns(m.time, t)
    return make_event(m, source="site.machines", epoch=1, seq=seq)


@pytest.fixture(params=["memory", "duckdb"])
def ledger(request, tmp_path):
    clock = ManualClock(1_000)
    store = MemoryStore(clock) if request.param == "memory" else DuckDBStore(tmp_path / "l.duckdb", clock)
    # machines declared at valid 10, 20, 30, 40 (global seq 0..3), recorded at 1000
    store.append([machine(s, 10 * (s + 1)) for s in range(4)])
    yield store, clock
    store.close()


@pytest.fixture
def snaps(tmp_path):
    with SnapshotStore(tmp_path / "snaps.duckdb") as s:
        yield s


def fold_to(store, config, valid_ns: int, known_ns: int = 2**62):
    state = F.initial_state(config)
    for event in store.as_of(valid_ns, known_ns, types=list(F.GEOMETRY_TYPES)):
        F.apply(state, event)
    return state


def save(store, snaps, config, valid_ns, folded_recorded_ns=None, known_ns=None):
    """A snapshot folded to ``valid_ns`` with the ledger's head as it is now."""
    head = store.head()
    state = fold_to(store, config, valid_ns)
    snaps.save(state, head.global_seq, head.recorded_time_ns if known_ns is None else known_ns,
               folded_recorded_ns)
    return state


def found_at(snaps, store, config, v, k):
    found = snaps.find(store, config, v, k)
    if found is None:
        return None
    state, position = found
    assert state.high_water == position
    # the state folded exactly the geometry known at K up to its position
    assert sorted(state.machines) == sorted(
        decode_payload(r.type, r.payload).machine_id
        for r in store.read(types=["machine_declared"])
        if (r.valid_time_ns, r.global_seq) <= position and r.recorded_time_ns <= k)
    return position


def test_a_snapshot_serves_queries_at_or_after_its_position(ledger, snaps):
    store, _ = ledger
    config = FoldConfig(pile_id=PILE)
    assert snaps.find(store, config, 100, 10**9) is None
    save(store, snaps, config, 20, folded_recorded_ns=1_000)
    assert found_at(snaps, store, config, 20, 1_000) == (20, 1)    # the boundaries count
    assert found_at(snaps, store, config, 10**6, 10**9) == (20, 1)
    assert found_at(snaps, store, config, 19, 10**9) is None        # before its position
    assert found_at(snaps, store, config, 20, 999) is None          # folded events unknown at K


def test_the_latest_usable_snapshot_wins(ledger, snaps):
    store, _ = ledger
    config = FoldConfig(pile_id=PILE)
    for v in (10, 30, 20):
        save(store, snaps, config, v, folded_recorded_ns=1_000)
    assert found_at(snaps, store, config, 100, 10**9) == (30, 2)
    assert found_at(snaps, store, config, 29, 10**9) == (20, 1)
    assert found_at(snaps, store, config, 10, 10**9) == (10, 0)


def test_of_two_snapshots_at_one_valid_time_the_later_position_wins(ledger, snaps):
    store, clock = ledger
    config = FoldConfig(pile_id=PILE)
    save(store, snaps, config, 40, folded_recorded_ns=1_000)        # position (40, 3)
    clock.set_ns(2_000)
    store.append([machine(4, 40)])                                  # global seq 4, valid 40
    save(store, snaps, config, 40, folded_recorded_ns=2_000)        # position (40, 4)
    assert found_at(snaps, store, config, 40, 2_000) == (40, 4)
    # known before seq 4 arrived: only the first snapshot (and it still holds then)
    assert found_at(snaps, store, config, 40, 1_999) == (40, 3)


def test_late_geometry_makes_a_snapshot_unusable_once_it_is_known(ledger, snaps):
    store, clock = ledger
    config = FoldConfig(pile_id=PILE)
    save(store, snaps, config, 10, folded_recorded_ns=1_000)        # (10, 0)
    save(store, snaps, config, 30, folded_recorded_ns=1_000)        # (30, 2), head 3
    clock.set_ns(5_000)
    store.append([machine(4, 25, "late")])                          # seq 4 at valid 25
    # known before the late event arrived: the latest snapshot still holds
    assert found_at(snaps, store, config, 100, 4_999) == (30, 2)
    # known after: the late event lies before (30, 2), so only the earlier snapshot serves
    assert found_at(snaps, store, config, 100, 5_000) == (10, 0)
    assert found_at(snaps, store, config, 100, 10**9) == (10, 0)
    clock.set_ns(6_000)
    store.append([machine(5, 5, "very-late")])                      # before both
    assert found_at(snaps, store, config, 100, 5_999) == (10, 0)
    assert found_at(snaps, store, config, 100, 6_000) is None


def test_a_late_event_at_the_snapshot_position_or_after_it_does_no_harm(ledger, snaps):
    store, clock = ledger
    config = FoldConfig(pile_id=PILE)
    save(store, snaps, config, 30, folded_recorded_ns=1_000)        # (30, 2), head 3
    clock.set_ns(5_000)
    # valid 30 after global seq 2 (it comes after the position), valid 35, and a late
    # non-geometry event before the position: none invalidates the snapshot
    store.append([machine(4, 30, "same-time"), machine(5, 35, "later"),
                  joint_event("a.src", 0, 1)])
    assert found_at(snaps, store, config, 100, 10**9) == (30, 2)


def test_the_first_event_after_k_ends_the_search(ledger, snaps):
    store, clock = ledger
    config = FoldConfig(pile_id=PILE)
    save(store, snaps, config, 30, folded_recorded_ns=1_000)        # head 3
    clock.set_ns(3_000)
    store.append([machine(4, 35, "fine")])                          # after the position
    clock.set_ns(4_000)
    store.append([machine(5, 15, "late")])                          # before it
    assert found_at(snaps, store, config, 100, 3_000) == (30, 2)
    assert found_at(snaps, store, config, 100, 3_999) == (30, 2)
    assert found_at(snaps, store, config, 100, 4_000) is None


def test_a_snapshot_taken_with_more_known_serves_an_earlier_k(ledger, snaps):
    store, clock = ledger
    config = FoldConfig(pile_id=PILE)
    clock.set_ns(2_000)
    store.append([joint_event("a.src", 0, 1)])                      # head 4 at 2000
    # taken at K=2000 but everything folded was recorded at 1000
    save(store, snaps, config, 40, folded_recorded_ns=1_000)
    assert found_at(snaps, store, config, 40, 1_000) == (40, 3)
    # default: the folded events count as recorded at the K it was taken at
    save(store, snaps, config, 40, known_ns=2_000)
    assert snaps.count(config) == 2


def test_another_pile_config_or_fold_version_is_never_used(ledger, snaps, monkeypatch):
    store, _ = ledger
    config = FoldConfig(pile_id=PILE)
    save(store, snaps, config, 20, folded_recorded_ns=1_000)
    assert found_at(snaps, store, FoldConfig(pile_id="P2"), 100, 10**9) is None
    assert found_at(snaps, store, FoldConfig(pile_id=PILE, scan_batch=config.scan_batch + 1),
                    100, 10**9) is None
    assert snaps.count(config) == 1 and snaps.latest_valid_ns(config) == 20
    monkeypatch.setattr(F, "FOLD_VERSION", F.FOLD_VERSION + 1)
    assert found_at(snaps, store, config, 100, 10**9) is None
    assert snaps.count(config) == 0
    # the snapshot of the other version is the one drop_other_versions deletes
    removed, freed = snaps.drop_other_versions()
    assert removed == 1 and freed > 0 and snaps.count() == 0


def test_the_config_key_names_the_fold_version_and_the_config(ledger, snaps):
    from projector.query import _config_key

    config = FoldConfig(pile_id=PILE)
    assert _config_key(config) == f"fold v{F.FOLD_VERSION} {config!r}"
    store, _ = ledger
    save(store, snaps, config, 20, folded_recorded_ns=1_000)
    assert snaps.drop_other_versions() == (0, 0) and snaps.count(config) == 1


def test_a_lost_snapshot_file_is_a_miss_and_an_older_one_serves(ledger, snaps):
    store, _ = ledger
    config = FoldConfig(pile_id=PILE)
    save(store, snaps, config, 10, folded_recorded_ns=1_000)
    save(store, snaps, config, 30, folded_recorded_ns=1_000)
    [(name,)] = snaps._con.execute(
        f"SELECT payload FROM {snaps.TABLE} WHERE valid_ns = 30").fetchall()
    (snaps.folder / name).unlink()
    assert found_at(snaps, store, config, 100, 10**9) == (10, 0)

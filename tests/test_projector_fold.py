"""The projector end to end on a simulated yard: bitemporal fold, snapshots, late assays.

A short ``demo`` run of the simulator with ``--scan-events truth`` gives real scans and
scanner poses; a synthetic reclaim cut and two assays (a provisional one and the final
one that supersedes it, each with a bulk density of its own, unlike the pile's default)
are added.  Hypothesis then draws arrival delays for the events, a scan that arrives
minutes late, snapshots taken before it arrived, and (V, K) queries, and checks that the
snapshot-accelerated ``project(V, K)`` equals, figure for figure, a brute-force fold of
exactly the events with valid <= V and recorded <= K, filtered and ordered here,
independently of the store's ``as_of``; on the in-memory store and on DuckDB.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from ledger import open_ledger
from projector import cuts, fold as F
from projector.query import (FAR_FUTURE_NS, SnapshotStore, build_snapshots,
                                    grade_inputs, project, summarise)
from ledger.records import RecordedEvent
from schemas import pb
from schemas.events import Event, decode_payload, make_event, set_timestamp_ns
from schemas.jsonl import decode_line

from schemas.times import NS_PER_S as S  # noqa: E402
PILE = "P1"
#: the assays' bulk densities (t/m3): neither is the pile's default (2.4), so tonnes move
#: when an assay becomes known
DENSITY = {"A1": 2.2, "A2": 2.7}


def _stamp(msg, name: str, t_ns: int):
    set_timestamp_ns(getattr(msg, name), t_ns)
    return msg


class _Yard(dict):
    """The yard's events and times; its repr is short (Hypothesis prints a failing case's
    arguments, and the events' repr runs to megabytes)."""

    def __repr__(self) -> str:
        return f"<yard: {len(self['events'])} events>"


@pytest.fixture(scope="module")
def yard(small_yard_sim) -> dict:
    out = small_yard_sim
    events = [decode_line(line) for line in (out / "events.jsonl").read_text().splitlines()]
    assert all(isinstance(e, Event) for e in events)
    machine = next(decode_payload(e.type, e.payload) for e in events
                   if e.type == "machine_declared"
                   and decode_payload(e.type, e.payload).machine_id == "bwr1")
    first = next(e for e in events if e.type == "stack_started")
    ended = next(e for e in events if e.type == "stack_ended")
    lot = decode_payload(first.type, first.payload).lot_id
    t_end = max(e.valid_time_ns for e in events)
    # a cut through the first layer, after the last scan: the wheel centre 10 m above
    # a floor at 1 m, slewing across the middle of the pile
    pivot_z = machine.rail_z_m + machine.l2_m + machine.l3_m
    luff = math.asin((1.0 + machine.cutting_radius_m - pivot_z) / machine.l5_m)
    rho = machine.l4_m + machine.l5_m * math.cos(luff)
    slew_mid = math.asin(min(1.0, (30.0 - machine.rail_x_m) / rho))
    cut = pb.ReclaimCut(pile_id=PILE, cut_id="X-C01", bench_id="X", machine_id="bwr1",
                        travel_m=30.0, luff_rad=luff, slew_start_rad=slew_mid - 0.15,
                        slew_end_rad=slew_mid + 0.15, tonnes=100.0)
    _stamp(cut, "start_time", t_end + 10 * S)
    _stamp(cut, "end_time", t_end + 130 * S)
    window = (first.valid_time_ns - 60 * S, ended.valid_time_ns + 60 * S)

    def assay(assay_id: str, fe: float, density: float, status: int, supersedes: str = ""):
        a = pb.Assay(assay_id=assay_id, lot_id=lot, status=status, supersedes=supersedes,
                     lab_id="lab1", bulk_density_t_m3=density)
        a.analytes.update({"Fe": fe, "SiO2": 4.0})
        _stamp(a, "window_start", window[0])
        _stamp(a, "window_end", window[1])
        _stamp(a, "reported_time", window[1] + 3 * 3600 * S)
        return a

    extra = [make_event(cut, source="bwr1.plc", epoch=1, seq=0),
             make_event(assay("A1", 61.0, DENSITY["A1"], pb.PROVISIONAL), source="lab1",
                        epoch=1, seq=0),
             make_event(assay("A2", 63.5, DENSITY["A2"], pb.FINAL, "A1"), source="lab1",
                        epoch=1, seq=1)]
    pile = next(decode_payload(e.type, e.payload) for e in events if e.type == "pile_declared")
    assert pile.default_bulk_density_t_m3 not in DENSITY.values()
    return _Yard(events=events + extra, cut_end=t_end + 130 * S, lot=lot, t_end=t_end,
                 stack_started=first.valid_time_ns,
                 default_density=pile.default_bulk_density_t_m3)


def _ledger(events: list[Event], delays_ns: list[int], path: str | Path = ":memory:"):
    """A ledger (in memory, or the DuckDB file ``path``) holding the events, each recorded
    at valid time + its delay."""
    stamped = sorted(((e.valid_time_ns + d, i, e) for i, (e, d) in enumerate(zip(events, delays_ns))),
                     key=lambda x: (x[0], x[1]))
    store = open_ledger(path)
    batch = [Event(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.payload, r)
             for r, _i, e in stamped]
    result = store.append(batch)
    assert result.appended == len(batch), result
    return store


def _brute_force(rows: list[RecordedEvent], v: int, k: int):
    """Fold exactly the events with valid <= V and recorded <= K, ordered here."""
    chosen = sorted((r for r in rows if r.valid_time_ns <= v and r.recorded_time_ns <= k),
                    key=lambda r: (r.valid_time_ns, r.global_seq))
    state = F.initial_state(PILE)
    lots, assays = {}, []
    from projector.grades import AssayRecord

    for r in chosen:
        if r.type == "lot_declared":
            msg = decode_payload(r.type, r.payload)
            lots[msg.lot_id] = dict(msg.planned_grade)
        elif r.type == "assay":
            assays.append(AssayRecord.from_message(decode_payload(r.type, r.payload),
                                                   r.recorded_time_ns))
        elif r.type in F.GEOMETRY_TYPES:
            F.apply(state, r)
    F.flush(state)
    return summarise(state, lots, assays, valid_time_ns=v, known_time_ns=k)


def _plain(x):
    """``x`` with NaN as the string "NaN" (NaN != NaN), dicts and tuples as lists."""
    if isinstance(x, float):
        return "NaN" if math.isnan(x) else x
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x


def _figures(p) -> dict:
    """Every figure of a :class:`PileState`: its JSON (volume, tonnes, grade, assayed
    fraction, each deposit's and cut's figures, counters), the analytes and the grid."""
    figures = _plain(p.to_json())
    figures["analytes"] = list(p.analytes)
    figures["geometry"] = repr(p.geometry)
    return figures


def _same(a, b) -> None:
    """``a`` and ``b`` agree exactly: every figure, the top surface, every deposit's
    surfaces, the fused height map (elevation and variance) and the voxels' tonnes and
    grades."""
    fa, fb = _figures(a), _figures(b)
    assert fa.keys() == fb.keys()
    for key in fa:
        assert fa[key] == fb[key], key
    if a.geometry is not None:
        assert np.array_equal(a.surface_m, b.surface_m)
        assert np.array_equal(a.state.stack.surfaces(), b.state.stack.surfaces())
        assert np.array_equal(a.elevation_m, b.elevation_m, equal_nan=True)
        assert np.array_equal(a.state.height.variance, b.state.height.variance, equal_nan=True)
    if a.geometry is not None:
        (ta, ga, _), (tb, gb, _) = a.voxel_grades(), b.voxel_grades()
        assert np.array_equal(ta, tb) and np.array_equal(ga, gb, equal_nan=True)


def _snapshot_rows(snaps: SnapshotStore) -> list[tuple[int, int, int, int, int]]:
    """``(valid ns, global seq, head seq, known ns, folded recorded ns)`` of each snapshot."""
    return snaps._con.execute(
        f"SELECT valid_ns, global_seq, head_seq, known_ns, folded_recorded_ns "
        f"FROM {snaps.TABLE} ORDER BY valid_ns, global_seq").fetchall()


#: examples per backend: each one meets a stale snapshot (asserted), so the mutant
#: "a snapshot is always unchanged since it was taken" fails every one of them
PROPERTY_EXAMPLES = 6


@pytest.mark.parametrize("backend", ["memory", "duckdb"])
@settings(max_examples=PROPERTY_EXAMPLES, deadline=None, derandomize=True, database=None,
          phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_snapshot_accelerated_project_equals_a_brute_force_fold(yard, tmp_path_factory, backend,
                                                                 data):
    events = yard["events"]
    seed = data.draw(st.integers(0, 2 ** 32 - 1), label="seed")
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    # most events arrive at once; some scans, poses, the cut and the assays arrive late
    late = rng.random(len(events)) < 0.05
    delays = np.where(late, rng.integers(1, 900, len(events)) * S, 0)
    for i, e in enumerate(events):
        if e.type == "assay":
            delays[i] = (3 + i % 3) * 3600 * S
    # and one scan during the pass arrives minutes late: the partial snapshots are taken
    # before it arrives, at a K that knows scans up to minutes after it
    scans = [i for i, e in enumerate(events) if e.type == "scan"
             and yard["stack_started"] + 60 * S <= e.valid_time_ns <= yard["t_end"] - 240 * S]
    forced = scans[data.draw(st.integers(0, len(scans) - 1), label="late scan")]
    delay_s = data.draw(st.integers(200, 900), label="its delay (s)")
    delays[forced] = delay_s * S
    path = ":memory:" if backend == "memory" else tmp_path_factory.mktemp("ledger") / "l.duckdb"
    store = _ledger(events, [int(d) for d in delays], path)
    rows = list(store.read())
    e = events[forced]
    (scan,) = [r for r in rows if (r.source, r.epoch, r.seq) == (e.source, e.epoch, e.seq)]
    t0 = min(r.valid_time_ns for r in rows)
    t1 = max(r.valid_time_ns for r in rows)
    r1 = max(r.recorded_time_ns for r in rows)
    snaps = SnapshotStore(tmp_path_factory.mktemp("snap") / "s.duckdb")
    k_partial = scan.valid_time_ns + data.draw(st.integers(190, delay_s - 1),
                                               label="partial snapshots' K, s after the scan") * S
    assert build_snapshots(store, snaps, PILE, every_ns=90 * S, known_ns=k_partial) > 0
    assert build_snapshots(store, snaps, PILE, every_ns=120 * S) > 0
    # the partial snapshots past the late scan miss it; once it has arrived they are stale
    snapshots = _snapshot_rows(snaps)
    position = (scan.valid_time_ns, scan.global_seq)
    stale = [row for row in snapshots if row[3] == k_partial and row[:2] > position
             and sum(other[0] == row[0] for other in snapshots) == 1]
    assert stale, "no partial snapshot between the late scan and its arrival"
    row = stale[data.draw(st.integers(0, len(stale) - 1), label="stale snapshot")]
    later = [other[0] for other in snapshots if other[0] > row[0]]
    # V from the stale snapshot to before the next one; K once the scan has arrived
    v_stale = row[0] + int((min(later, default=t1 + 60 * S) - 1 - row[0])
                           * data.draw(st.floats(0.0, 1.0), label="V past the stale snapshot"))
    k_stale = scan.recorded_time_ns + int((r1 + 3600 * S - scan.recorded_time_ns)
                                          * data.draw(st.floats(0.0, 1.0), label="K, after"))
    queries = [(v_stale, k_stale)]
    print(f"late scan {scan.global_seq} ({delay_s} s), partial K {k_partial - scan.valid_time_ns}"
          f" ns after it, {len(stale)} stale, V {v_stale - row[0]} ns past one, K "
          f"{k_stale - scan.recorded_time_ns} ns after the scan's arrival")
    for _ in range(2):
        queries.append((int(t0 + (t1 - t0) * data.draw(st.floats(0.0, 1.05), label="V")),
                        int(t0 + (r1 - t0) * data.draw(st.floats(0.0, 1.05), label="K"))))
    for v, k in queries:
        fast = project(store, PILE, v, k, snapshots=snaps)
        _same(fast, _brute_force(rows, v, k))
    # the stale snapshot is never the one used past the scan's arrival
    found = snaps.find(store, F.FoldConfig(pile_id=PILE), v_stale, k_stale)
    assert found is None or found[1] != row[:2]
    snaps.close()
    store.close()


def test_a_snapshot_taken_knowing_everything_serves_an_earlier_known_time(yard, tmp_path,
                                                                          monkeypatch):
    # every event arrives a minute after its valid time: a snapshot holds only events
    # recorded by about its position, so it serves a K an hour before the head
    events = yard["events"]
    store = _ledger(events, [60 * S] * len(events))
    rows = list(store.read())
    head_k = max(r.recorded_time_ns for r in rows)
    t0 = min(r.valid_time_ns for r in rows)
    t1 = max(r.valid_time_ns for r in rows)
    with SnapshotStore(tmp_path / "s.duckdb") as snaps:
        built = build_snapshots(store, snaps, PILE, every_ns=60 * S)
        assert built > 0
        # counted per fold config: another config's queries never use these
        assert snaps.count() == snaps.count(F.FoldConfig(pile_id=PILE)) == built
        assert snaps.count(F.FoldConfig(pile_id=PILE, margin_sigma=2.5)) == 0
        # nor do the next version's: a changed fold folds the same events differently
        with monkeypatch.context() as m:
            m.setattr(F, "FOLD_VERSION", F.FOLD_VERSION + 1)
            assert snaps.count(F.FoldConfig(pile_id=PILE)) == 0
            assert snaps.find(store, F.FoldConfig(pile_id=PILE), t1, head_k) is None
        v = t0 + (t1 - t0) * 3 // 4
        k = v + 120 * S
        assert k < head_k
        found = snaps.find(store, F.FoldConfig(pile_id=PILE), v, k)
        assert found is not None, "a snapshot with all its events recorded by K is usable"
        _state, (v_s, _g) = found
        assert v_s <= v
        # not usable for a K before its own events were recorded
        earlier = snaps.find(store, F.FoldConfig(pile_id=PILE), v, v_s - 61 * S)
        assert earlier is None or earlier[1][0] < v_s
        _same(project(store, PILE, v, k, snapshots=snaps), _brute_force(rows, v, k))
        # the latest one's position, and dropping a config's snapshots deletes their files
        config = F.FoldConfig(pile_id=PILE)
        latest = snaps.latest_valid_ns(config)
        assert latest is not None and latest >= v_s
        assert snaps.find(store, config, FAR_FUTURE_NS, head_k)[1][0] == latest
        files = list(snaps.folder.glob("*.snap.zst"))
        assert len(files) == built
        assert snaps.drop(config) == built
        assert snaps.count() == 0 and snaps.latest_valid_ns(config) is None
        assert not any(f.exists() for f in files)
        assert snaps.find(store, config, t1, head_k) is None
        # a snapshot another version of the fold took is never read again: deleted
        with monkeypatch.context() as m:
            m.setattr(F, "FOLD_VERSION", F.FOLD_VERSION - 1)
            snaps.save(_state, rows[-1].global_seq, head_k)
            assert snaps.drop_other_versions() == (0, 0)    # its own version's are kept
        (older,) = snaps.folder.glob("*.snap.zst")
        size = older.stat().st_size
        assert snaps.count() == 1 and snaps.count(config) == 0
        assert snaps.drop_other_versions() == (1, size)
        assert snaps.count() == 0 and not older.exists()
    store.close()


def test_a_packed_state_unpacks_to_the_same_arrays_and_a_foreign_file_is_refused(yard,
                                                                                monkeypatch):
    # the frames of a packed state decompress on every core (a thread each): the state
    # that comes back is the one that went in, array for array
    from projector import query as Q
    from projector.query import _pack, _unpack

    store = _ledger(yard["events"], [0] * len(yard["events"]))
    state = F.initial_state(F.FoldConfig(pile_id=PILE))
    for event in store.as_of(FAR_FUTURE_NS, FAR_FUTURE_NS, types=list(F.GEOMETRY_TYPES)):
        F.apply(state, event)
    store.close()
    back = _unpack(_pack(state))
    assert back.stack.n_deposits == state.stack.n_deposits > 0
    for k in range(1, state.stack.n_deposits + 1):
        for a, b in zip(back.stack.deposit_cells(k), state.stack.deposit_cells(k)):
            np.testing.assert_array_equal(a, b)
    for name, layer in state.height.grid.layers.items():
        np.testing.assert_array_equal(back.height.grid.layers[name], layer)
        assert back.height.grid.layers[name].flags.writeable    # the fold updates them
    assert [c.cut_id for c in back.cuts] == [c.cut_id for c in state.cuts]
    # an open face's first sightings are updated in place by the fold after a snapshot
    # (projector.material_fit.note_sightings): they come back writeable too
    state.face_sightings = (np.full((3, 2), np.nan), np.arange(6.0).reshape(3, 2))
    back = _unpack(_pack(state))
    for a, b in zip(back.face_sightings, state.face_sightings):
        np.testing.assert_array_equal(a, b)
        assert a.flags.writeable
    # empty arrays' buffers, first, between and last, come back as they went (an empty
    # buffer has no frame), on one thread and on several
    from types import SimpleNamespace

    arrays = [np.zeros(0), np.arange(3.0), np.zeros((0, 2)), np.arange(4), np.zeros(0)]
    for threads in (1, 3):
        monkeypatch.setattr(Q, "SNAPSHOT_THREADS", threads)
        back = _unpack(_pack(SimpleNamespace(height=None, face_sightings=None, arrays=arrays)))
        assert [a.shape for a in back.arrays] == [a.shape for a in arrays]
        for a, b in zip(back.arrays, arrays):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="not a snapshot"):
        _unpack(b"\x28\xb5\x2f\xfd" + bytes(64))        # a bare zstd frame (the old layout)


def test_a_past_cut_changes_grade_exactly_when_its_assay_arrives(yard):
    events = yard["events"]
    delays = [0] * len(events)
    arrive = {}
    for i, e in enumerate(events):
        if e.type == "assay":
            arrive[decode_payload(e.type, e.payload).assay_id] = i
    delays[arrive["A1"]] = 4 * 3600 * S   # provisional, 4 h after its window
    delays[arrive["A2"]] = 7 * 3600 * S   # final, 7 h after
    store = _ledger(events, delays)
    rec = {decode_payload(r.type, r.payload).assay_id: r.recorded_time_ns
           for r in store.read(types=["assay"])}
    v = yard["cut_end"]

    def cut(k: int):
        state = project(store, PILE, v, k)
        [c] = [c for c in state.cuts if c.cut_id == "X-C01"]
        return c

    before = cut(rec["A1"] - 1)
    at_provisional = cut(rec["A1"])
    before_final = cut(rec["A2"] - 1)
    at_final = cut(rec["A2"])
    assert before.tonnes > 0, "the synthetic cut must take material"
    lot_part = [d for d in at_final.deposits if d["lot_id"] == yard["lot"]]
    assert lot_part and lot_part[0]["tonnes"] > 0
    assert before.assayed_fraction == 0.0
    assert at_provisional.assayed_fraction > 0.0
    assert before.grade["Fe"] != pytest.approx(at_provisional.grade["Fe"])
    assert at_provisional.grade == pytest.approx(before_final.grade)   # nothing new yet
    assert at_final.grade["Fe"] > at_provisional.grade["Fe"]            # 63.5 replaced 61.0
    # the cut's geometry does not depend on when assays arrived; its tonnes do, through
    # the assays' densities: the assayed part at the assay's, the rest at the pile's default
    assert at_final.volume_m3 == before.volume_m3 > 0
    default = yard["default_density"]
    assert before.tonnes == pytest.approx(before.volume_m3 * default, rel=1e-12)
    for c, density in ((at_provisional, DENSITY["A1"]), (at_final, DENSITY["A2"])):
        assayed_m3 = c.assayed_fraction * c.tonnes / density
        unassayed_m3 = (1.0 - c.assayed_fraction) * c.tonnes / default
        assert assayed_m3 + unassayed_m3 == pytest.approx(c.volume_m3, rel=1e-12)
        assert c.tonnes != pytest.approx(before.tonnes, rel=1e-3)


def test_grade_inputs_are_the_lots_and_assays_known_at_k_and_regrade_a_fold(yard):
    """``grade_inputs`` gives the lots and the assays recorded by K; ``summarise`` grades
    one folded state with other assays (how ``bench/projector_truth.py`` grades the cuts
    with an exact lab) without touching its geometry."""
    import dataclasses

    events = yard["events"]
    delays = [0] * len(events)
    for i, e in enumerate(events):
        if e.type == "assay":
            delays[i] = (4 if decode_payload(e.type, e.payload).assay_id == "A1" else 7) * 3600 * S
    store = _ledger(events, delays)
    rec = {decode_payload(r.type, r.payload).assay_id: r.recorded_time_ns
           for r in store.read(types=["assay"])}
    v = yard["cut_end"]
    for k, ids in ((rec["A1"] - 1, []), (rec["A1"], ["A1"]), (rec["A2"], ["A1", "A2"])):
        lots, assays = grade_inputs(store, v, k)
        assert yard["lot"] in lots and "Fe" in lots[yard["lot"]]
        assert sorted(a.assay_id for a in assays) == ids
        assert all(a.recorded_ns <= k for a in assays)
    state = project(store, PILE, v, FAR_FUTURE_NS)
    lots, assays = grade_inputs(store, v, FAR_FUTURE_NS)
    again = summarise(state.state, lots, assays, valid_time_ns=v, known_time_ns=FAR_FUTURE_NS)
    [cut] = [c for c in state.cuts if c.cut_id == "X-C01"]
    [same] = [c for c in again.cuts if c.cut_id == "X-C01"]
    assert same.grade == pytest.approx(cut.grade) and same.tonnes == cut.tonnes
    # the final assay (63.5 % Fe) read as 60.0 %: the lot's share of the cut moves by
    # 3.5 pp times that share, and its tonnes stay
    lower = [dataclasses.replace(a, analytes={**a.analytes, "Fe": 60.0}) if a.assay_id == "A2"
             else a for a in assays]
    regraded = summarise(state.state, lots, lower, valid_time_ns=v,
                         known_time_ns=FAR_FUTURE_NS)
    [low] = [c for c in regraded.cuts if c.cut_id == "X-C01"]
    share = sum(d["tonnes"] for d in cut.deposits if d["lot_id"] == yard["lot"]) / cut.tonnes
    assert share > 0
    assert low.tonnes == cut.tonnes
    assert low.grade["Fe"] == pytest.approx(cut.grade["Fe"] - 3.5 * share, abs=1e-6)


def test_stockpile_project_json_matches_the_python_api(yard, tmp_path):
    import json

    path = tmp_path / "ledger.duckdb"
    with open_ledger(path) as store:
        batch = [Event(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.payload,
                       e.valid_time_ns) for e in sorted(yard["events"], key=lambda e: e.valid_time_ns)]
        assert store.append(batch).appended == len(batch)
        expected = project(store, PILE)
    done = subprocess.run([sys.executable, "-m", "stockpile.cli", "project", "--ledger", str(path),
                           "--pile", PILE, "--json"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    for key in ("volume_m3", "tonnes", "grade", "assayed_fraction", "deposits", "cuts"):
        assert key in out
    assert out["tonnes"] == pytest.approx(expected.tonnes, rel=1e-12)
    [cut] = out["cuts"]
    for key in ("cut_id", "tonnes", "tonnes_scale", "grade", "assayed_fraction", "deposits"):
        assert key in cut
    assert cut["tonnes_scale"] == 100.0 and cut["tonnes"] > 0
    text = subprocess.run([sys.executable, "-m", "stockpile.cli", "project", "--ledger", str(path),
                           "--pile", "NOPE"], capture_output=True, text=True, timeout=300)
    assert text.returncode == 2 and "not declared" in text.stderr


def test_each_buried_top_is_fitted_once_at_the_first_cut_after_its_pass():
    from projector.grid import GridGeometry
    from projector.layers import DepositInfo, LayerStack

    seed = 11
    print(f"seed={seed}")
    rng = np.random.default_rng(seed)
    g = GridGeometry(0.0, 0.0, 0.5, 24, 20)
    x = np.arange(g.nx)[:, None] * 0.5 + np.zeros(g.ny)
    stack = LayerStack.empty(g, 0.0)

    def lay(stack, k):
        stack = stack.open_deposit(DepositInfo(k, f"P{k}", "L", k * S))
        crest = 1.0 * k - 0.15 * np.abs(x - 6.0)          # a ridge across x
        top = np.maximum(stack.surface(), crest + rng.normal(0.0, 0.05, g.shape))
        return stack.raise_to(top, k * S + 1)[0]

    for k in (1, 2, 3):
        stack = lay(stack, k)
    state = F.initial_state(PILE)
    state.stack = stack
    cuts.fit_buried_boundaries(state)
    assert state.boundaries_fitted == 2 and state.counters["boundaries_fitted"] == 2
    once = stack.fit_boundaries([1, 2], 7)
    np.testing.assert_array_equal(state.stack.surfaces(), once.surfaces())
    assert not np.array_equal(once.surfaces(), stack.surfaces())
    cuts.fit_buried_boundaries(state)                     # nothing new is buried: no change
    np.testing.assert_array_equal(state.stack.surfaces(), once.surfaces())
    assert state.counters["boundaries_fitted"] == 2
    state.stack = lay(state.stack, 4)                  # a new pass buries deposit 3's top
    before = state.stack
    cuts.fit_buried_boundaries(state)
    assert state.boundaries_fitted == 3 and state.counters["boundaries_fitted"] == 3
    np.testing.assert_array_equal(state.stack.surfaces(),
                                  before.fit_boundaries([3], 7).surfaces())
    # off: the tops stay as fused
    off = F.initial_state(F.FoldConfig(pile_id=PILE, boundary_fit_cells=1))
    off.stack = stack
    cuts.fit_buried_boundaries(off)
    assert off.stack is stack and off.boundaries_fitted == 0
    with pytest.raises(ValueError, match="boundary_fit_cells"):
        F.FoldConfig(pile_id=PILE, boundary_fit_cells=4)
    with pytest.raises(ValueError, match="cut_fit_cells"):
        F.FoldConfig(pile_id=PILE, cut_fit_cells=6)


def test_voxels_before_anything_is_stacked_are_empty(yard):
    """As of the moment the pile is declared there is no deposit: the voxel grid is all
    zero tonnes with NaN grades, of the pile's voxel geometry."""
    store = _ledger(yard["events"], [0] * len(yard["events"]))
    declared = min(e.valid_time_ns for e in yard["events"] if e.type == "pile_declared")
    assert declared < yard["stack_started"]
    state = project(store, PILE, declared, None)
    assert state.state.stack.n_deposits == 0
    tonnes, grade, grid = state.voxel_grades()
    assert tonnes.shape == grid.volume_m3.shape and not tonnes.any()
    assert grade.shape == tonnes.shape + (len(state.analytes),) and np.isnan(grade).all()
    later = project(store, PILE, yard["t_end"], None)
    t_later, _g, _grid = later.voxel_grades()
    assert t_later.sum() == pytest.approx(later.tonnes, rel=1e-9)

"""MCAP sessions end to end on the live process demo: record, export, replay, bad input.

One short run of the process demo (``stockpile.yard_demo``: simulator, scanner, GNSS,
localizer and ledger as separate processes on a loopback Zenoh router) runs with the
recorder service beside the ledger.  Its recording is compared with the ledger
written live; then the demo ledger, with two late assays added (a provisional one
recorded an hour after the run, the final one superseding it two hours later, so
as-of-known reads differ with K), goes through ``export-mcap`` and ``replay --ledger``.
The commands run through ``stockpile.cli.main`` (the real command line, in this
process: an exception would fail the test rather than hide in a child's stderr); the
files are read back with the ``mcap`` library itself.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import Writer
from mcap_protobuf.decoder import DecoderFactory

from ledger import open_ledger
from ledger.cli import export_lines
from ledger.signing import KEY_TYPES
from replay.record_parts import FileNamer
from replay.mcap_scan import McapScan
from replay.mcap_format import SIGNATURE_SUFFIX
from replay.mcap_writer import schema_of
from replay.replay import iter_events
from schemas import pb
from schemas.events import EVENT_TYPES, Event, decode_payload, make_event, set_timestamp_ns
from services.service import DEFAULT_SMOOTH_LAG_S, LIVE_REORDER_S
from cli_in_process import run
from stockpile.cli import main as stockpile
from stockpile.yard_demo import SITE_OF_SCENARIO as SITE

from schemas.times import NS_PER_S as S  # noqa: E402
H = 3600 * S


def _assay(assay_id: str, lot: str, window: tuple[int, int], fe: float, status: int,
           seq: int, recorded_ns: int, supersedes: str = "") -> Event:
    a = pb.Assay(assay_id=assay_id, lot_id=lot, status=status, supersedes=supersedes,
                 lab_id="lab9", bulk_density_t_m3=2.4)
    a.analytes.update({"Fe": fe, "SiO2": 4.0})
    set_timestamp_ns(a.window_start, window[0])
    set_timestamp_ns(a.window_end, window[1])
    set_timestamp_ns(a.reported_time, recorded_ns)
    return dataclasses.replace(make_event(a, source="lab9", epoch=1, seq=seq),
                               recorded_time_ns=recorded_ns)


@pytest.fixture(scope="module")
def demo(process_demo) -> Path:
    """The shared short process demo (recorder on): ``ledger.duckdb`` and ``live.mcap``."""
    out, run = process_demo
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def yard(demo, tmp_path_factory) -> dict:
    """The demo ledger's events without their signatures (this module tests the MCAP
    format's robustness, one message per event; signatures through MCAP are
    test_replay_signatures.py's), two late assays added, and its export as JSON lines."""
    root = tmp_path_factory.mktemp("replay")
    ledger = root / "original.duckdb"
    with open_ledger(demo / "ledger.duckdb", read_only=True) as source:
        unsigned = [dataclasses.replace(r.to_event(), signer=None, signature=None)
                    for r in source.read() if r.type not in KEY_TYPES]
    with open_ledger(ledger) as store:
        assert store.append(unsigned).appended == len(unsigned)
        rows = list(store.read())
        t_end = max(r.valid_time_ns for r in rows)
        last_recorded = max(r.recorded_time_ns for r in rows)
        start = next(r for r in rows if r.type == "stack_started")
        lot = decode_payload("stack_started", start.payload).lot_id
        window = (start.valid_time_ns - 60 * S, t_end)
        late = [_assay("A1", lot, window, 61.0, pb.PROVISIONAL, 0, last_recorded + 1 * H),
                _assay("A2", lot, window, 63.5, pb.FINAL, 1, last_recorded + 3 * H, "A1")]
        assert store.append(late).appended == 2
        text = io.StringIO()
        export_lines(store, text)
        total = store.head().global_seq + 1
    return {"root": root, "ledger": ledger, "lines": text.getvalue(), "t_end": t_end,
            "known_end": last_recorded, "t_start": min(r.valid_time_ns for r in rows),
            "total": total,
            "per_type": {t: sum(1 for r in rows if r.type == t) for t in EVENT_TYPES}}


def test_the_live_recording_holds_exactly_the_events_of_the_live_ledger(demo):
    # all but the site admin's key declarations, which the demo writes into the ledger
    # before the services start (they never go over Zenoh)
    with open_ledger(demo / "ledger.duckdb", read_only=True) as store:
        ledgered = [(r.type, r.source, r.epoch, r.seq, r.valid_time_ns, r.payload)
                    for r in store.read() if r.source != "site-admin"]
        assert len(ledgered) == store.head().global_seq + 1 - 6
    recorded = list(iter_events(demo / "live.mcap"))
    identities = [(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.payload) for e in recorded]
    assert len(identities) == len(set(identities)) == len(ledgered) > 10_000
    assert set(identities) == set(ledgered)  # same identities, byte-identical payloads
    # log_time is the receive time in site-clock time (the site runs ~50x faster than the
    # wall clock, and weeks away from it): never backwards, and near the valid time, within
    # a real second or so of latency on a loaded machine; the localizer's estimates a
    # smoothing lag later (held until the filter is that far past them)
    logs = [e.log_time_ns for e in recorded]
    assert all(a <= b for a, b in zip(logs, logs[1:]))

    def median_lag_s(events) -> float:
        lags_s = sorted(abs(e.log_time_ns - e.valid_time_ns) / S for e in events)
        return lags_s[len(lags_s) // 2]
    localized = [e for e in recorded if e.source.endswith(".localizer")]
    assert len(localized) > 1_000
    assert median_lag_s([e for e in recorded if not e.source.endswith(".localizer")]) < 60.0
    assert DEFAULT_SMOOTH_LAG_S <= median_lag_s(localized) < LIVE_REORDER_S + 60.0
    with open(demo / "live.mcap", "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        topics = [c.topic for c in reader.get_summary().channels.values()
                  if not c.topic.endswith(SIGNATURE_SUFFIX)]
        assert sum(1 for _ in reader.iter_decoded_messages(topics=topics)) == len(ledgered)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert json.loads(meta["stockpile.recording"]["open_gaps"]) == []
    assert meta["stockpile.recording"]["clock"] == "site"


@pytest.fixture(scope="module")
def exported(yard, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("export") / "session.mcap"
    code = stockpile(["export-mcap", "--ledger", str(yard["ledger"]), "--out", str(out), "--site", SITE,
                      "--no-progress"])
    assert code == 0
    return out


@pytest.fixture(scope="module")
def replayed(exported, tmp_path_factory) -> dict:
    """``replay --ledger`` of the export into an empty ledger: its path and output."""
    copy = tmp_path_factory.mktemp("replayed") / "copy.duckdb"
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = stockpile(["replay", str(exported), "--ledger", str(copy), "--no-progress"])
    return {"path": copy, "code": code, "out": out.getvalue(), "err": err.getvalue()}


def test_round_trip_export_replay_export_is_line_for_line_identical(yard, exported, replayed,
                                                                     capsys):
    copy = replayed["path"]
    assert replayed["code"] == 0, replayed["err"]
    assert f"{yard['total']:,} appended, 0 duplicate, 0 conflict, 0 rejected" in replayed["out"]
    code, out, err = run(capsys, "ledger", "export", "--ledger", str(copy))
    assert code == 0, err
    assert out == yard["lines"]  # identities, payloads, valid and recorded times, order
    with open_ledger(copy, read_only=True) as a, open_ledger(yard["ledger"], read_only=True) as b:
        assert a.verify().ok
        assert a.head().chain_sha256 == b.head().chain_sha256  # the same hash chain
    # replaying the same file again adds nothing
    code, out, err = run(capsys, "replay", str(exported), "--ledger", str(copy), "--no-progress")
    assert code == 0, err
    assert f"0 appended, {yard['total']:,} duplicate" in out


def test_project_answers_identically_on_the_replayed_ledger(yard, replayed, capsys):
    copy = replayed["path"]
    t0, t_end, known = yard["t_start"], yard["t_end"], yard["known_end"]
    cases = [(t_end, known), (t_end, known + 2 * H), ((t0 + t_end) // 2, known + 4 * H)]
    answers = []
    for v, k in cases:
        when = [] if v is None else ["--valid-time", str(v), "--known-time", str(k)]
        outputs = []
        for path in (yard["ledger"], copy):
            code, out, err = run(capsys, "project", "--ledger", str(path), "--pile", "P1",
                                 "--json", *when)
            assert code == 0, err
            outputs.append(out)
        assert outputs[0] == outputs[1], (v, k)
        answers.append(json.loads(outputs[0]))
    # the cases differ where they should: the late assays are known only from K = +1 h,
    # and half-way through the run less had been stacked
    assert answers[0]["deposits"] and answers[0]["assayed_fraction"] == 0.0
    assert answers[1]["assayed_fraction"] > 0.0
    assert answers[1]["grade"]["Fe"] != answers[0]["grade"]["Fe"]
    assert answers[2]["volume_m3"] < answers[1]["volume_m3"]


def test_the_file_follows_the_conventions_and_opens_with_the_mcap_reader(yard, exported):
    with open(exported, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary.statistics.message_count == yard["total"]
        names = {s.name for s in summary.schemas.values()}
        assert {"foxglove.LaserScan", "foxglove.FrameTransform", "stockpile.v1.Assay",
                "stockpile.v1.Clock"} <= names
        assert all(s.encoding == "protobuf" for s in summary.schemas.values())
        decoded = 0
        for schema, channel, message, proto in reader.iter_decoded_messages(log_time_order=False):
            assert proto.DESCRIPTOR.full_name == schema.name
            meta = channel.metadata
            assert channel.topic == f"stockpile/{SITE}/@v1/{meta['type']}/{meta['source']}"
            assert EVENT_TYPES[meta["type"]].DESCRIPTOR.full_name == schema.name
            decoded += 1
        assert decoded == yard["total"]
    # the streaming reader also checks the data section's CRC
    with open(exported, "rb") as f:
        assert sum(1 for _ in NonSeekingReader(f, validate_crcs=True).iter_messages(
            log_time_order=False)) == yard["total"]
    # sequence = source seq, publish_time = valid time, log_time = recorded time
    lines = [json.loads(line) for line in yard["lines"].splitlines()]
    events = list(iter_events(exported))
    assert [(e.type, e.source, e.epoch, e.seq, e.valid_time_ns, e.log_time_ns) for e in events] == \
        [(d["type"], d["source"], d["epoch"], d["seq"], d["valid_time_ns"], d["recorded_time_ns"])
         for d in lines]
    with open(exported, "rb") as f:
        metadata = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert metadata["stockpile.export"]["events"] == str(yard["total"])


def test_topics_and_offsets_select_what_is_replayed(yard, exported, tmp_path, capsys):
    code, out, err = run(capsys, "replay", str(exported), "--ledger", str(tmp_path / "a.duckdb"),
                         "--topics", "stockpile/*/@v1/assay/**", "--no-progress")
    assert code == 0, err
    assert "2 events -> 2 appended" in out
    # the first minute of the session (log time), everything else left out
    code, out, err = run(capsys, "replay", str(exported), "--ledger", str(tmp_path / "b.duckdb"),
                         "--until", "60", "--no-progress")
    assert code == 0, err
    with open_ledger(tmp_path / "b.duckdb", read_only=True) as store:
        recorded = [r.recorded_time_ns for r in store.read()]
    assert 0 < len(recorded) < yard["total"]
    # a clock event is logged at the site time the recorder knew when it arrived, up to
    # one clock period (1 s) before its own value, which becomes the recorded time
    assert max(recorded) <= yard["t_start"] + 61 * S


# -- bad input ---------------------------------------------------------------------------


def _chunk_offsets(path: Path) -> list[tuple[int, int, int]]:
    """(chunk start, chunk length, messages in it) of every chunk, from the summary."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    out = []
    with open(path, "rb") as f:
        reader = make_reader(f)
        for index in reader.get_summary().chunk_indexes:
            f.seek(index.chunk_start_offset + 9)
            from mcap.data_stream import ReadDataStream

            chunk = Chunk.read(ReadDataStream(f))
            n = sum(1 for r in breakup_chunk(chunk) if isinstance(r, Message))
            out.append((index.chunk_start_offset, index.chunk_length, n))
    return out


def test_a_chunk_with_a_bad_crc_loses_exactly_its_messages(yard, exported, tmp_path, capsys):
    chunks = _chunk_offsets(exported)
    assert len(chunks) >= 3
    start, length, lost = chunks[1]
    broken = tmp_path / "bad-crc.mcap"
    data = bytearray(exported.read_bytes())
    data[start + length // 2] ^= 0xFF  # inside the compressed records
    broken.write_bytes(bytes(data))
    code, out, err = run(capsys, "replay", str(broken), "--ledger", str(tmp_path / "l.duckdb"),
                         "--no-progress")
    assert code == 1
    assert f"{lost:,} messages lost" in err and "chunk at byte" in err
    assert f"{yard['total'] - lost:,} appended" in out
    assert "Traceback" not in err
    fixed = tmp_path / "fixed.mcap"
    code, out, err = run(capsys, "record", "--recover", str(broken), str(fixed))
    assert code == 1 and f"lost: {lost:,} messages" in out
    with open(fixed, "rb") as f:  # a complete, valid file holding the rest
        reader = make_reader(f, validate_crcs=True)
        assert sum(1 for _ in reader.iter_messages()) == yard["total"] - lost


def test_a_truncated_file_is_read_up_to_the_cut_and_recovered(yard, exported, tmp_path, capsys):
    data = exported.read_bytes()
    chunks = _chunk_offsets(exported)
    cut = chunks[2][0] + chunks[2][1] // 2  # in the middle of the third chunk
    broken = tmp_path / "truncated.mcap"
    broken.write_bytes(data[:cut])
    copy = tmp_path / "l.duckdb"
    code, out, err = run(capsys, "replay", str(broken), "--ledger", str(copy), "--no-progress")
    assert code == 1 and "Traceback" not in err
    assert "cut short" in err and "unknown number" in err
    whole = chunks[0][2] + chunks[1][2]
    with open_ledger(copy, read_only=True) as store:
        text = io.StringIO()
        n = export_lines(store, text)
    # what was read is exactly the beginning of the ledger, in order, with its times
    assert whole <= n < yard["total"]
    assert text.getvalue() == "".join(yard["lines"].splitlines(keepends=True)[:n])
    fixed = tmp_path / "fixed.mcap"
    code, out, err = run(capsys, "record", "--recover", str(broken), str(fixed))
    assert code == 1 and f"recovered {n:,} messages" in out
    with open(fixed, "rb") as f:
        assert sum(1 for _ in make_reader(f, validate_crcs=True).iter_messages()) == n
    # a file cut inside its header is not a recording at all: one clear line
    stub = tmp_path / "stub.mcap"
    stub.write_bytes(data[:5])
    code, _out, err = run(capsys, "replay", str(stub), "--ledger", str(copy), "--no-progress")
    assert code == 2 and err.strip().splitlines() == [
        f"stockpile: error: {stub} is not an MCAP file (no MCAP magic at its start)"]


def test_unknown_schemas_are_counted_and_skipped_never_guessed(yard, exported, tmp_path, capsys):
    mixed = tmp_path / "mixed.mcap"
    good = [e for e in iter_events(exported)][:50]
    with open(mixed, "wb") as f:
        writer = Writer(f)
        writer.start()
        odom = writer.register_schema("acme.Odometry", "protobuf", b"")
        odom_channel = writer.register_channel("/robot/odom", "protobuf", odom)
        scan_name, scan_data = schema_of("scan")
        wrong = writer.register_schema(scan_name, "protobuf", scan_data)
        # an assay topic whose schema is a LaserScan: not trusted as an assay
        liar = writer.register_channel(f"stockpile/{SITE}/@v1/assay/lab9", "protobuf", wrong,
                                       {"type": "assay", "source": "lab9", "epoch": "1"})
        ids = {}
        for i, e in enumerate(good):
            if e.type not in ids:
                name, data = schema_of(e.type)
                ids[e.type] = writer.register_channel(
                    e.topic, "protobuf", writer.register_schema(name, "protobuf", data),
                    {"type": e.type, "source": e.source, "epoch": str(e.epoch)})
            writer.add_message(ids[e.type], e.log_time_ns, e.payload, e.valid_time_ns, e.seq)
            writer.add_message(odom_channel, e.log_time_ns, b"\x08\x01", e.log_time_ns, i)
        writer.add_message(liar, good[-1].log_time_ns, b"\x01", good[-1].valid_time_ns, 0)
        writer.finish()
    code, out, err = run(capsys, "replay", str(mixed), "--ledger", str(tmp_path / "l.duckdb"),
                         "--no-progress")
    assert code == 1 and "Traceback" not in err
    assert "50 events -> 50 appended" in out
    assert "51 messages of" in err and "'/robot/odom'" in err and "acme.Odometry" in err
    assert "is not stockpile.v1.Assay" in err
    # a file with nothing but unknown channels is an error: nothing could be used
    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        writer = Writer(f)
        writer.start()
        channel = writer.register_channel("/robot/odom", "json", 0)
        writer.add_message(channel, 1, b"{}", 1, 0)
        writer.finish()
    code, _out, err = run(capsys, "replay", str(foreign), "--ledger", str(tmp_path / "m.duckdb"),
                          "--no-progress")
    assert code == 2 and err.strip().splitlines()[-1] == \
        f"stockpile: error: no stockpile events could be read from {foreign}"


def test_bad_usage_and_missing_files_are_one_line_errors(exported, tmp_path, capsys):
    cases = [
        ("replay", str(tmp_path / "nope.mcap"), "--ledger", str(tmp_path / "l.duckdb")),
        ("replay", str(exported)),  # neither --publish nor --ledger
        ("replay", str(exported), "--ledger", str(tmp_path / "l.duckdb"), "--max"),
        ("replay", str(exported), "--publish", "--rate", "0"),
        ("export-mcap", "--ledger", str(tmp_path / "nope.duckdb"), "--out", str(tmp_path / "x.mcap")),
        ("record", "--recover", str(tmp_path / "nope.mcap"), str(tmp_path / "fixed.mcap")),
        ("record",),
    ]
    for args in cases:
        code, out, err = run(capsys, *args)
        assert code == 2, (args, out, err)
        assert len(err.strip().splitlines()) == 1 and err.startswith("stockpile"), (args, err)
    assert not (tmp_path / "x.mcap").exists()
    # a recorder never overwrites a recording: given one that exists (a restart under
    # `stockpile run`), it continues in the first free numbered part
    namer = FileNamer(str(exported), split=False)
    part = namer.check()
    assert part == exported.with_name(f"{exported.stem}-0000{exported.suffix}")
    assert namer.next() == part and not part.exists()
    assert McapScan(exported).report.path == str(exported)  # still there, untouched


def test_rerun_ingests_the_recording_and_shows_the_foxglove_transforms(demo, yard, tmp_path):
    rerun = Path(sys.executable).with_name("rerun")
    if not rerun.exists():
        rerun = Path(shutil.which("rerun") or "rerun")
    rrd = tmp_path / "session.rrd"
    conv = subprocess.run([str(rerun), "mcap", "convert", str(demo / "live.mcap"), "-o", str(rrd)],
                          capture_output=True, text=True, timeout=120)
    assert conv.returncode == 0 and "ERROR" not in conv.stderr, conv.stderr[-2000:]
    shown = subprocess.run([str(rerun), "rrd", "print", "-v", str(rrd)], capture_output=True,
                           text=True, timeout=120)
    assert shown.returncode == 0, shown.stderr[-2000:]
    # every frame_transform message (the localizer's wheel and scanner poses) became a row
    # of Rerun's Transform3D on its topic
    rows = 0
    for line in shown.stdout.splitlines():
        if "/frame_transform/" in line and "Transform3D:translation" in line:
            rows += int(line.split(" with ")[1].split(" rows")[0].replace(" ", ""))
    assert rows == yard["per_type"]["frame_transform"] > 0

"""Fuzz tests of ``stockpile ledger import`` and of :func:`schemas.jsonl.decode_line`
(Hypothesis, seeded from the run's seed by conftest.py, which prints it; about 30 s in all).

Generated files mix good canonical lines (``event_line`` of events built as the bad-input
tests build them) with hostile ones: random bytes, good lines cut short or with bytes
spliced in, Latin-1 bytes, lone surrogate escapes, integers of thousands of digits or
beyond 64 bits, deep nesting, unknown types, repeated lines and changed payloads under a
stored key.  The invariant, read back from the ledger: every non-blank line is appended, a
duplicate, quarantined or in the reject file; the counts add up to the lines; no
exception escapes (the CLI exits 0, or 2 only when it names a reject file).
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import tempfile
from collections import Counter
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bad_input_helpers import V0, assay, clock_tick, joint_reading, lot
from ledger import open_ledger
from ledger.importing import TO_REJECT_FILE, import_lines
from ledger.records import STATUSES
from schemas.events import Event, Malformed, make_event
from schemas.jsonl import decode_line, event_line
from schemas.validate import REASON_CODES
from stockpile.cli import main as stockpile

#: good canonical lines: two joint streams, the site clock, a lot and its assays
GOOD = (
    [event_line(make_event(joint_reading(V0 + i), source="bwr1.joints", epoch=0, seq=i))
     for i in range(6)]
    + [event_line(make_event(clock_tick(V0 + i), source="site.clock", epoch=3, seq=i))
       for i in range(3)]
    + [event_line(make_event(lot(V0), source="lims", epoch=0, seq=0)),
       event_line(make_event(assay(V0 + 5), source="lims", epoch=0, seq=1)),
       event_line(make_event(assay(V0 + 6, assay_id="A2"), source="lims", epoch=0, seq=2))]
)
#: the same keys as some good lines with another payload (conflicts once the first is stored)
CHANGED = [event_line(make_event(joint_reading(V0 + i, travel=99.0), source="bwr1.joints",
                                 epoch=0, seq=i)) for i in range(3)]

_SPLICES = [b"\xe9", b"\xff\xfe", b"\\ud800", b"\\udfff", b"\x00", b"9" * 5_000,
            str(-2**63 - 1).encode(), str(2**64).encode(), b"[" * 50_000, b"{", b"\"", b"\\",
            b"1e999", b"NaN", b"-", b"\r", b" "]


@st.composite
def spoiled(draw) -> bytes:
    """A good line with bytes spliced in, a value swapped or its tail cut."""
    line = draw(st.sampled_from(GOOD)).encode()
    how = draw(st.sampled_from(["splice", "cut", "swap"]))
    if how == "cut":
        return line[:draw(st.integers(0, len(line)))]
    at = draw(st.integers(0, len(line)))
    piece = draw(st.one_of(st.sampled_from(_SPLICES), st.binary(max_size=8)))
    if how == "splice":
        return line[:at] + piece + line[at:]
    # swap: replace the next value after ``at`` (up to a comma or brace) with ``piece``
    end = min([i for i in (line.find(b",", at), line.find(b"}", at)) if i >= 0] or [len(line)])
    return line[:at] + piece + line[end:]


def _hostile_whole_lines() -> list[bytes]:
    good = GOOD[0]
    return [
        good.replace('"machine_id":"bwr1"', '"machine_id":"LOT-\\u00e9"').encode()
        .replace(b"\\u00e9", b"\xe9"),
        good.replace('"machine_id"', '"\\ud800"').encode(),
        good.replace('"type":"joint_reading"', '"type":"\\udc00"').encode(),
        good.replace('"source":"bwr1.joints"', '"source":"\\ud800x"').encode(),
        good.replace('"epoch":0', '"epoch":' + "1" * 5_000).encode(),
        good.replace('"seq":0', f'"seq":{-2**63 - 7}').encode(),
        good.replace('"type":"joint_reading"', '"type":"no_such_type"').encode(),
        b'{"body":' + b"[" * 100_000 + b"]" * 100_000 + b"}",
        b"[1, 2, 3]", b"null", b"{}", b"\xef\xbb\xbf" + good.encode(),
    ]


HOSTILE = _hostile_whole_lines()

lines_strategy = st.lists(
    st.one_of(
        st.sampled_from(GOOD).map(str.encode),
        st.sampled_from(CHANGED).map(str.encode),
        st.sampled_from(HOSTILE),
        spoiled(),
        st.binary(max_size=64),
        st.sampled_from([b"", b"   ", b"\t\r"]),
    ),
    min_size=1, max_size=25)


def non_blank(content: bytes) -> list[bytes]:
    """The lines an import counts: split at newlines as a binary file reads them, stripped."""
    return [line.strip() for line in content.split(b"\n") if line.strip()]


def check_invariant(lines: list[bytes], counts: dict[str, int], rows, quarantine,
                    rejected: list[bytes]) -> None:
    """Every line is a stored row (appended or a duplicate), a quarantine entry or a
    reject-file record, and the counts add up to the lines."""
    assert counts["lines"] == len(lines)
    assert sum(counts[s] for s in STATUSES) + counts[TO_REJECT_FILE] == len(lines)
    assert len(rows) == counts["appended"]
    assert len(quarantine) == counts["rejected"] + counts["conflict"]
    assert len(rejected) == counts[TO_REJECT_FILE]
    stored = {(r.source, r.epoch, r.seq): bytes(r.payload) for r in rows}
    raws = Counter(q.raw for q in quarantine) + Counter(rejected)
    for line in lines:
        item = decode_line(line)
        if isinstance(item, Event) and stored.get((item.source, item.epoch, item.seq)) \
                == item.payload:
            continue  # appended, or a duplicate of a stored event
        raw = item.raw if isinstance(item, Malformed) else item.payload
        if raws[raw] == 0 and raws[line]:
            raw = line  # refused as a whole line (unstorable / reject file)
        assert raws[raw] > 0, f"line {line[:120]!r} is neither stored nor quarantined"
        raws[raw] -= 1


@settings(max_examples=1_000, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.one_of(st.binary(max_size=300), spoiled(), st.sampled_from(HOSTILE),
                 st.text(max_size=100).map(lambda t: t.encode("utf-8", "surrogatepass"))))
def test_decode_line_never_raises(raw):
    item = decode_line(raw, where="fuzz.jsonl:1")
    assert isinstance(item, (Event, Malformed))
    if isinstance(item, Malformed):
        assert item.raw == raw
        code = item.reason.partition(": ")[0]
        assert code in REASON_CODES, item.reason
        for text in (item.type, item.source, item.reason):
            text.encode("utf-8")  # storable: no lone surrogate


@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
@given(lines_strategy, st.integers(1, 8))
def test_import_lines_memory_store_loses_nothing(generated, batch_size):
    content = b"\n".join(generated)
    with open_ledger(":memory:") as store:
        counts = import_lines(store, io.BytesIO(content), name="fuzz.jsonl",
                              batch_size=batch_size, rejects=None)
        rows, quarantine = list(store.read()), store.quarantine()
        assert store.verify().ok
    check_invariant(non_blank(content), counts, rows, quarantine, [])


@settings(max_examples=20, deadline=None, suppress_health_check=list(HealthCheck))
@given(lines_strategy, st.sampled_from(["1", "3", "1000"]))
def test_cli_import_duckdb_loses_nothing(generated, batch_size):
    content = b"\n".join(generated)
    with tempfile.TemporaryDirectory(prefix="import-fuzz-") as tmp:
        path, ledger = Path(tmp) / "fuzz.jsonl", Path(tmp) / "ledger.duckdb"
        rejects = Path(tmp) / "rejects.jsonl"
        path.write_bytes(content)
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = stockpile(["ledger", "import", str(path), "--ledger", str(ledger), "--json",
                              "--batch-size", batch_size, "--rejects", str(rejects)])
        assert "Traceback" not in err.getvalue()
        assert code == (2 if rejects.exists() else 0), err.getvalue()
        counts = json.loads(out.getvalue())
        rejected = ([base64.b64decode(json.loads(line)["raw_base64"])
                     for line in rejects.read_text().splitlines()]
                    if rejects.exists() else [])
        with open_ledger(ledger, read_only=True) as store:
            rows, quarantine = list(store.read()), store.quarantine()
            assert store.verify().ok
    check_invariant(non_blank(content), counts, rows, quarantine, rejected)

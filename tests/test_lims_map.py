"""The LIMS map and export rows (services/lims_map.py) and the simulator's LIMS files
(sim/lims.py): pure, no processes.

The simulator's round trip draws lab results from the run's seed (``--seed N`` or
``STOCKPILE_TEST_SEED=N`` reproduces it; the seed is printed).
"""

from __future__ import annotations

import json
from decimal import Decimal
from pathlib import Path
from zoneinfo import ZoneInfo

import numpy as np
import pytest

from schemas import pb
from schemas.events import timestamp_ns
from schemas.times import parse_time_ns as utc
from services import lims_map as L
from sim import lims as S
from sim import messages
from sim.grades import BeltGrade, LabModel, table_5_4_lots

from seeding import session_seed

SEED = session_seed()
EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "lims.example.toml"
PERTH = ZoneInfo("Australia/Perth")

#: a small map for hand-written rows: comma CSV, UTC ISO times, a ppm and a g/t analyte
SMALL_MAP = """
[file]
format = "csv"
[time]
format = "iso8601"
[columns]
sample_id = "id"
lot = "lot"
window_start = "from"
window_end = "to"
status = "st"
reported_time = "at"
revision = "rev"
bulk_density = { column = "bd", unit = "kg/m3" }
[lab]
id = "labX"
[status]
Prov = "PROVISIONAL"
Fin = "final"
[analytes]
FE = { column = "fe" }
p = { column = "p", unit = "ppm" }
S = { column = "s", unit = "g/t" }
"""
HEADER = "id,lot,from,to,st,at,rev,bd,fe,p,s"
GOOD = "S1,L1,2026-11-20T01:00:00Z,2026-11-20T01:20:00Z,Prov,2026-11-20T05:00:00Z,,2400,60.5,830,120"


def small_map() -> L.LimsMap:
    return L.parse_map(SMALL_MAP)


# -- the map ------------------------------------------------------------------------------


def test_the_documented_example_is_the_map_of_the_simulators_files():
    example = L.parse_map(EXAMPLE.read_text())
    assert example == L.parse_map(S.MAP_TOML)
    assert example.format == "csv" and example.delimiter == ";" and example.decimal == ","
    assert example.header_row == 2 and example.timezone == "Australia/Perth"
    assert [(a.name, a.unit) for a in example.analytes] == [
        ("Fe", "%"), ("SiO2", "%"), ("Al2O3", "%"), ("P", "ppm"), ("LOI", "%")]
    assert example.status_codes == {"p": "PROVISIONAL", "f": "FINAL", "a": "FINAL"}
    assert example.density_unit == "kg/m3"


def test_analyte_names_and_status_values_are_canonical():
    lims = small_map()
    assert [a.name for a in lims.analytes] == ["Fe", "P", "S"]
    assert lims.status_codes == {"prov": "PROVISIONAL", "fin": "FINAL"}
    assert lims.lab_id == "labX" and lims.column("supersedes") is None


@pytest.mark.parametrize(("change", "names"), [
    (("sample_id = \"id\"\n", ""), "columns.sample_id is missing"),
    (("[lab]\nid = \"labX\"\n", ""), "lab.id is missing"),
    (("unit = \"ppm\"", "unit = \"ppb\""), "analytes.p.unit 'ppb'"),
    (("unit = \"kg/m3\"", "unit = \"lb/ft3\""), "columns.bulk_density.unit"),
    (("format = \"csv\"", "format = \"xlsx\""), "file.format 'xlsx'"),
    (("format = \"iso8601\"", "format = \"iso8601\"\ntimezone = \"Mars/Olympus\""),
     "time.timezone 'Mars/Olympus'"),
    (("format = \"iso8601\"", "format = \"dd.mm.yyyy\""), "time.format must be"),
    (("Fin = \"final\"", "Fin = \"done\""), "status.Fin must be one of"),
    (("rev\"\n", "rev\"\nrevison = \"x\"\n"), "columns.revison is not a key"),
    (("S = {", "Fe = {"), "analytes.Fe names Fe a second time"),
    (("column = \"p\"", "column = \"fe\""), "column 'fe' is mapped twice"),
    (("format = \"csv\"", "format = \"csv\"\ndelimiter = \";;\""), "file.delimiter"),
    (("format = \"csv\"", "format = \"csv\"\ndecimal = \",\""), "file.decimal and"),
    (("format = \"csv\"", "format = \"csv\"\nheader_row = 0"), "file.header_row"),
    (("format = \"csv\"", "format = \"csv\"\nencoding = \"klingon\""), "file.encoding"),
    (("[analytes]", "[analytez]"), "map.analytez is not a key"),
    (("[file]", "[file"), "not valid TOML"),
    (("column = \"p\", unit", "column = \"p\", repeatability = -1, unit"),
     "analytes.p.repeatability must be > 0"),
    (("column = \"p\", unit", "column = \"p\", repeatability = \"low\", unit"),
     "analytes.p.repeatability must be a number"),
])
def test_a_bad_map_is_one_line_naming_the_key(change, names):
    old, new = change
    assert old in SMALL_MAP
    with pytest.raises(ValueError) as info:
        L.parse_map(SMALL_MAP.replace(old, new, 1))
    message = str(info.value)
    assert names in message and "\n" not in message, message


# -- times and numbers --------------------------------------------------------------------


@pytest.mark.parametrize(("text", "expected"), [
    ("2026-11-20T01:02:03Z", "2026-11-20T01:02:03Z"),
    ("2026-11-20 09:02:03", "2026-11-20T01:02:03Z"),                  # Perth local
    ("2026-11-20 09:02:03.123456789", "2026-11-20T01:02:03.123456789Z"),
    ("2026-11-20T09:02", "2026-11-20T01:02:00Z"),
    ("2026-11-20T03:02:03,5+02:00", "2026-11-20T01:02:03.5Z"),
    ("2026-11-19T21:02:03-0400", "2026-11-20T01:02:03Z"),
])
def test_iso_times_keep_nanoseconds_and_read_local_times_in_the_maps_zone(text, expected):
    assert L.parse_time_ns(text, L.ISO8601, PERTH) == utc(expected)


def test_strptime_times_and_bad_times():
    assert L.parse_time_ns("20/11/2026 09:02", "%d/%m/%Y %H:%M", PERTH) == utc(
        "2026-11-20T01:02:00Z")
    assert L.parse_time_ns("20/11/2026 01:02 +0000", "%d/%m/%Y %H:%M %z", PERTH) == utc(
        "2026-11-20T01:02:00Z")
    for bad in ("2026-13-01T00:00:00", "yesterday", "2026-11-20T01:02:03.1234567890Z"):
        with pytest.raises(ValueError, match="time"):
            L.parse_time_ns(bad, L.ISO8601, PERTH)
    with pytest.raises(ValueError, match="does not match"):
        L.parse_time_ns("2026-11-20", "%d/%m/%Y", PERTH)


def test_numbers_follow_the_decimal_mark():
    assert L.parse_number("56,31", ",") == Decimal("56.31")
    assert L.parse_number(" 830 ", ".") == Decimal(830)
    assert L.parse_number("1.5e-3", ".") == Decimal("0.0015")
    assert L.parse_number(Decimal("0.083"), ",") == Decimal("0.083")
    for text, mark in (("56.31", ","), ("1.234,5", ","), ("<0.01", "."), ("n/a", "."),
                       ("", "."), ("nan", "."), (True, ".")):
        with pytest.raises(ValueError):
            L.parse_number(text, mark)


def test_assay_ids_of_revisions():
    assert L.assay_id_for("S1", 0) == "S1" and L.assay_id_for("S1", 3) == "S1-r3"
    assert L.superseded_id("S1", 0) == "" and L.superseded_id("S1", 1) == "S1"
    assert L.superseded_id("S1", 2) == "S1-r1"


# -- rows -> assays -----------------------------------------------------------------------


def test_a_good_row_becomes_the_assay_with_units_converted():
    (row,), refused = L.rows_to_assays(f"{HEADER}\n{GOOD}\n".encode(), small_map())
    assert refused == [] and row.line == 2
    a = row.assay
    assert (a.assay_id, a.lot_id, a.status, a.supersedes, a.lab_id) == (
        "S1", "L1", pb.PROVISIONAL, "", "labX")
    assert dict(a.analytes) == {"Fe": 60.5, "P": 0.083, "S": 0.012}
    assert a.bulk_density_t_m3 == 2.4 and a.moisture_pct == 0.0
    assert timestamp_ns(a.window_start) == utc("2026-11-20T01:00:00Z")
    assert timestamp_ns(a.window_end) == utc("2026-11-20T01:20:00Z")
    assert timestamp_ns(a.reported_time) == utc("2026-11-20T05:00:00Z")


def test_a_stated_repeatability_goes_with_every_assay_in_pp():
    """``repeatability`` is in the column's unit (ppm / 10,000 = pp), and an assay
    carries it for the analytes it reports."""
    lims = L.parse_map(SMALL_MAP.replace('FE = { column = "fe" }',
                                         'FE = { column = "fe", repeatability = 0.2 }')
                       .replace('column = "p", unit', 'column = "p", repeatability = 30, unit'))
    assert [a.repeatability_pp for a in lims.analytes] == [0.2, 0.003, None]
    no_p = GOOD.replace("S1,", "S2,", 1).replace(",830,", ",,")
    rows, refused = L.rows_to_assays(f"{HEADER}\n{GOOD}\n{no_p}\n".encode(), lims)
    assert refused == [] and len(rows) == 2
    assert dict(rows[0].assay.repeatability_pp) == {"Fe": 0.2, "P": 0.003}
    assert dict(rows[1].assay.repeatability_pp) == {"Fe": 0.2}
    # without the key, assays state none (the site's configured one applies)
    (plain,), _ = L.rows_to_assays(f"{HEADER}\n{GOOD}\n".encode(), small_map())
    assert dict(plain.assay.repeatability_pp) == {}


def test_bad_rows_are_refused_with_line_and_reason_and_good_ones_kept():
    rows = [
        GOOD,                                                           # line 2
        GOOD.replace("S1,", "S2,").replace("60.5", "<0.5"),             # 3: not a number
        GOOD.replace("S1,", "S3,").replace("Prov", "Hold"),             # 4: unknown status
        GOOD.replace("S1,", "S4,").replace("T01:20", "T00:20"),         # 5: window reversed
        GOOD.replace("S1,", "S5,").replace("60.5", "101"),              # 6: ledger's range
        GOOD.replace("S1,", "S6,") + ",extra",                          # 7: field count
        "",                                                             # 8: blank, skipped
        GOOD.replace("S1,", "S7,").replace(",,", ",1,"),                # 9: good, revision 1
        GOOD.replace("S1,", "S8,").replace("T05:00", "T01:10"),         # 10: reported early
        GOOD.replace("S1,", "S9,").replace("60.5,830,120", ",,"),       # 11: no analyte
        GOOD,                                                           # 12: S1 again
        GOOD.replace("S1,", ",").replace("L1", "L2"),                   # 13: empty sample
        '"S10",L1,"2026-11-20T01:00:00Z",2026-11-20T01:20:00Z,Fin,2026-11-20T05:00:00Z,,'
        '"2400",70,"1,1",',                                             # 14: ppm with comma
    ]
    text = HEADER + "\n" + "\n".join(rows) + "\n"
    assays, refused = L.rows_to_assays(text.encode(), small_map())
    assert [(a.line, a.assay.assay_id) for a in assays] == [(2, "S1"), (9, "S7-r1")]
    assert assays[1].assay.supersedes == "S7"
    reasons = {r.line: r.reason for r in refused}
    assert sorted(reasons) == [3, 4, 5, 6, 7, 10, 11, 12, 13, 14]
    assert "fe: '<0.5' is not a number" in reasons[3]
    assert "status 'Hold' is not one of" in reasons[4]
    assert "ends before it starts" in reasons[5]
    assert "analyte_out_of_range" in reasons[6]
    assert "12 fields, the header has 11" in reasons[7]
    assert "reported before" in reasons[10]
    assert "no analyte has a value" in reasons[11]
    assert "already on line 2" in reasons[12]
    assert "id is empty" in reasons[13]
    assert "p: '1,1' is not a number" in reasons[14]


def test_a_header_without_a_mapped_column_refuses_the_whole_file_at_its_line():
    lims = L.parse_map(SMALL_MAP.replace("[file]", "[file]\nheader_row = 3"))
    text = f"LIMS export\nexported 2026-11-20\n{HEADER.replace(',p,s', ',p,sulphur')}\n{GOOD}\n"
    assert L.rows_to_assays(text.encode(), lims) == ([], [L.RefusedRow(3, "the header has no "
                                                                       "column 's'")])
    assert L.rows_to_assays(b"", lims)[1] == [L.RefusedRow(3, "no header row")]


def test_bytes_invalid_in_the_encoding_refuse_only_their_row():
    lines = [HEADER.encode(), GOOD.encode(),
             GOOD.replace("S1,", "S2,").replace("L1", "L\xe9").encode("latin-1"),
             GOOD.replace("S1,", "S3,").encode()]
    assays, refused = L.rows_to_assays(b"\xef\xbb\xbf" + b"\r\n".join(lines), small_map())
    assert [a.assay.assay_id for a in assays] == ["S1", "S3"]
    assert [r.line for r in refused] == [3] and "not valid text" in refused[0].reason
    latin = L.parse_map(SMALL_MAP.replace("[file]", "[file]\nencoding = \"latin-1\""))
    assays, refused = L.rows_to_assays(b"\n".join(lines), latin)
    assert refused == [] and assays[1].assay.lot_id == "L\xe9"


def test_a_quoted_field_over_two_lines_keeps_the_line_numbers_of_the_rows_after_it():
    quoted = GOOD.replace("S1,L1", 'S1,"L1\nsecond line"')
    text = f"{HEADER}\n{quoted}\n{GOOD.replace('S1,', 'S2,').replace('60.5', 'x')}\n"
    assays, refused = L.rows_to_assays(text.encode(), small_map())
    assert assays[0].line == 2 and assays[0].assay.lot_id == "L1\nsecond line"
    assert refused[0].line == 4


def test_a_supersedes_column_names_the_replaced_result():
    lims = L.parse_map(SMALL_MAP.replace('revision = "rev"', 'supersedes = "rev"'))
    row = GOOD.replace("S1,", "S9,").replace(",,", ",S1,")
    (a,), refused = L.rows_to_assays(f"{HEADER}\n{row}\n".encode(), lims)
    assert refused == [] and (a.assay.assay_id, a.assay.supersedes) == ("S9", "S1")


JSON_MAP = SMALL_MAP.replace('format = "csv"', 'format = "json"')


def test_json_exports_give_the_line_of_each_object():
    items = [dict(zip(HEADER.split(","), GOOD.split(","))) for _ in range(3)]
    items[1]["id"], items[1]["fe"] = "S2", 61.25            # a JSON number
    items[2]["id"], items[2]["fe"] = "S3", "high"
    text = "[\n" + ",\n".join(json.dumps(i, indent=1) for i in items) + ", 7\n]\n"
    assays, refused = L.rows_to_assays(text.encode(), L.parse_map(JSON_MAP))
    starts = [n for n, line in enumerate(text.splitlines(), 1) if line.startswith("{")]
    assert [(a.line, a.assay.assay_id) for a in assays] == [(starts[0], "S1"),
                                                             (starts[1], "S2")]
    assert assays[1].assay.analytes["Fe"] == 61.25
    assert [r.line for r in refused] == [starts[2], text.count("\n") - 1]
    assert "'high' is not a number" in refused[0].reason
    assert refused[1].reason == "an item that is not an object"
    assert L.rows_to_assays(b'{"id": 1}', L.parse_map(JSON_MAP)) == (
        [], [L.RefusedRow(1, "not a JSON list of objects")])
    broken = L.rows_to_assays(b'[\n' + json.dumps(items[0]).encode() + b',\n{"id": ',
                              L.parse_map(JSON_MAP))
    assert len(broken[0]) == 1 and broken[1][0].line == 3
    assert "not JSON" in broken[1][0].reason


# -- the simulator's LIMS files -----------------------------------------------------------


def _lab_results(rng: np.random.Generator) -> list:
    lot = table_5_4_lots()[1]
    start = utc("2026-11-20T00:00:00Z") + 123_456_789       # not on a whole second
    belt = BeltGrade(lot, start, start + 6 * 3600 * 10**9, rng)
    lab = LabModel(provisional_fraction=0.5)
    results = lab.assays(belt, start, start + 6 * 3600 * 10**9, rng, [0])
    return sorted(results, key=lambda r: (r.reported_ns, r.assay_id))


def test_the_simulators_files_read_back_as_the_assays_the_simulator_emits(tmp_path):
    print(f"sim LIMS round trip: seed {SEED} (--seed {SEED} reproduces it)")
    results = _lab_results(np.random.default_rng(SEED))
    assert any(r.supersedes for r in results), "the draw has no provisional result"
    writer = S.LimsDropWriter(tmp_path)
    batches = [results[i:i + 4] for i in range(0, len(results), 4)]
    paths = [writer.write(batch[-1].reported_ns, batch) for batch in batches]
    assert writer.write(0, []) is None
    assert sorted(tmp_path.iterdir()) == sorted(paths)       # no temporary file left
    lims = L.parse_map(EXAMPLE.read_text())
    got = []
    for path in paths:
        assays, refused = L.rows_to_assays(path.read_bytes(), lims)
        assert refused == []
        got += [a.assay for a in assays]
    assert len(got) == len(results)
    for assay, r in zip(got, results):
        expected = messages.assay(r)
        expected.assay_id = writer.assay_ids[r.assay_id]
        expected.supersedes = writer.assay_ids[r.supersedes] if r.supersedes else ""
        assert assay == expected, r.assay_id
    # the same supersession: each FINAL that replaced a PROVISIONAL is its next revision
    for r in results:
        if r.supersedes:
            assert writer.assay_ids[r.assay_id] == writer.assay_ids[r.supersedes] + "-r1"


def test_local_times_and_decimal_commas_of_the_simulator():
    assert S.local_time(utc("2026-11-20T01:02:03.5Z"), PERTH) == "2026-11-20 09:02:03.5"
    assert S.local_time(utc("2026-11-20T01:02:03Z"), PERTH) == "2026-11-20 09:02:03"
    assert S.decimal_comma(0.083, Decimal(10_000)) == "830,000"
    assert S.decimal_comma(1e-05) == "0,00001"
    assert L.parse_number(S.decimal_comma(6.123456789012345), ",") == Decimal(
        "6.123456789012345")

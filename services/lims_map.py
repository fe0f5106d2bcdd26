"""The LIMS map (``lims.toml``): which column of a laboratory's export holds what, and the rows
of one export file turned into ``assay`` messages.

Everything here is pure: :func:`parse_map` reads the map's TOML text, :func:`rows_to_assays`
turns the bytes of one export file into assays and refused rows; the cells' times and
numbers are read by :mod:`services.lims_values` (re-exported here).  ``services.lab`` does
the I/O (the drop folder, the journal, publishing).

The map's sections (``docs/lims.example.toml`` is a complete map with every key explained;
``docs/integration.md`` how to write one): ``[file]`` (``format`` csv or json, ``encoding``,
and for CSV ``delimiter``, ``decimal`` mark and ``header_row``), ``[time]`` (``format``:
``iso8601`` or a strptime format; the ``timezone`` of times without an offset),
``[columns]`` (``sample_id``, ``lot``, ``window_start``, ``window_end``, ``status``,
``reported_time``; optional ``revision``, ``supersedes``, ``moisture``, ``bulk_density``
with its unit, ``lab_id``), ``[lab] id``, ``[status]`` (LIMS code -> PROVISIONAL or
FINAL) and ``[analytes]`` (analyte -> ``{ column, unit }``, unit %, ppm or g/t, and
optionally the lab's stated ``repeatability``: one sd in the column's unit, written into
every assay's ``repeatability_pp``).

The assay id of a result (:func:`assay_id_for`) is the sample id for revision 0 and
``<sample>-r<N>`` for revision N > 0; revision N supersedes revision N - 1 (``<sample>`` for
N = 1), unless a ``supersedes`` column names the replaced result's sample id.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
import tomllib
from dataclasses import dataclass, field
from datetime import timezone
from decimal import Decimal
from typing import Any
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from schemas import pb
from schemas.analytes import DEFAULT_ANALYTES, canonical_name, name_problem
from schemas.events import make_event, set_timestamp_ns
from schemas.validate import InvalidEvent, check_event
from services.lims_values import ISO8601, parse_number, parse_time_ns

__all__ = ["FORMATS", "ANALYTE_UNITS", "DENSITY_UNITS", "STATUSES", "ISO8601", "AnalyteColumn",
           "LimsMap", "RowAssay", "RefusedRow", "parse_map", "assay_id_for", "superseded_id",
           "parse_time_ns", "parse_number", "row_assay", "rows_to_assays"]

#: File formats a map may name.
FORMATS = ("csv", "json")
#: Analyte units -> the factor to mass % (ppm and g/t are parts per million by mass).
ANALYTE_UNITS: dict[str, Decimal] = {"%": Decimal(1), "ppm": Decimal("0.0001"),
                                     "g/t": Decimal("0.0001")}
#: Bulk density units -> the factor to t/m3.
DENSITY_UNITS: dict[str, Decimal] = {"t/m3": Decimal(1), "g/cm3": Decimal(1),
                                     "kg/m3": Decimal("0.001")}
#: The Assay status enum's names a LIMS code may map to.
STATUSES = ("PROVISIONAL", "FINAL")

_REQUIRED_COLUMNS = ("sample_id", "lot", "window_start", "window_end", "status",
                     "reported_time")
_OPTIONAL_COLUMNS = ("revision", "supersedes", "moisture", "bulk_density", "lab_id")
_SPACE_RE = re.compile(r"\s*")


# -- the map ------------------------------------------------------------------------------


@dataclass(frozen=True)
class AnalyteColumn:
    """One analyte of the map: its canonical name, its column, the column's unit, and
    the lab's stated repeatability (one sd, pp; None: not stated, the site's configured
    one applies)."""

    name: str
    column: str
    unit: str
    repeatability_pp: float | None = None


@dataclass(frozen=True)
class LimsMap:
    """A parsed ``lims.toml``: ``columns`` maps a field (``sample_id``, ``lot``, ...; the
    optional ones only when mapped) to its column; ``status_codes`` a LIMS code (stripped,
    case-folded) to ``PROVISIONAL`` or ``FINAL``; ``lab_id`` is the lab when no ``lab_id``
    column is mapped; ``tz`` the zone of ``timezone``; the rest as the TOML keys."""

    columns: dict[str, str]
    analytes: tuple[AnalyteColumn, ...]
    status_codes: dict[str, str]
    format: str = "csv"
    encoding: str = "utf-8"
    delimiter: str = ","
    decimal: str = "."
    header_row: int = 1
    time_format: str = ISO8601
    timezone: str = "UTC"
    lab_id: str = ""
    density_unit: str = "t/m3"
    tz: Any = field(default=None, compare=False, repr=False)

    def column(self, name: str) -> str | None:
        """The column of field ``name``, or None when the map does not name one."""
        return self.columns.get(name)


def _table(doc: dict, name: str, *, required: bool = False) -> dict:
    value = doc.get(name, {})
    if not isinstance(value, dict):
        raise ValueError(f"[{name}] must be a table")
    if required and not value:
        raise ValueError(f"[{name}] is missing or empty")
    return value


def _text(table: dict, key: str, where: str, default: str | None = None) -> str:
    value = table.get(key, default)
    if value is None:
        raise ValueError(f"{where}.{key} is missing")
    if not isinstance(value, str) or (not value.strip() and default is None):
        raise ValueError(f"{where}.{key} must be a non-empty string, got {value!r}")
    return value


def _unknown_keys(table: dict, allowed, where: str) -> None:
    extra = sorted(set(table) - set(allowed))
    if extra:
        raise ValueError(f"{where}.{extra[0]} is not a key of the map (allowed: "
                         f"{', '.join(allowed)})")


def _column_and_unit(value: Any, where: str, units, default_unit: str,
                     extra_keys: tuple[str, ...] = ()) -> tuple[str, str]:
    """A column given as ``"NAME"`` or ``{ column = "NAME", unit = "U" }`` (and the
    caller's ``extra_keys``, read by the caller)."""
    if isinstance(value, str) and value.strip():
        return value, default_unit
    if isinstance(value, dict):
        _unknown_keys(value, ("column", "unit", *extra_keys), where)
        column = _text(value, "column", where)
        unit = _text(value, "unit", where, default_unit)
        if unit not in units:
            raise ValueError(f"{where}.unit {unit!r} is not one of {', '.join(units)}")
        return column, unit
    raise ValueError(f"{where} must be a column name or {{ column = ..., unit = ... }}")


def _file_section(doc: dict) -> dict[str, Any]:
    table = _table(doc, "file")
    _unknown_keys(table, ("format", "encoding", "delimiter", "decimal", "header_row"), "file")
    fmt = _text(table, "format", "file", "csv")
    if fmt not in FORMATS:
        raise ValueError(f"file.format {fmt!r} is not one of {', '.join(FORMATS)}")
    encoding = _text(table, "encoding", "file", "utf-8")
    try:
        "".encode(encoding)
    except LookupError:
        raise ValueError(f"file.encoding {encoding!r} is not a known text encoding") from None
    delimiter = _text(table, "delimiter", "file", ",")
    if len(delimiter) != 1 or delimiter in "\"\r\n":
        raise ValueError(f"file.delimiter must be one character (not a quote or newline), "
                         f"got {delimiter!r}")
    decimal = _text(table, "decimal", "file", ".")
    if decimal not in (".", ","):
        raise ValueError(f"file.decimal must be '.' or ',', got {decimal!r}")
    if decimal == delimiter:
        raise ValueError("file.decimal and file.delimiter are the same character")
    header_row = table.get("header_row", 1)
    if type(header_row) is not int or header_row < 1:
        raise ValueError(f"file.header_row must be an integer >= 1, got {header_row!r}")
    return {"format": fmt, "encoding": encoding, "delimiter": delimiter, "decimal": decimal,
            "header_row": header_row}


def _time_section(doc: dict) -> dict[str, Any]:
    table = _table(doc, "time")
    _unknown_keys(table, ("format", "timezone"), "time")
    fmt = _text(table, "format", "time", ISO8601)
    if fmt != ISO8601 and "%" not in fmt:
        raise ValueError(f"time.format must be {ISO8601!r} or a strptime format, got {fmt!r}")
    name = _text(table, "timezone", "time", "UTC")
    try:
        tz = timezone.utc if name == "UTC" else ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError):
        raise ValueError(f"time.timezone {name!r} is not a known time zone") from None
    return {"time_format": fmt, "timezone": name, "tz": tz}


def _columns_section(doc: dict) -> tuple[dict[str, str], str]:
    table = _table(doc, "columns", required=True)
    _unknown_keys(table, _REQUIRED_COLUMNS + _OPTIONAL_COLUMNS, "columns")
    columns = {name: _text(table, name, "columns") for name in _REQUIRED_COLUMNS}
    density_unit = "t/m3"
    for name in _OPTIONAL_COLUMNS:
        if name not in table:
            continue
        if name == "bulk_density":
            columns[name], density_unit = _column_and_unit(
                table[name], "columns.bulk_density", DENSITY_UNITS, "t/m3")
        elif name == "moisture":
            columns[name], _ = _column_and_unit(table[name], "columns.moisture", ("%",), "%")
        else:
            columns[name] = _text(table, name, "columns")
    return columns, density_unit


def _analytes_section(doc: dict) -> tuple[AnalyteColumn, ...]:
    table = _table(doc, "analytes", required=True)
    out: dict[str, AnalyteColumn] = {}
    for raw_name, value in table.items():
        problem = name_problem(raw_name)
        if problem:
            raise ValueError(f"analytes: {problem}")
        name = canonical_name(raw_name, DEFAULT_ANALYTES)
        if name in out:
            raise ValueError(f"analytes.{raw_name} names {name} a second time")
        where = f"analytes.{raw_name}"
        column, unit = _column_and_unit(value, where, ANALYTE_UNITS, "%", ("repeatability",))
        stated = value.get("repeatability") if isinstance(value, dict) else None
        out[name] = AnalyteColumn(name, column, unit, _repeatability_pp(stated, unit, where))
    return tuple(out.values())


def _repeatability_pp(value: Any, unit: str, where: str) -> float | None:
    """An analyte's stated repeatability (in its column's unit) as pp; None if absent."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}.repeatability must be a number (one sd, in the column's "
                         f"unit), got {value!r}")
    pp = float(Decimal(str(value)) * ANALYTE_UNITS[unit])
    if not (math.isfinite(pp) and 0 < pp <= 100):
        raise ValueError(f"{where}.repeatability must be > 0 and at most 100 %, got {value!r}")
    return pp


def _status_section(doc: dict) -> dict[str, str]:
    table = _table(doc, "status", required=True)
    codes: dict[str, str] = {}
    for code, status in table.items():
        if not isinstance(status, str) or status.strip().upper() not in STATUSES:
            raise ValueError(f"status.{code} must be one of {', '.join(STATUSES)}, got {status!r}")
        folded = code.strip().casefold()
        if not folded:
            raise ValueError("status: an empty LIMS code")
        if folded in codes:
            raise ValueError(f"status.{code} is given twice (codes ignore case)")
        codes[folded] = status.strip().upper()
    return codes


def parse_map(text: str) -> LimsMap:
    """A :class:`LimsMap` from the TOML text of a ``lims.toml``.

    Raises
    ------
    ValueError
        With one line naming the key that is missing or wrong.
    """
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"not valid TOML: {exc}") from None
    _unknown_keys(doc, ("file", "time", "columns", "lab", "status", "analytes"), "map")
    columns, density_unit = _columns_section(doc)
    lab = _table(doc, "lab")
    _unknown_keys(lab, ("id",), "lab")
    lab_id = _text(lab, "id", "lab", "")
    if "lab_id" not in columns and not lab_id.strip():
        raise ValueError("lab.id is missing (or map a columns.lab_id)")
    analytes = _analytes_section(doc)
    taken: dict[str, str] = {}
    for name, column in [*columns.items(), *((a.name, a.column) for a in analytes)]:
        if column in taken:
            raise ValueError(f"column {column!r} is mapped twice ({taken[column]} and {name})")
        taken[column] = name
    return LimsMap(columns=columns, analytes=analytes, status_codes=_status_section(doc),
                   lab_id=lab_id.strip(), density_unit=density_unit, **_file_section(doc),
                   **_time_section(doc))


# -- ids ------------------------------------------------------------------


def assay_id_for(sample_id: str, revision: int) -> str:
    """The assay id of a result: ``sample_id`` for revision 0, ``<sample_id>-r<N>`` after."""
    return sample_id if revision == 0 else f"{sample_id}-r{revision}"


def superseded_id(sample_id: str, revision: int) -> str:
    """The assay id revision ``revision`` of ``sample_id`` replaces: revision - 1's ("" for 0)."""
    return "" if revision == 0 else assay_id_for(sample_id, revision - 1)


# -- rows -> assays -----------------------------------------------------------------------


@dataclass(frozen=True)
class RowAssay:
    """A row that became an assay: its line in the file, and the message."""

    line: int
    assay: Any  # pb.Assay


@dataclass(frozen=True)
class RefusedRow:
    """A row (or the whole file, at the line of the problem) that did not become an assay."""

    line: int
    reason: str


class _RowError(ValueError):
    """A row refused: the message is the one-line reason."""


def _cell(row: dict, column: str, *, required: bool = True) -> Any:
    value = row.get(column)
    if isinstance(value, str):
        if any("\udc80" <= c <= "\udcff" for c in value):
            raise _RowError(f"{column}: bytes that are not valid text in the file's encoding")
        value = value.strip()
    if required and (value is None or value == ""):
        raise _RowError(f"{column} is empty")
    return value


def _text_cell(row: dict, column: str) -> str:
    value = _cell(row, column)
    if not isinstance(value, (str, int)) or isinstance(value, bool):
        raise _RowError(f"{column}: {value!r} is not text")
    return str(value)


def _number(row: dict, column: str, decimal: str) -> Decimal:
    try:
        return parse_number(_cell(row, column), decimal)
    except ValueError as exc:
        raise _RowError(f"{column}: {exc}") from None


def _time(row: dict, column: str, lims: LimsMap) -> int:
    value = _cell(row, column)
    if not isinstance(value, str):
        raise _RowError(f"{column}: {value!r} is not a time")
    try:
        return parse_time_ns(value, lims.time_format, lims.tz)
    except ValueError as exc:
        raise _RowError(f"{column}: {exc}") from None


def _optional(row: dict, lims: LimsMap, name: str) -> bool:
    """Whether the map names a column for ``name`` and the row has a value in it."""
    column = lims.column(name)
    return column is not None and _cell(row, column, required=False) not in (None, "")


def _revision(row: dict, lims: LimsMap) -> int:
    if not _optional(row, lims, "revision"):
        return 0
    column = lims.columns["revision"]
    value = _cell(row, column)
    text = str(value)
    if isinstance(value, bool) or not re.fullmatch(r"\d{1,6}", text):
        raise _RowError(f"{column}: revision {value!r} is not an integer >= 0")
    return int(text)


def _status(row: dict, lims: LimsMap) -> str:
    column = lims.columns["status"]
    code = str(_cell(row, column))
    status = lims.status_codes.get(code.casefold())
    if status is None:
        raise _RowError(f"{column}: status {code!r} is not one of the map's codes "
                        f"({', '.join(sorted(lims.status_codes))})")
    return status


def _analytes(row: dict, lims: LimsMap) -> dict[str, float]:
    out: dict[str, float] = {}
    for analyte in lims.analytes:
        if _cell(row, analyte.column, required=False) in (None, ""):
            continue  # not assayed: the analyte is left out of this result
        value = _number(row, analyte.column, lims.decimal) * ANALYTE_UNITS[analyte.unit]
        out[analyte.name] = float(value)
    if not out:
        raise _RowError("no analyte has a value")
    return out


def row_assay(row: dict, lims: LimsMap) -> tuple[tuple[str, int], Any]:
    """One row (column -> cell) -> ((sample id, revision), ``pb.Assay``), checked as the
    ledger checks an event (:func:`schemas.validate.check_event`) and by the map's own
    rules (window order, reported after the window).  Raises ``_RowError``."""
    col = lims.columns
    sample = _text_cell(row, col["sample_id"])
    revision = _revision(row, lims)
    start_ns, end_ns = _time(row, col["window_start"], lims), _time(row, col["window_end"], lims)
    reported_ns = _time(row, col["reported_time"], lims)
    if end_ns < start_ns:
        raise _RowError(f"{col['window_end']}: the sampling window ends before it starts")
    if reported_ns < end_ns:
        raise _RowError(f"{col['reported_time']}: reported before the sampling window ends")
    supersedes = (_text_cell(row, col["supersedes"]) if _optional(row, lims, "supersedes")
                  else superseded_id(sample, revision))
    msg = pb.Assay(assay_id=assay_id_for(sample, revision), lot_id=_text_cell(row, col["lot"]),
                   status=getattr(pb, _status(row, lims)), supersedes=supersedes,
                   lab_id=(_text_cell(row, col["lab_id"]) if lims.column("lab_id")
                           else lims.lab_id))
    msg.analytes.update(_analytes(row, lims))
    msg.repeatability_pp.update({a.name: a.repeatability_pp for a in lims.analytes
                                 if a.repeatability_pp is not None and a.name in msg.analytes})
    if _optional(row, lims, "moisture"):
        msg.moisture_pct = float(_number(row, col["moisture"], lims.decimal))
    if _optional(row, lims, "bulk_density"):
        density = _number(row, col["bulk_density"], lims.decimal)
        msg.bulk_density_t_m3 = float(density * DENSITY_UNITS[lims.density_unit])
    set_timestamp_ns(msg.window_start, start_ns)
    set_timestamp_ns(msg.window_end, end_ns)
    set_timestamp_ns(msg.reported_time, reported_ns)
    try:
        check_event(make_event(msg, source="lims.check", epoch=0, seq=0))
    except InvalidEvent as exc:
        raise _RowError(f"the ledger would refuse it: {exc}") from None
    return (sample, revision), msg


def _csv_rows(text: str, lims: LimsMap) -> tuple[list[tuple[int, dict]], list[RefusedRow]]:
    """(line, column -> cell) of each data row of a CSV export, and the rows refused for
    their shape; a header without a mapped column refuses the whole file at its line."""
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=lims.delimiter)
    header: list[str] | None = None
    rows: list[tuple[int, dict]] = []
    refused: list[RefusedRow] = []
    line = 1
    try:
        for cells in reader:
            first, line = line, reader.line_num + 1
            if first < lims.header_row or not any(c.strip() for c in cells):
                continue
            if header is None:
                header = [c.strip() for c in cells]
                missing = [c for c in _mapped_columns(lims) if c not in header]
                if missing:
                    return [], [RefusedRow(first, f"the header has no column {missing[0]!r}")]
                continue
            if len(cells) != len(header):
                refused.append(RefusedRow(first, f"{len(cells)} fields, the header has "
                                          f"{len(header)}"))
                continue
            rows.append((first, dict(zip(header, cells))))
    except csv.Error as exc:
        refused.append(RefusedRow(line, f"the rest of the file is not CSV: {exc}"))
    if header is None:
        refused.append(RefusedRow(lims.header_row, "no header row"))
    return rows, refused


def _mapped_columns(lims: LimsMap) -> list[str]:
    return [*lims.columns.values(), *(a.column for a in lims.analytes)]


def _json_rows(text: str) -> tuple[list[tuple[int, dict]], list[RefusedRow]]:
    """(line of the object's start, object) of each item of a JSON list export."""
    decoder = json.JSONDecoder(parse_float=Decimal)
    lines = _LineCounter(text)
    pos = _SPACE_RE.match(text).end()
    if not text.startswith("[", pos):
        return [], [RefusedRow(lines.at(pos), "not a JSON list of objects")]
    rows: list[tuple[int, dict]] = []
    refused: list[RefusedRow] = []
    pos = _SPACE_RE.match(text, pos + 1).end()
    if text.startswith("]", pos):
        return rows, refused
    while True:
        line = lines.at(pos)
        try:
            item, pos = decoder.raw_decode(text, pos)
        except json.JSONDecodeError as exc:
            refused.append(RefusedRow(line, f"the rest of the file is not JSON: {exc.msg}"))
            return rows, refused
        if isinstance(item, dict):
            rows.append((line, item))
        else:
            refused.append(RefusedRow(line, "an item that is not an object"))
        pos = _SPACE_RE.match(text, pos).end()
        if text.startswith("]", pos):
            return rows, refused
        if not text.startswith(",", pos):
            refused.append(RefusedRow(lines.at(pos),
                                      "the rest of the file is not JSON: expected ',' or ']'"))
            return rows, refused
        pos = _SPACE_RE.match(text, pos + 1).end()


class _LineCounter:
    """Line numbers of increasing positions in a text, counted once."""

    def __init__(self, text: str) -> None:
        self.text, self.pos, self.line = text, 0, 1

    def at(self, pos: int) -> int:
        """The 1-based line of ``pos`` (positions must not decrease)."""
        self.line += self.text.count("\n", self.pos, pos)
        self.pos = pos
        return self.line


def rows_to_assays(data: bytes, lims: LimsMap) -> tuple[list[RowAssay], list[RefusedRow]]:
    """The assays of one export file, and the rows refused with their line and reason.

    Never raises for bad data: a row that does not make a valid assay (an empty or
    malformed cell, an unknown status code, what the ledger would refuse, a second row of
    one sample and revision) is refused and the other rows still become assays; a file
    that cannot be read at all (no header, not a JSON list) is one refused "row" at the
    line of the problem.  Bytes that are not valid in the map's encoding refuse only the
    rows that hold them.  Assays come in file order.
    """
    text = data.decode(lims.encoding, errors="surrogateescape")
    text = text.removeprefix("\ufeff")
    rows, refused = (_csv_rows(text, lims) if lims.format == "csv" else _json_rows(text))
    assays: list[RowAssay] = []
    first_line: dict[tuple[str, int], int] = {}
    for line, row in rows:
        try:
            ident, msg = row_assay(row, lims)
        except _RowError as exc:
            refused.append(RefusedRow(line, str(exc)))
            continue
        if ident in first_line:
            refused.append(RefusedRow(line, f"sample {ident[0]!r} revision {ident[1]} is "
                                      f"already on line {first_line[ident]}"))
            continue
        first_line[ident] = line
        assays.append(RowAssay(line, msg))
    refused.sort(key=lambda r: r.line)
    return assays, refused

"""The simulated laboratory's LIMS: its results written as export files into a drop folder.

:class:`LimsDropWriter` writes each report batch of :class:`~sim.grades.LabResult` as one
CSV file in the format :data:`MAP_TOML` maps (the same map as ``docs/lims.example.toml``):
a title line, then a header, ``;`` between fields, a decimal comma, local times of
Australia/Perth with nanoseconds, P in ppm and bulk density in kg/m3.  A file is written
under a hidden temporary name, flushed to disk and renamed, so a watcher never sees half
a file.

The laboratory's supersession becomes a revision: a FINAL result that supersedes a
PROVISIONAL one is written as the same sample with the next revision, so
``stockpile service lab`` publishes it as ``<sample>-r1`` superseding ``<sample>``
(:func:`services.lims_map.assay_id_for`).  :attr:`LimsDropWriter.assay_ids` maps each
result's simulator id to the assay id the adapter gives it.  Numbers are written from
their shortest decimal form and converted with decimal arithmetic, so every value reads
back as the same double.
"""

from __future__ import annotations

import csv
import io
import os
from datetime import datetime, timezone
from decimal import Decimal
from pathlib import Path
from typing import Iterable
from zoneinfo import ZoneInfo

from schemas.times import NS_PER_S
from services.lims_map import assay_id_for
from sim.grades import ANALYTES, LabModel, LabResult

__all__ = ["MAP_TOML", "TIMEZONE", "COLUMNS", "ANALYTE_COLUMNS", "STATUS_CODES",
           "LimsDropWriter", "local_time", "decimal_comma", "write_map"]

#: The time zone the simulated LIMS writes its local times in.
TIMEZONE = "Australia/Perth"
#: Header of the export: sample, lot, window, status, revision, authorised time, lab.
COLUMNS = ("SampleID", "Lot", "SampledFrom", "SampledTo", "Status", "Rev", "Authorised", "Lab")
#: analyte -> (column, unit, factor from mass % to the unit)
ANALYTE_COLUMNS: dict[str, tuple[str, str, Decimal]] = {
    "Fe": ("Fe_pct", "%", Decimal(1)), "SiO2": ("SiO2_pct", "%", Decimal(1)),
    "Al2O3": ("Al2O3_pct", "%", Decimal(1)), "P": ("P_ppm", "ppm", Decimal(10_000)),
    "LOI": ("LOI_pct", "%", Decimal(1)),
}
#: moisture (mass %) and bulk density (kg/m3) columns
MOISTURE_COLUMN, DENSITY_COLUMN = "H2O_pct", "BulkDensity_kgm3"
#: Assay status -> the LIMS's code
STATUS_CODES = {"PROVISIONAL": "P", "FINAL": "F"}
#: The first line of every export (above the header).
TITLE = "Laboratory results export"

#: The map of these files for ``stockpile service lab --map`` (``docs/lims.example.toml``
#: is the same map with every key explained).
def _stated_in_column_unit(analyte: str, factor: Decimal) -> float:
    """The simulated lab's stated repeatability of a final result (its error sd) in the
    analyte's column unit."""
    return float(Decimal(str(LabModel().stated(1.0)[analyte])) * factor)


MAP_TOML = f"""\
[file]
format = "csv"
encoding = "utf-8"
delimiter = ";"
decimal = ","
header_row = 2

[time]
format = "iso8601"
timezone = "{TIMEZONE}"

[columns]
sample_id = "SampleID"
lot = "Lot"
window_start = "SampledFrom"
window_end = "SampledTo"
status = "Status"
revision = "Rev"
reported_time = "Authorised"
lab_id = "Lab"
moisture = {{ column = "{MOISTURE_COLUMN}", unit = "%" }}
bulk_density = {{ column = "{DENSITY_COLUMN}", unit = "kg/m3" }}

[lab]
id = "lab1"

[status]
P = "PROVISIONAL"
F = "FINAL"
A = "FINAL"

[analytes]
""" + "".join(f'{name} = {{ column = "{column}", unit = "{unit}", '
              f'repeatability = {_stated_in_column_unit(name, factor)} }}\n'
              for name, (column, unit, factor) in ANALYTE_COLUMNS.items())


def write_map(path: str | Path) -> Path:
    """Write :data:`MAP_TOML` to ``path``; return it."""
    path = Path(path)
    path.write_text(MAP_TOML, encoding="utf-8")
    return path


def local_time(t_ns: int, tz: ZoneInfo) -> str:
    """UTC ns as local time in ``tz`` without an offset: ``2026-11-22 14:03:27.5`` (the
    fraction to the nanosecond, trailing zeros dropped, none when whole)."""
    seconds, frac = divmod(int(t_ns), NS_PER_S)
    moment = datetime.fromtimestamp(seconds, tz=timezone.utc).astimezone(tz)
    text = moment.strftime("%Y-%m-%d %H:%M:%S")
    return f"{text}.{frac:09d}".rstrip("0") if frac else text


def decimal_comma(value: float, factor: Decimal = Decimal(1)) -> str:
    """``value * factor`` in plain decimal notation with a decimal comma, from the shortest
    decimal that reads back as ``value`` (``0.083`` ppm-scaled -> ``830,000``)."""
    number = Decimal(repr(float(value))) * factor
    return format(number, "f").replace(".", ",")


class LimsDropWriter:
    """Writes the simulated laboratory's report batches as LIMS CSV files into ``directory``.

    Parameters
    ----------
    directory : path
        The drop folder ``stockpile service lab --watch`` reads (created if missing).
    prefix : str
        File names are ``<prefix>-<UTC time of the batch>-<n>.csv``.
    """

    def __init__(self, directory: str | Path, *, prefix: str = "lims") -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.prefix = prefix
        self.tz = ZoneInfo(TIMEZONE)
        self.files = 0
        #: simulator assay id -> (sample id, revision) as written
        self.samples: dict[str, tuple[str, int]] = {}
        #: simulator assay id -> the assay id the adapter publishes
        self.assay_ids: dict[str, str] = {}

    def _sample_of(self, r: LabResult) -> tuple[str, int]:
        """The sample id and revision a result is written as: a result that supersedes one
        this writer wrote is that sample's next revision."""
        if r.supersedes:
            sample, revision = self.samples.get(r.supersedes, (r.supersedes, 0))
            return sample, revision + 1
        return r.assay_id, 0

    def row(self, r: LabResult) -> list[str]:
        """The fields of one result, in header order (records its sample and revision)."""
        sample, revision = self._sample_of(r)
        self.samples[r.assay_id] = (sample, revision)
        self.assay_ids[r.assay_id] = assay_id_for(sample, revision)
        fields = [sample, r.lot_id, local_time(r.window_start_ns, self.tz),
                  local_time(r.window_end_ns, self.tz), STATUS_CODES[r.status], str(revision),
                  local_time(r.reported_ns, self.tz), r.lab_id]
        fields += [decimal_comma(r.analytes_pct[a], factor) if a in r.analytes_pct else ""
                   for a, (_c, _u, factor) in ANALYTE_COLUMNS.items()]
        fields += [decimal_comma(r.moisture_pct), decimal_comma(r.bulk_density_t_m3,
                                                                Decimal(1000))]
        return fields

    def header(self) -> list[str]:
        return [*COLUMNS, *(c for c, _u, _f in ANALYTE_COLUMNS.values()), MOISTURE_COLUMN,
                DENSITY_COLUMN]

    def write(self, t_ns: int, results: Iterable[LabResult]) -> Path | None:
        """Write one report batch, exported at site time ``t_ns`` (UTC ns), as one file;
        return its path (None for an empty batch).  The file appears whole: it is written
        under a hidden temporary name, fsynced and renamed."""
        results = list(results)
        if not results:
            return None
        unknown = sorted({a for r in results for a in r.analytes_pct} - set(ANALYTES))
        if unknown:
            raise ValueError(f"no LIMS column for analyte {unknown[0]!r}")
        buffer = io.StringIO()
        writer = csv.writer(buffer, delimiter=";", lineterminator="\r\n")
        writer.writerow([TITLE, results[0].lab_id, local_time(t_ns, self.tz)])
        writer.writerow(self.header())
        writer.writerows(self.row(r) for r in results)
        stamp = datetime.fromtimestamp(t_ns // NS_PER_S, tz=timezone.utc).strftime(
            "%Y%m%dT%H%M%SZ")
        while True:  # a name no earlier batch took (a writer restarted in the same second)
            self.files += 1
            name = f"{self.prefix}-{stamp}-{self.files:05d}.csv"
            final, temp = self.directory / name, self.directory / f".{name}.tmp"
            if not final.exists():
                break
        with open(temp, "w", encoding="utf-8", newline="") as out:
            out.write(buffer.getvalue())
            out.flush()
            os.fsync(out.fileno())
        os.replace(temp, final)
        return final

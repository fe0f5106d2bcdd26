"""Drone surveys of the simulated yard: point clouds of the true surface, written as LAZ.

A yard surveys its stockpiles from the air (drone photogrammetry): a dense cloud of
points on the surface, in the mine grid.  This module makes such a cloud from the world's
true surface (:class:`sim.world.World`) and writes it as a LAS 1.4 / LAZ file, so that a
survey import and a reconciliation against the ledger can be tested on a surface whose
truth is known.  (This is not the scanner's survey pass after stacking, which
:mod:`sim.timetable` plans.)

- :func:`survey_points` samples points uniformly over the survey's footprint
  (:func:`survey_footprint`: the world's grid and a margin of flat ground around it) at a
  density, heights from the true surface, with Gaussian noise added; :func:`survey_chunks`
  yields the same survey in chunks of bounded size;
- :func:`write_laz` streams site-frame chunks into a LAZ file in the mine grid (one chunk
  in memory at a time) and returns the point count and bounding box;
- :func:`write_survey` writes one survey of a surface: ``survey-<YYYYmmddTHHMMSSZ>.laz``,
  its truth sidecar ``.json`` (time, seed, noise, CRS, the true volume above the ground
  over the footprint) and the true surface grid ``.truth.npz``;
- :class:`DroneSurveys` is the list of surveys a run takes (``stockpile sim --survey-at``):
  :class:`sim.runner.Simulation` hands it the world as site time passes.

Heights are **per cell**: a point takes the height of the world's column it falls in (the
world's surface is its columns' flat tops), and the flat ground (``Grid.ground_z_m``)
outside the grid.  So the mean height above the ground of the points times the footprint's
area is an unbiased estimate of exactly :func:`true_volume_m3`.  Noise: each point is
drawn at a true position (x0, y0) and height z0 = surface(x0, y0); the file holds
(x0 + ex, y0 + ey, z0 + ez), ex and ey ~ N(0, ``sd_horizontal_m``), ez ~ N(0,
``sd_vertical_m``).  Defaults are those of drone photogrammetry: 20 points/m2, 0.03 m
vertical and 0.02 m horizontal sd.

The file: point format 6, 1 mm scale (0.001), offsets the first chunk's smallest
coordinates rounded down to whole kilometres, the CRS as an OGC WKT VLR (laspy's
``add_crs``; the WKT bit of the global encoding set), the survey time as adjusted
standard GPS time on every point, return 1 of 1 and classification 0 (never classified).
Coordinates are the mine grid's (:class:`geo.site_crs.SiteCrs`): easting, northing and the
*ellipsoidal* height on the CRS's datum (not an RL).  Site frame = the local ENU tangent
plane at the scenario's datum (m).
"""

from __future__ import annotations

import itertools
import json
import math
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Iterable, Iterator, NamedTuple, Sequence

import numpy as np

from geo.site_crs import SiteCrs
from schemas.times import NS_PER_S, format_time_ns
from sim.grid import Grid
from sim.rng import check_rng, named_rng
from sim.scenario import Scenario

__all__ = ["DEFAULT_CHUNK_POINTS", "DEFAULT_DENSITY_PER_M2", "DEFAULT_MARGIN_M",
           "DEFAULT_SD_HORIZONTAL_M", "DEFAULT_SD_VERTICAL_M", "DroneSurveys", "Footprint",
           "LAZ_SCALE_M", "LazSummary", "gps_adjusted_time_s", "site_crs_of", "survey_chunks",
           "survey_footprint", "survey_point_count", "survey_points", "survey_stem",
           "surface_heights_m", "true_volume_m3", "write_laz", "write_survey"]

#: drone photogrammetry: points per square metre of ground
DEFAULT_DENSITY_PER_M2 = 20.0
#: the points' height noise, standard deviation (m)
DEFAULT_SD_VERTICAL_M = 0.03
#: the points' position noise per horizontal axis, standard deviation (m)
DEFAULT_SD_HORIZONTAL_M = 0.02
#: flat ground surveyed around the world's grid (m)
DEFAULT_MARGIN_M = 5.0
#: points per chunk: what :func:`survey_chunks` draws and :func:`write_laz` converts at once
DEFAULT_CHUNK_POINTS = 500_000
#: the LAZ file's coordinate resolution (m)
LAZ_SCALE_M = 0.001
#: LAS 1.4 point format: x, y, z, intensity, returns, classification, GPS time (30 bytes)
POINT_FORMAT = 6
#: offsets are whole multiples of this (m)
OFFSET_STEP_M = 1000.0
#: GPS time 0 (1980-01-06T00:00:00Z) in Unix seconds, and GPS - UTC since 2017-01-01 (s)
GPS_EPOCH_UNIX_S = 315_964_800
GPS_MINUS_UTC_S = 18
#: adjusted standard GPS time is GPS seconds minus this (LAS 1.4)
GPS_ADJUSTMENT_S = 1_000_000_000
#: int32, the LAS integer coordinates' range
_INT32_MAX = 2**31 - 1


# -- the survey's points -----------------------------------------------------------------------

@dataclass(frozen=True)
class Footprint:
    """The rectangle a survey covers, site frame (m)."""

    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float

    @property
    def area_m2(self) -> float:
        return (self.x_max_m - self.x_min_m) * (self.y_max_m - self.y_min_m)

    def to_dict(self) -> dict:
        return {"x_min_m": self.x_min_m, "x_max_m": self.x_max_m, "y_min_m": self.y_min_m,
                "y_max_m": self.y_max_m, "area_m2": self.area_m2}


def survey_footprint(grid: Grid, margin_m: float = DEFAULT_MARGIN_M) -> Footprint:
    """The grid's outer edges widened by ``margin_m`` of flat ground on every side (m)."""
    margin = _non_negative(margin_m, "margin_m")
    x_min, x_max, y_min, y_max = grid.extent
    return Footprint(x_min - margin, x_max + margin, y_min - margin, y_max + margin)


def survey_point_count(footprint: Footprint, density_per_m2: float) -> int:
    """Points of a survey: ``density_per_m2`` x the footprint's area, rounded."""
    density = _positive(density_per_m2, "density_per_m2")
    return int(round(density * footprint.area_m2))


def surface_heights_m(surface_z_m: np.ndarray, grid: Grid, x_m, y_m) -> np.ndarray:
    """The surface's height at site points (m): the top of the column each point falls in,
    ``grid.ground_z_m`` off the grid.

    Parameters
    ----------
    surface_z_m : ndarray, shape (ny, nx)
        Column tops over ``grid`` (m).
    grid : Grid
        The grid the surface lives on.
    x_m, y_m : array_like
        Site-frame positions (m), of one shape.
    """
    surface = _check_surface(surface_z_m, grid)
    x, y = np.asarray(x_m, np.float64), np.asarray(y_m, np.float64)
    if x.shape != y.shape:
        raise ValueError(f"x_m and y_m differ in shape: {x.shape} and {y.shape}")
    iy, ix = grid.index_of(x, y)
    inside = (iy >= 0) & (iy < grid.ny) & (ix >= 0) & (ix < grid.nx)
    z = np.full(x.shape, grid.ground_z_m, np.float64)
    z[inside] = surface[iy[inside], ix[inside]]
    return z


def survey_points(surface_z_m: np.ndarray, grid: Grid, rng: np.random.Generator, *,
                  density_per_m2: float = DEFAULT_DENSITY_PER_M2,
                  sd_vertical_m: float = DEFAULT_SD_VERTICAL_M,
                  sd_horizontal_m: float = DEFAULT_SD_HORIZONTAL_M,
                  margin_m: float = DEFAULT_MARGIN_M,
                  n_points: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A drone survey's points on the surface, site frame (m).

    Positions are uniform over :func:`survey_footprint`; heights per cell
    (:func:`surface_heights_m`); then the noise (see the module docstring).  Draws, in
    this order: x0, y0 (uniform), ez, ex, ey (standard normal, scaled), whatever the sds,
    so one generator state gives the same true points at any noise.

    Parameters
    ----------
    surface_z_m : ndarray, shape (ny, nx)
        The true surface over ``grid`` (m).
    grid : Grid
        Its grid (origin, cell size, and the ground's height off the grid).
    rng : numpy.random.Generator
        The survey's random stream.
    density_per_m2 : float
        Points per square metre of footprint (> 0).
    sd_vertical_m, sd_horizontal_m : float
        Noise standard deviations (m, >= 0): height, and each horizontal axis.
    margin_m : float
        Flat ground surveyed around the grid (m, >= 0).
    n_points : int, optional
        Draw this many points instead of ``density_per_m2`` x the footprint's area.

    Returns
    -------
    x_m, y_m, z_m : ndarray, shape (n,)
        Site-frame coordinates of the points (m).
    """
    surface = _check_surface(surface_z_m, grid)
    rng = check_rng(rng)
    sd_v = _non_negative(sd_vertical_m, "sd_vertical_m")
    sd_h = _non_negative(sd_horizontal_m, "sd_horizontal_m")
    footprint = survey_footprint(grid, margin_m)
    n = survey_point_count(footprint, density_per_m2) if n_points is None else n_points
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ValueError(f"n_points must be an integer >= 0, got {n_points!r}")
    x0 = rng.uniform(footprint.x_min_m, footprint.x_max_m, n)
    y0 = rng.uniform(footprint.y_min_m, footprint.y_max_m, n)
    z = surface_heights_m(surface, grid, x0, y0)
    z += sd_v * rng.standard_normal(n)
    x0 += sd_h * rng.standard_normal(n)
    y0 += sd_h * rng.standard_normal(n)
    return x0, y0, z


def survey_chunks(surface_z_m: np.ndarray, grid: Grid, rng: np.random.Generator, *,
                  density_per_m2: float = DEFAULT_DENSITY_PER_M2,
                  sd_vertical_m: float = DEFAULT_SD_VERTICAL_M,
                  sd_horizontal_m: float = DEFAULT_SD_HORIZONTAL_M,
                  margin_m: float = DEFAULT_MARGIN_M,
                  chunk_points: int = DEFAULT_CHUNK_POINTS,
                  ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """One survey (:func:`survey_points`' arguments) as chunks of at most ``chunk_points``
    points, each uniform over the whole footprint, together ``density_per_m2`` x its area.

    The arguments are checked on the call, before the first chunk is drawn.
    """
    _check_surface(surface_z_m, grid)
    check_rng(rng)
    if isinstance(chunk_points, bool) or not isinstance(chunk_points, (int, np.integer)) \
            or chunk_points < 1:
        raise ValueError(f"chunk_points must be an integer >= 1, got {chunk_points!r}")
    total = survey_point_count(survey_footprint(grid, margin_m), density_per_m2)
    noise = {"sd_vertical_m": sd_vertical_m, "sd_horizontal_m": sd_horizontal_m}
    for name, value in noise.items():
        _non_negative(value, name)

    def chunks():
        for start in range(0, total, chunk_points):
            yield survey_points(surface_z_m, grid, rng, margin_m=margin_m,
                                n_points=min(chunk_points, total - start), **noise)
    return chunks()


def true_volume_m3(surface_z_m: np.ndarray, grid: Grid) -> float:
    """Volume above the ground (``grid.ground_z_m``) under the per-cell surface (m3); the
    flat ground around the grid adds nothing."""
    surface = _check_surface(surface_z_m, grid)
    return float(np.clip(surface - grid.ground_z_m, 0.0, None).sum() * grid.cell_area_m2)


# -- the LAZ file --------------------------------------------------------------------------------

class LazSummary(NamedTuple):
    """What :func:`write_laz` wrote: the point count and the bounding box of the stored
    (1 mm) coordinates, mine grid (easting, northing, ellipsoidal height; m)."""

    point_count: int
    bbox_min_m: tuple[float, float, float]
    bbox_max_m: tuple[float, float, float]


def gps_adjusted_time_s(time_ns: int) -> float:
    """UTC ns -> adjusted standard GPS time (GPS seconds - 1e9), LAS 1.4's point time;
    GPS - UTC is taken as 18 s (right from 2017-01-01)."""
    unix_s = int(time_ns) / NS_PER_S
    return unix_s - GPS_EPOCH_UNIX_S + GPS_MINUS_UTC_S - GPS_ADJUSTMENT_S


def write_laz(path: str | Path,
              points_chunks: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]],
              site_crs: SiteCrs, *, time_ns: int | None = None,
              offset_m: Sequence[float] | None = None,
              scale_m: float = LAZ_SCALE_M) -> LazSummary:
    """Stream site-frame points into a LAZ file in the mine grid, chunk by chunk.

    Each chunk goes through ``site_crs.to_grid`` and is quantised, compressed (laspy's
    single-threaded lazrs backend) and written before the next is read: memory stays
    bounded by the chunk size.  The file is written under ``<path>.part`` and renamed when
    complete.

    Parameters
    ----------
    path : str or Path
        The file to write (``.laz``).
    points_chunks : iterable of (x_m, y_m, z_m)
        Site-frame chunks: three finite 1-D float arrays of one length each (m).
    site_crs : SiteCrs
        The site's datum and mine-grid CRS, recorded in the header (WKT).
    time_ns : int, optional
        The survey's time (UTC ns): every point's GPS time and the file's creation date.
    offset_m : sequence of 3 floats, optional
        The header's (E, N, h) offsets (m); default: the first non-empty chunk's smallest
        grid coordinates rounded down to a whole :data:`OFFSET_STEP_M`.
    scale_m : float
        The coordinates' resolution (m), all three axes.

    Returns
    -------
    LazSummary
        The point count and the bounding box of the written coordinates.

    Raises
    ------
    ValueError
        A malformed chunk, a point outside the CRS's area, or coordinates beyond the
        int32 range of ``scale_m`` about the offsets.
    """
    import laspy

    path = Path(path)
    scale = _positive(scale_m, "scale_m")
    if not isinstance(site_crs, SiteCrs):
        raise ValueError(f"site_crs must be a geo.site_crs.SiteCrs, got {type(site_crs).__name__}")
    grid_chunks = _grid_chunks(points_chunks, site_crs)
    first = next(grid_chunks, None)
    offsets = _offsets(first, offset_m)
    chunks = iter(()) if first is None else itertools.chain([first], grid_chunks)
    del first   # the chain holds it only until it is written
    header = _laz_header(site_crs, offsets, scale, time_ns)
    gps_time_s = None if time_ns is None else gps_adjusted_time_s(time_ns)
    part = path.with_name(path.name + ".part")
    count, lo, hi = 0, np.full(3, _INT32_MAX, np.int64), np.full(3, -_INT32_MAX - 1, np.int64)
    try:
        with laspy.open(part, mode="w", header=header, do_compress=True,
                        laz_backend=laspy.LazBackend.Lazrs) as writer:
            for chunk in chunks:
                record = _point_record(header, chunk, offsets, scale, gps_time_s)
                del chunk
                for axis, name in enumerate("XYZ"):
                    lo[axis] = min(lo[axis], record[name].min())
                    hi[axis] = max(hi[axis], record[name].max())
                writer.write_points(record)
                count += len(record)
                del record   # before the next chunk is drawn
        os.replace(part, path)
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    if count == 0:
        return LazSummary(0, (math.nan,) * 3, (math.nan,) * 3)
    # whole millimetres: rounding drops the float sum's sub-nanometre error
    return LazSummary(count, tuple(round(float(v), 9) for v in lo * scale + offsets),
                      tuple(round(float(v), 9) for v in hi * scale + offsets))


def _laz_header(site_crs: SiteCrs, offsets: np.ndarray, scale_m: float, time_ns: int | None):
    """A LAS 1.4 point-format-6 header with the scale, offsets, CRS (WKT) and GPS time type."""
    import laspy
    from laspy.header import GpsTimeType

    header = laspy.LasHeader(version="1.4", point_format=POINT_FORMAT)
    header.scales = np.full(3, scale_m)
    header.offsets = offsets
    header.add_crs(site_crs.crs)
    header.global_encoding.gps_time_type = GpsTimeType.STANDARD
    header.system_identifier = "stockpile sim (drone survey)"
    header.generating_software = "stockpile-ledger sim.survey"
    if time_ns is not None:
        header.creation_date = _utc(time_ns).date()
    return header


def _point_record(header, grid_chunk, offsets: np.ndarray, scale_m: float,
                  gps_time_s: float | None):
    """One chunk of mine-grid coordinates as a point record of ``header``'s format."""
    import laspy

    ints = []
    for axis, values in enumerate(grid_chunk):
        q = values - offsets[axis]
        q /= scale_m
        np.round(q, out=q)
        if q.size and (q.min() < -_INT32_MAX - 1 or q.max() > _INT32_MAX):
            raise ValueError(f"coordinates beyond the int32 range of a {scale_m} m scale "
                             f"about the offset {offsets[axis]} m (axis {axis})")
        ints.append(q.astype(np.int32))
        del q
    n = len(ints[0])
    record = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    record.X, record.Y, record.Z = ints
    record.return_number = np.ones(n, np.uint8)
    record.number_of_returns = np.ones(n, np.uint8)
    if gps_time_s is not None:
        record.gps_time = np.full(n, gps_time_s)
    return record


def _grid_chunks(points_chunks, site_crs: SiteCrs):
    """The non-empty chunks in the mine grid, one at a time: no reference to a chunk is
    kept while the next one is drawn and converted."""
    for k, chunk in enumerate(points_chunks):
        x, y, z = _check_chunk(chunk, k)
        del chunk
        grid_chunk = site_crs.to_grid(x, y, z)
        del x, y, z
        if grid_chunk[0].size:
            yield grid_chunk
        del grid_chunk


def _offsets(first_grid_chunk, offset_m) -> np.ndarray:
    if offset_m is not None:
        offsets = np.asarray(offset_m, np.float64)
        if offsets.shape != (3,) or not np.all(np.isfinite(offsets)):
            raise ValueError(f"offset_m must be 3 finite numbers, got {offset_m!r}")
        return offsets
    if first_grid_chunk is None:
        return np.zeros(3)
    return np.array([math.floor(float(v.min()) / OFFSET_STEP_M) * OFFSET_STEP_M
                     for v in first_grid_chunk])


def _check_chunk(chunk, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not isinstance(chunk, (tuple, list)) or len(chunk) != 3:
        raise ValueError(f"chunk {k} must be (x_m, y_m, z_m)")
    arrays = tuple(np.asarray(v, np.float64) for v in chunk)
    if any(a.ndim != 1 for a in arrays) or len({a.shape for a in arrays}) != 1:
        raise ValueError(f"chunk {k}: x_m, y_m, z_m must be 1-D arrays of one length, got "
                         f"shapes {[a.shape for a in arrays]}")
    return arrays  # type: ignore[return-value]


# -- one survey, and a run's surveys ------------------------------------------------------------

def survey_stem(time_ns: int) -> str:
    """``survey-<YYYYmmddTHHMMSSZ>``: a survey's file name without suffix (whole seconds)."""
    return "survey-" + _utc(time_ns).strftime("%Y%m%dT%H%M%SZ")


def site_crs_of(scenario: Scenario) -> SiteCrs:
    """The scenario's datum and mine-grid CRS (``crs_epsg``)."""
    return SiteCrs(scenario.datum_lat_deg, scenario.datum_lon_deg, scenario.datum_alt_m,
                   int(scenario.crs_epsg))


def write_survey(out_dir: str | Path, surface_z_m: np.ndarray, grid: Grid, site_crs: SiteCrs,
                 time_ns: int, seed: int, *,
                 density_per_m2: float = DEFAULT_DENSITY_PER_M2,
                 sd_vertical_m: float = DEFAULT_SD_VERTICAL_M,
                 sd_horizontal_m: float = DEFAULT_SD_HORIZONTAL_M,
                 margin_m: float = DEFAULT_MARGIN_M,
                 chunk_points: int = DEFAULT_CHUNK_POINTS, about: dict | None = None) -> dict:
    """Survey ``surface_z_m`` at ``time_ns`` into ``out_dir``; returns the sidecar.

    Writes ``<stem>.laz`` (:func:`write_laz`), ``<stem>.truth.npz`` (the true surface:
    ``surface_z_m``, ``x_centres_m``, ``y_centres_m``, ``ground_z_m``) and last
    ``<stem>.json``, the sidecar: time, seed and random stream, point count, density,
    noise, CRS and datum, footprint, ``true_volume_m3`` above ``grid.ground_z_m``, the
    grid, the file's bounding box, and ``about`` (for example the scenario).  The points
    come from ``named_rng(seed, "drone-survey@<time_ns>")``.
    """
    out = Path(out_dir)
    stem = survey_stem(time_ns)
    stream = f"drone-survey@{int(time_ns)}"
    noise = {"sd_vertical_m": float(sd_vertical_m), "sd_horizontal_m": float(sd_horizontal_m)}
    chunks = survey_chunks(surface_z_m, grid, named_rng(int(seed), stream),
                           density_per_m2=density_per_m2, margin_m=margin_m,
                           chunk_points=chunk_points, **noise)
    written = write_laz(out / f"{stem}.laz", chunks, site_crs, time_ns=time_ns)
    np.savez_compressed(out / f"{stem}.truth.npz", surface_z_m=np.asarray(surface_z_m),
                        x_centres_m=grid.x_centres, y_centres_m=grid.y_centres,
                        ground_z_m=np.float64(grid.ground_z_m))
    footprint = survey_footprint(grid, margin_m)
    sidecar = {
        "time": format_time_ns(time_ns), "time_ns": int(time_ns), "seed": int(seed),
        "rng_stream": stream, "point_count": written.point_count,
        "density_per_m2": float(density_per_m2), **noise, "heights": "per_cell",
        "epsg": int(site_crs.epsg), "crs_name": site_crs.crs.name,
        "z": "ellipsoidal height on the CRS's datum (m), not an RL",
        "datum": {"lat_deg": site_crs.datum_lat_deg, "lon_deg": site_crs.datum_lon_deg,
                  "alt_m": site_crs.datum_alt_m},
        "ground_z_m": float(grid.ground_z_m),
        "true_volume_m3": true_volume_m3(surface_z_m, grid),
        "footprint_site_m": footprint.to_dict(), "margin_m": float(margin_m),
        "grid": grid.to_dict(),
        "bbox_grid_m": {"min": list(written.bbox_min_m), "max": list(written.bbox_max_m)},
        "laz": f"{stem}.laz", "truth_npz": f"{stem}.truth.npz", **(about or {}),
    }
    (out / f"{stem}.json").write_text(json.dumps(sidecar, indent=1, sort_keys=True))
    return sidecar


@dataclass
class DroneSurveys:
    """The drone surveys a run takes (``stockpile sim --survey-at``).

    The run calls :meth:`take_due` with the time of each event before handling it, and
    once with the run's end + 1 ns: a survey at T sees the world after everything at or
    before T.  Taking one draws only from the survey's own stream (:func:`write_survey`)
    and writes only its own files.

    Parameters
    ----------
    times_ns : sequence of int
        The surveys' site times (UTC ns); two in one second would share a file name.
    out_dir : Path
        Where the files go.
    scenario : Scenario
        The run's scenario (its datum, CRS and names).
    seed : int
        The surveys' seed.
    density_per_m2 : float
        Points per square metre (> 0).
    report : callable, optional
        Called with one line per survey written.
    """

    times_ns: Sequence[int]
    out_dir: Path
    scenario: Scenario
    seed: int
    density_per_m2: float = DEFAULT_DENSITY_PER_M2
    report: Callable[[str], None] | None = None
    #: the sidecars of the surveys written so far
    written: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.pending = sorted(int(t) for t in self.times_ns)
        stems = [survey_stem(t) for t in self.pending]
        if len(set(stems)) != len(stems):
            raise ValueError("two surveys in one second of site time (one file name)")
        _positive(self.density_per_m2, "density_per_m2")
        self.site_crs = site_crs_of(self.scenario)

    def take_due(self, before_ns: int, world) -> None:
        """Survey ``world``'s surface for every pending time before ``before_ns``."""
        while self.pending and self.pending[0] < before_ns:
            t = self.pending.pop(0)
            sc = self.scenario
            sidecar = write_survey(self.out_dir, world.surface_z(), world.grid, self.site_crs,
                                   t, self.seed, density_per_m2=self.density_per_m2,
                                   about={"scenario": sc.name, "site_id": sc.site_id,
                                          "pile_id": sc.pile_id})
            self.written.append(sidecar)
            if self.report is not None:
                self.report(_survey_line(sidecar, self.out_dir))


def _survey_line(sidecar: dict, out_dir: Path) -> str:
    area = sidecar["footprint_site_m"]["area_m2"]
    return (f"survey {sidecar['time']}: {sidecar['point_count']:,} points "
            f"({sidecar['density_per_m2']:g}/m2 over {area:,.0f} m2, EPSG:{sidecar['epsg']}), "
            f"true volume {sidecar['true_volume_m3']:,.3f} m3 -> {Path(out_dir) / sidecar['laz']}")


# -- argument checks ------------------------------------------------------------

def _check_surface(surface_z_m, grid: Grid) -> np.ndarray:
    if not isinstance(grid, Grid):
        raise ValueError(f"grid must be a sim.grid.Grid, got {type(grid).__name__}")
    surface = np.asarray(surface_z_m, np.float64)
    if surface.shape != grid.shape:
        raise ValueError(f"surface_z_m has shape {surface.shape}, the grid {grid.shape}")
    if not np.all(np.isfinite(surface)):
        raise ValueError("surface_z_m must be finite")
    return surface


def _positive(value, name: str) -> float:
    v = _number(value, name)
    if not v > 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return v


def _non_negative(value, name: str) -> float:
    v = _number(value, name)
    if not v >= 0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return v


def _number(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def _utc(time_ns: int) -> datetime:
    return datetime.fromtimestamp(int(time_ns) // NS_PER_S, timezone.utc)

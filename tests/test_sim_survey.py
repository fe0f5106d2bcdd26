"""The simulator's drone surveys (sim/survey.py, ``stockpile sim --survey-at``): real LAZ
files read back with laspy, their CRS, point count and heights against the world's truth,
the streaming writer's memory, and a run whose events do not change."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import laspy
import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from geo.site_crs import SiteCrs
from schemas.times import parse_time_ns
from sim.grid import Grid
from sim.survey import (DEFAULT_DENSITY_PER_M2, DEFAULT_MARGIN_M, DEFAULT_SD_HORIZONTAL_M,
                        DEFAULT_SD_VERTICAL_M, gps_adjusted_time_s, survey_chunks,
                        survey_footprint, survey_points, write_laz)

#: the short run the projector tests use (tests/conftest.py small_yard_sim): one pass,
#: 00:05-00:10 site time, its last chunk of material lands at 00:10:00
RUN = ["--scenario", "demo", "--seed", "2", "--duration", "0.19h", "--speed", "0"]
MID_PASS, AFTER_PASS = "2026-11-01T00:07:30Z", "2026-11-01T00:10:30Z"
STEMS = {MID_PASS: "survey-20261101T000730Z", AFTER_PASS: "survey-20261101T001030Z"}


def _sim(out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "stockpile.cli", "sim", *RUN, "--out",
                           str(out), *extra], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def runs(tmp_path_factory, seed):
    """The short run twice, without and with two surveys (their points from the test
    run's seed); returns (plain dir, surveyed dir, the surveyed run's stdout)."""
    base = tmp_path_factory.mktemp("surveys")
    plain = _sim(base / "plain")
    surveyed = _sim(base / "surveyed", "--survey-at", MID_PASS, "--survey-at", AFTER_PASS,
                    "--survey-seed", str(seed))
    assert plain.returncode == 0, plain.stderr
    assert surveyed.returncode == 0, surveyed.stderr
    return base / "plain", base / "surveyed", surveyed.stdout


def _sidecar(out: Path, at: str) -> dict:
    return json.loads((out / f"{STEMS[at]}.json").read_text())


def _site_points(out: Path, at: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The survey's points read back and taken to the site frame (m)."""
    side = _sidecar(out, at)
    las = laspy.read(out / side["laz"])
    datum = side["datum"]
    crs = SiteCrs(datum["lat_deg"], datum["lon_deg"], datum["alt_m"], side["epsg"])
    return crs.to_site(np.asarray(las.x), np.asarray(las.y), np.asarray(las.z))


def _truth_grid(out: Path) -> Grid:
    return Grid(**json.loads((out / "truth.json").read_text())["world"]["grid"])


# -- the run ------------------------------------------------------------------------------------

def test_a_survey_changes_no_other_output(runs):
    plain, surveyed, stdout = runs
    for name in ("events.jsonl", "lms200.bin", "gnss.nmea"):
        a, b = (plain / name).read_bytes(), (surveyed / name).read_bytes()
        assert a and a == b, name
    truths = [json.loads((d / "truth.json").read_text()) for d in (plain, surveyed)]
    for truth in truths:   # wall-clock figures differ run to run
        for key in ("wall_s", "fast_forward_wall_s", "live_late_s", "max_lag_s"):
            truth["stats"].pop(key)
    assert truths[0] == truths[1]
    npz = [np.load(d / "truth.npz") for d in (plain, surveyed)]
    assert sorted(npz[0].files) == sorted(npz[1].files)
    for key in npz[0].files:
        assert np.array_equal(npz[0][key], npz[1][key]), key
    lines = [line for line in stdout.splitlines() if line.startswith("survey ")]
    assert len(lines) == 2
    for line, (at, stem) in zip(lines, STEMS.items()):
        assert line.startswith(f"survey {at}: ") and line.endswith(f"{stem}.laz")
    assert not list(plain.glob("survey-*"))
    assert not list(surveyed.glob("*.part"))


def test_the_header_names_epsg_7850(runs):
    _, surveyed, _ = runs
    side = _sidecar(surveyed, AFTER_PASS)
    with laspy.open(surveyed / side["laz"]) as reader:
        header = reader.header
        assert header.are_points_compressed
    assert (str(header.version), header.point_format.id) == ("1.4", 6)
    assert header.global_encoding.wkt
    crs = header.parse_crs()
    assert crs is not None and crs.to_epsg() == 7850 == side["epsg"]
    assert np.allclose(header.scales, 0.001)
    assert np.all(np.mod(header.offsets, 1000.0) == 0)
    assert str(header.creation_date) == "2026-11-01"
    las = laspy.read(surveyed / side["laz"])
    assert np.all(las.gps_time == gps_adjusted_time_s(parse_time_ns(AFTER_PASS)))
    assert np.all(np.asarray(las.return_number) == 1)
    # the bounding box the writer returned is the file's
    assert np.allclose(side["bbox_grid_m"]["min"], header.mins, rtol=0, atol=1e-6)
    assert np.allclose(side["bbox_grid_m"]["max"], header.maxs, rtol=0, atol=1e-6)


def test_the_point_count_is_density_times_area(runs):
    _, surveyed, _ = runs
    grid = _truth_grid(surveyed)
    x_min, x_max, y_min, y_max = grid.extent
    area_m2 = (x_max - x_min + 2 * DEFAULT_MARGIN_M) * (y_max - y_min + 2 * DEFAULT_MARGIN_M)
    for at in STEMS:
        side = _sidecar(surveyed, at)
        count = laspy.read(surveyed / side["laz"]).header.point_count
        assert count == side["point_count"]
        assert abs(count / (DEFAULT_DENSITY_PER_M2 * area_m2) - 1) < 0.02, (at, count)
        assert side["footprint_site_m"]["area_m2"] == pytest.approx(area_m2)


def _truth_heights(out: Path, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """From the run's truth.npz: the top of the cell each point is in (found by bisecting
    the cell edges; the ground off the grid), and whether that cell and its eight
    neighbours are level (there a point's position noise cannot change its height)."""
    truth = np.load(out / "truth.npz")
    grid = _truth_grid(out)
    half = grid.cell_m / 2
    columns = []
    for centres, v in ((truth["x_centres"], x), (truth["y_centres"], y)):
        edges = np.r_[centres - half, centres[-1] + half]
        # 0: before the grid, 1..n: its cells, n + 1: after it (the padded surface's index)
        columns.append(np.clip(np.searchsorted(edges, v, side="right"), 0, len(centres) + 1))
    ix, iy = columns
    padded = np.pad(truth["surface_z"], 1, constant_values=grid.ground_z_m)
    windows = sliding_window_view(np.pad(padded, 1, mode="edge"), (3, 3))
    level = np.ptp(windows, axis=(2, 3)) < 1e-9
    return padded[iy, ix], level[iy, ix]


def test_the_points_lie_on_the_true_surface_within_the_noise(runs):
    _, surveyed, _ = runs
    x, y, z = _site_points(surveyed, AFTER_PASS)
    expected, level = _truth_heights(surveyed, x, y)
    residual = z - expected
    # level ground: the height noise alone (plus 1 mm quantisation, sd 0.3 mm)
    flat = residual[level]
    assert flat.size > 50_000
    assert abs(flat.mean()) < 4 * DEFAULT_SD_VERTICAL_M / np.sqrt(flat.size)
    assert flat.std() == pytest.approx(DEFAULT_SD_VERTICAL_M, rel=0.03)
    # everywhere: unbiased; on the pile's flanks a point moved across a cell edge by its
    # position noise is compared with the neighbouring column (up to tan 37 deg x 0.25 m
    # higher or lower), which widens the tails a little
    assert abs(residual.mean()) < 4 * residual.std() / np.sqrt(residual.size)
    assert residual.std() < 1.25 * DEFAULT_SD_VERTICAL_M
    mad_sd = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    assert mad_sd == pytest.approx(DEFAULT_SD_VERTICAL_M, rel=0.05)
    assert np.mean(np.abs(residual) > 4 * DEFAULT_SD_VERTICAL_M) < 0.02


def test_the_sidecar_holds_the_true_volume_and_surface(runs):
    _, surveyed, _ = runs
    truth = json.loads((surveyed / "truth.json").read_text())
    after, mid = _sidecar(surveyed, AFTER_PASS), _sidecar(surveyed, MID_PASS)
    # nothing moves after the pass: the run's final world is the later survey's
    assert after["true_volume_m3"] == pytest.approx(truth["world"]["volume_m3"], rel=1e-9)
    assert np.array_equal(np.load(surveyed / after["truth_npz"])["surface_z_m"],
                          np.load(surveyed / "truth.npz")["surface_z"])
    # half the pass (5 of 10 chunks) by 00:07:30
    assert mid["true_volume_m3"] == pytest.approx(truth["world"]["volume_m3"] / 2, rel=1e-9)
    assert (after["time"], after["epsg"], after["heights"]) == (AFTER_PASS, 7850, "per_cell")
    assert (after["sd_vertical_m"], after["sd_horizontal_m"]) == (0.03, 0.02)
    # the points' mean height above the ground x the footprint estimates the true volume
    for side, at in ((after, AFTER_PASS), (mid, MID_PASS)):
        _, _, z = _site_points(surveyed, at)
        area_m2 = side["footprint_site_m"]["area_m2"]
        height = z - side["ground_z_m"]
        estimate_m3 = area_m2 * height.mean()
        se_m3 = area_m2 * height.std() / np.sqrt(z.size)
        assert abs(estimate_m3 - side["true_volume_m3"]) < 4 * se_m3, (at, estimate_m3)


def test_a_survey_outside_the_run_is_refused(tmp_path):
    done = _sim(tmp_path / "late", "--survey-at", "2026-11-02T00:00:00Z")
    assert done.returncode == 2
    assert "--survey-at 2026-11-02T00:00:00Z: not between the run's start" in done.stderr
    assert not (tmp_path / "late").exists()


# -- the functions ---------------------------------------------------------------------------

def _cone(grid: Grid, height_m: float = 5.0) -> np.ndarray:
    x, y = grid.centres()
    cx, cy = np.mean(grid.extent[:2]), np.mean(grid.extent[2:])
    return np.maximum(grid.ground_z_m, grid.ground_z_m + height_m
                      - np.tan(np.radians(37)) * np.hypot(x - cx, y - cy))


def test_the_noise_is_what_it_says(seed):
    grid = Grid(10.0, -5.0, 0.25, 120, 160, ground_z_m=1.5)
    surface = _cone(grid)
    exact = survey_points(surface, grid, np.random.default_rng(seed), sd_vertical_m=0.0,
                          sd_horizontal_m=0.0)
    noisy = survey_points(surface, grid, np.random.default_rng(seed))
    footprint = survey_footprint(grid)
    n = exact[0].size
    assert n == round(DEFAULT_DENSITY_PER_M2 * footprint.area_m2)
    assert np.all((exact[0] >= footprint.x_min_m) & (exact[0] <= footprint.x_max_m))
    assert np.all((exact[1] >= footprint.y_min_m) & (exact[1] <= footprint.y_max_m))
    # uniform: a tenth of the footprint holds a tenth of the points
    share = np.mean(exact[0] < footprint.x_min_m + 0.1 * (footprint.x_max_m - footprint.x_min_m))
    assert abs(share - 0.1) < 4 * np.sqrt(0.09 / n)
    # exact heights: the column tops, the ground off the grid
    x_min, x_max, y_min, y_max = grid.extent
    off = (exact[0] < x_min) | (exact[0] >= x_max) | (exact[1] < y_min) | (exact[1] >= y_max)
    assert off.any() and np.all(exact[2][off] == 1.5)
    ix = ((exact[0][~off] - x_min) // grid.cell_m).astype(int)
    iy = ((exact[1][~off] - y_min) // grid.cell_m).astype(int)
    assert np.array_equal(exact[2][~off], surface[iy, ix])
    for axis, sd in ((0, DEFAULT_SD_HORIZONTAL_M), (1, DEFAULT_SD_HORIZONTAL_M),
                     (2, DEFAULT_SD_VERTICAL_M)):
        error = noisy[axis] - exact[axis]
        assert abs(error.mean()) < 4 * sd / np.sqrt(n), axis
        assert error.std() == pytest.approx(sd, rel=0.03), axis


def test_chunks_add_up_to_one_survey(seed):
    grid = Grid(0.0, 0.0, 0.5, 40, 30)
    chunks = list(survey_chunks(_cone(grid), grid, np.random.default_rng(seed),
                                density_per_m2=50.0, chunk_points=7_000))
    sizes = [c[0].size for c in chunks]
    assert max(sizes) == 7_000 and sum(sizes) == round(50.0 * survey_footprint(grid).area_m2)


@pytest.mark.parametrize("change, message", [
    ({"surface_z_m": np.zeros((4, 4))}, "shape"),
    ({"surface_z_m": np.full((30, 40), np.nan)}, "finite"),
    ({"density_per_m2": 0.0}, "density_per_m2"),
    ({"sd_vertical_m": -0.01}, "sd_vertical_m"),
    ({"sd_horizontal_m": float("inf")}, "sd_horizontal_m"),
    ({"margin_m": -1.0}, "margin_m"),
    ({"n_points": -3}, "n_points"),
])
def test_bad_survey_arguments_are_refused(change, message):
    grid = Grid(0.0, 0.0, 0.5, 40, 30)
    args = {"surface_z_m": np.zeros(grid.shape), "grid": grid,
            "rng": np.random.default_rng(0), **change}
    with pytest.raises(ValueError, match=message):
        survey_points(**args)


def test_a_bad_chunk_leaves_no_file(tmp_path):
    crs = SiteCrs(-20.659739, 117.078497, 5.0, 7850)
    good = (np.zeros(3), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="chunk 1"):
        write_laz(tmp_path / "bad.laz", [good, (np.zeros(3), np.zeros(2), np.zeros(3))], crs)
    assert list(tmp_path.iterdir()) == []
    empty = write_laz(tmp_path / "empty.laz", [], crs)
    assert empty.point_count == 0 and laspy.read(tmp_path / "empty.laz").header.point_count == 0


#: 5 M points in chunks of 500 k, written in a fresh process that reports its peak RSS
#: over the write less its RSS before (KiB).  Linux's VmHWM of the process image, reset
#: before the write: getrusage's ru_maxrss would start from the parent's (pytest's) RSS,
#: as Linux keeps it across fork and exec
_MEMORY_SCRIPT = textwrap.dedent("""
    import json, sys
    import numpy as np
    from geo.site_crs import SiteCrs
    from sim.grid import Grid
    from sim.survey import survey_chunks, write_laz

    def status_kib(field):
        for line in open("/proc/self/status"):
            if line.startswith(field + ":"):
                return int(line.split()[1])

    seed, path = int(sys.argv[1]), sys.argv[2]
    crs = SiteCrs(-20.659739, 117.078497, 5.0, 7850)
    grid = Grid(0.0, 0.0, 0.25, 360, 360)      # 90 m square, 100 m with the margin
    x, y = grid.centres()
    surface = np.maximum(0.0, 10.0 - 0.75 * np.hypot(x - 45.0, y - 45.0))
    write_laz(path, [(np.zeros(10), np.zeros(10), np.zeros(10))], crs)   # warm PROJ, lazrs
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")                           # VmHWM := VmRSS
    before_kib = status_kib("VmRSS")
    chunks = survey_chunks(surface, grid, np.random.default_rng(seed), density_per_m2=500.0,
                           chunk_points=500_000)
    written = write_laz(path, chunks, crs)
    print(json.dumps({"points": written.point_count, "before_kib": before_kib,
                      "growth_kib": status_kib("VmHWM") - before_kib}))
""")


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="Linux /proc only")
def test_the_streaming_writer_keeps_memory_bounded(tmp_path, seed):
    path = tmp_path / "big.laz"
    done = subprocess.run([sys.executable, "-c", _MEMORY_SCRIPT, str(seed), str(path)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    growth_mib = report["growth_kib"] / 1024
    # all 5 M points at once: their site (3 x 8 B) and grid (3 x 8 B) coordinates and the
    # 30-byte records alone, no temporaries
    at_once_mib = 5_000_000 * (24 + 24 + 30) / 2**20
    print(f"seed={seed}: {report['points']:,} points in chunks of 500,000: peak RSS growth "
          f"{growth_mib:.0f} MiB (all at once >= {at_once_mib:.0f} MiB), "
          f"{path.stat().st_size / 2**20:.1f} MiB file")
    assert report["points"] == 5_000_000
    assert growth_mib < 0.4 * at_once_mib
    with laspy.open(path) as reader:
        assert reader.header.point_count == 5_000_000

"""``stockpile survey import``: a real LAZ file into a real DuckDB ledger, read back.

The LAZ files are written by the simulator's streaming writer (``sim.survey.write_laz``)
from points on a known plane over the audit tests' pile (site declared with EPSG:7850);
the survey's cells are checked against the plane at each cell's centre (the mean of a
plane over a cell is its value at the centre), its identity against hashlib and the
ledger's rules (the same file again is a duplicate, another file at the same time a
conflict).  Memory: a 3 M-point file imported in chunks takes far less than all at once,
both measured as the peak RSS of the real command in a child process.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from ledger import open_ledger
from projector import fold as F
from schemas.events import decode_payload
from schemas.times import NS_PER_S as S
from stockpile import cli
from test_audit import PILE, audit_ledger

pytest.importorskip("laspy")

from geo.site_crs import SiteCrs  # noqa: E402
from sim.survey import write_laz  # noqa: E402
from projector.surveys import survey_heights  # noqa: E402

LAT, LON, ALT, EPSG = -20.659739, 117.078497, 5.0, 7850
SITE = SiteCrs(LAT, LON, ALT, EPSG)
#: the plane the points lie on: z = A + B x + C y (m)
A, B, C = 3.0, 0.02, -0.01
TIME = "2026-11-01T05:00:00Z"


@pytest.fixture
def ledger(small_yard_sim, tmp_path_factory, tmp_path):
    source, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    path = tmp_path / "yard.duckdb"
    shutil.copy(source, path)
    return path


@pytest.fixture(scope="module")
def geometry(small_yard_sim, tmp_path_factory):
    source, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    with open_ledger(source, read_only=True) as store:
        pile = next(r for r in store.read(types=["pile_declared"])
                    if decode_payload(r.type, r.payload).pile_id == PILE)
    state = F.initial_state(PILE)
    F.apply(state, pile)
    return state.pile.geometry


def _plane_laz(path, geometry, n_points: int, seed: int, chunk: int = 500_000) -> int:
    """``n_points`` on the plane, uniform over the grid, written in chunks."""
    rng = np.random.default_rng(seed)
    print(f"survey points seed {seed}")
    x0, y0 = geometry.origin_x_m, geometry.origin_y_m
    w, h = geometry.nx * geometry.cell_m, geometry.ny * geometry.cell_m

    def chunks():
        left = n_points
        while left:
            n = min(chunk, left)
            x, y = x0 + rng.uniform(0, w, n), y0 + rng.uniform(0, h, n)
            yield x, y, A + B * x + C * y
            left -= n
    return write_laz(path, chunks(), SITE).point_count


def _survey(path):
    with open_ledger(path, read_only=True) as store:
        records = list(store.read(types=["survey"]))
    return records


def test_a_survey_is_decimated_to_the_piles_cells(ledger, geometry, tmp_path, capsys, seed):
    laz = tmp_path / "flight.laz"
    n = _plane_laz(laz, geometry, 400_000, seed)
    capsys.readouterr()
    assert cli.main(["survey", "import", str(laz), "--ledger", str(ledger), "--pile", PILE,
                     "--time", TIME, "--provider", "drone co", "--accuracy-m", "0.03",
                     "--json", "--no-progress"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["outcome"] == "appended" and out["points"] == n
    # points on the grid's very edge may leave it by the file's 1 mm quantum
    assert 0 <= n - out["points_in_grid"] < 50
    assert out["crs_epsg"] == EPSG
    assert out["sha256_hex"] == hashlib.sha256(laz.read_bytes()).hexdigest()
    (record,) = _survey(ledger)
    msg = decode_payload(record.type, record.payload)
    assert record.valid_time_ns == 1793509200 * S and record.source == "survey.import"
    assert (msg.provider, msg.accuracy_m, msg.pile_id) == ("drone co", 0.03, PILE)
    heights, counts = survey_heights(msg, geometry)
    assert counts.sum() == out["points_in_grid"]
    seen = counts > 0
    assert seen.mean() > 0.99            # 400,000 points on about 60,000 cells
    cx = geometry.origin_x_m + (np.arange(geometry.nx) + 0.5) * geometry.cell_m
    cy = geometry.origin_y_m + (np.arange(geometry.ny) + 0.5) * geometry.cell_m
    plane = A + B * cx[:, None] + C * cy[None, :]
    err = (heights - plane)[seen]
    # the mean over a cell's points is the plane at the centre, to the points' spread in
    # the cell (0.02 x 0.25 m / sqrt(12) / sqrt(count)) and the file's 1 mm quantum
    assert np.abs(err).max() < 0.01 and abs(err.mean()) < 5e-4


def test_the_same_file_again_is_a_duplicate_and_another_a_conflict(ledger, geometry, tmp_path,
                                                                 capsys, seed):
    laz, other = tmp_path / "a.laz", tmp_path / "b.laz"
    _plane_laz(laz, geometry, 50_000, seed)
    _plane_laz(other, geometry, 50_000, seed + 1)
    capsys.readouterr()
    base = ["survey", "import", "--ledger", str(ledger), "--pile", PILE, "--time", TIME,
            "--no-progress"]
    assert cli.main([*base[:2], str(laz), *base[2:]]) == 0
    assert cli.main([*base[:2], str(laz), *base[2:]]) == 0
    assert "duplicate" in capsys.readouterr().out
    assert cli.main([*base[:2], str(other), *base[2:]]) == 2
    out = capsys.readouterr().out.strip()
    assert "conflict" in out and "\n" not in out
    assert len(_survey(ledger)) == 1
    with open_ledger(ledger, read_only=True) as store:
        assert len(store.quarantine()) >= 1      # the other file, kept with its reason


def test_errors_are_one_line(ledger, geometry, tmp_path, capsys, seed):
    laz = tmp_path / "a.laz"
    _plane_laz(laz, geometry, 10_000, seed)
    capsys.readouterr()
    base = ["survey", "import", str(laz), "--ledger", str(ledger), "--time", TIME,
            "--no-progress"]
    assert cli.main([*base, "--pile", "NOPE"]) == 2
    (err,) = _errors(capsys.readouterr().err)
    assert "NOPE" in err and "not declared" in err
    assert cli.main([*base, "--pile", PILE, "--crs", "28348"]) == 2    # MGA zone 48: far away
    (err,) = _errors(capsys.readouterr().err)
    assert "no point" in err
    assert _survey(ledger) == []


def _errors(stderr: str) -> list[str]:
    """The command's error lines (not the log lines beside them)."""
    return [line for line in stderr.splitlines() if line.startswith("stockpile")]


#: runs the command in a fresh interpreter and prints its own peak RSS (VmHWM, kB): the
#: kernel's figure for a child (wait4's ru_maxrss) keeps the forking parent's peak
_RUN_AND_REPORT = (
    "import sys\n"
    "from stockpile import cli\n"
    "code = cli.main(sys.argv[1:])\n"
    "hwm = next(l for l in open('/proc/self/status') if l.startswith('VmHWM:'))\n"
    "print(hwm.split()[1], flush=True)\n"
    "sys.exit(code)\n")


def _peak_rss_mib(argv) -> float:
    done = subprocess.run([sys.executable, "-c", _RUN_AND_REPORT, *argv], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return int(done.stdout.split()[-1]) / 1024


def test_a_large_file_is_read_in_bounded_memory(small_yard_sim, tmp_path_factory, tmp_path,
                                                geometry, seed):
    source, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    laz = tmp_path / "big.laz"
    n = _plane_laz(laz, geometry, 3_000_000, seed)
    peaks = {}
    for chunk in (200_000, n):
        path = tmp_path / f"yard-{chunk}.duckdb"
        shutil.copy(source, path)
        peaks[chunk] = _peak_rss_mib(["survey", "import", str(laz), "--ledger", str(path),
                                      "--pile", PILE, "--time", TIME, "--no-progress",
                                      "--chunk-points", str(chunk)])
        assert len(_survey(path)) == 1
    print(f"peak RSS: chunks of 200,000 {peaks[200_000]:.0f} MiB, all {n:,} at once "
          f"{peaks[n]:.0f} MiB")
    # 3 M points at once hold several float64 copies (about 72 MB each set of three)
    assert peaks[200_000] < peaks[n] - 150


def test_reconciliation_finds_a_survey_10_cm_above_the_model(ledger, geometry, tmp_path,
                                                             capsys, seed):
    from projector.query import project

    with open_ledger(ledger, read_only=True) as store:
        model = project(store, PILE, 1793509200 * S)
    top = model.state.stack.surface()
    rng = np.random.default_rng(seed)
    print(f"survey points seed {seed}")
    # four points in every cell of the middle of the grid, each at the model's top + 10 cm
    ix, iy = np.meshgrid(np.arange(20, geometry.nx - 20), np.arange(20, geometry.ny - 20),
                         indexing="ij")
    ix, iy = np.repeat(ix.ravel(), 4), np.repeat(iy.ravel(), 4)
    x = geometry.origin_x_m + (ix + rng.uniform(0.05, 0.95, ix.size)) * geometry.cell_m
    y = geometry.origin_y_m + (iy + rng.uniform(0.05, 0.95, iy.size)) * geometry.cell_m
    laz = tmp_path / "biased.laz"
    write_laz(laz, [(x, y, top[ix, iy] + 0.10)], SITE)
    assert cli.main(["survey", "import", str(laz), "--ledger", str(ledger), "--pile", PILE,
                     "--time", TIME, "--no-progress"]) == 0
    capsys.readouterr()
    assert cli.main(["audit", "survey", "--ledger", str(ledger), "--pile", PILE,
                     "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)["surveys"]
    cells = (geometry.nx - 40) * (geometry.ny - 40)
    area = cells * geometry.cell_area_m2
    assert row["cells"] == cells and row["area_m2"] == pytest.approx(area)
    # every surveyed cell 10 cm above the model (bare ground too): 0.1 m x the area
    assert row["diff_now_m3"] == pytest.approx(0.1 * area, rel=0.01)
    assert row["model_now_m3"] == pytest.approx(float(
        np.clip(top - model.state.stack.ground(), 0, None)[20:-20, 20:-20].sum()
        * geometry.cell_area_m2), rel=1e-9)
    assert row["diff_then_m3"] == pytest.approx(row["diff_now_m3"], rel=1e-6)
    assert row["diff_now_t"] == pytest.approx(row["diff_now_m3"] * model.tonnes
                                              / model.volume_m3, rel=1e-9)
    # the map: each block's share is its surveyed cells' 10 cm
    diff_map = np.array(row["map"]["diff_m3"], dtype=float)
    assert np.nansum(diff_map) == pytest.approx(row["diff_now_m3"], rel=1e-9)
    assert row["largest_blocks"] and all(b["diff_m3"] > 0 for b in row["largest_blocks"])
    assert cli.main(["audit", "survey", "--ledger", str(ledger), "--pile", PILE]) == 0
    text = capsys.readouterr().out
    assert "difference (survey - model)" in text and "where" in text


#: the issue's large survey: generated here, never committed
LARGE_POINTS = 50_000_000
#: a 50 M-point file's coordinates alone, read at once, are 1.2 GB (three float64 each)
LARGE_BOUND_MIB = 600


@pytest.mark.slow
def test_a_50_million_point_survey_imports_in_bounded_memory(small_yard_sim, tmp_path_factory,
                                                            tmp_path, geometry, seed):
    source, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    laz = tmp_path / "large.laz"
    assert _plane_laz(laz, geometry, LARGE_POINTS, seed, chunk=1_000_000) == LARGE_POINTS
    path = tmp_path / "yard.duckdb"
    shutil.copy(source, path)
    started = time.monotonic()
    peak = _peak_rss_mib(["survey", "import", str(laz), "--ledger", str(path), "--pile", PILE,
                          "--time", TIME, "--no-progress"])
    wall_s = time.monotonic() - started
    (record,) = _survey(path)
    msg = decode_payload(record.type, record.payload)
    print(f"{LARGE_POINTS:,} points ({laz.stat().st_size / 2**20:,.0f} MiB of LAZ): "
          f"{wall_s:.1f} s wall, peak RSS {peak:.0f} MiB")
    assert msg.points == LARGE_POINTS and msg.points_in_grid > 0.99 * LARGE_POINTS
    assert peak < LARGE_BOUND_MIB

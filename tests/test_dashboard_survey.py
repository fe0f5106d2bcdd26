"""The survey heat map on the dashboard: a real LAZ imported into a real ledger, rendered
to an .rrd and read back with Rerun's own reader.

The survey is planted on the audit tests' yard: 10 cm above the model over the west half
of the surveyed box and 5 cm below it over the east half, both growing northwards. The map read back must hold
those values in the right pixels (north up, east to the right), red where the survey is
above and blue where it is below. The report, the log line and the survey's time must
also be there.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from ledger import open_ledger
from projector.query import project
from schemas.times import parse_time_ns
from services.dashboard import Config, render_ledger
from services.dashboard.surveys import heat_map
from stockpile import cli
from test_audit import PILE, audit_ledger
from test_dashboard import Rrd

pytest.importorskip("laspy")

from geo.site_crs import SiteCrs  # noqa: E402
from sim.survey import write_laz  # noqa: E402

SITE = SiteCrs(-20.659739, 117.078497, 5.0, 7850)
TIME = "2026-11-01T05:00:00Z"
#: the box surveyed: cells [MARGIN, n - MARGIN) each way
MARGIN = 20


@pytest.fixture(scope="module")
def rendered(small_yard_sim, tmp_path_factory, seed):
    """(the .rrd read back, the grid, the planted difference per cell (nx, ny), NaN off
    the box)."""
    base = tmp_path_factory.mktemp("dashboard-survey")
    source, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    ledger = base / "yard.duckdb"
    shutil.copy(source, ledger)
    with open_ledger(ledger, read_only=True) as store:
        model = project(store, PILE, parse_time_ns(TIME))
    g, top = model.geometry, model.state.stack.surface()
    planted = np.full(g.shape, np.nan)
    box = (slice(MARGIN, g.nx - MARGIN), slice(MARGIN, g.ny - MARGIN))
    west = np.arange(g.nx)[:, None] < g.nx // 2
    north = 0.0002 * np.arange(g.ny)[None, :]      # m; the map's rows must not be flipped
    planted[box] = np.where(west, 0.10 + north, -0.05 - north)[box]
    rng = np.random.default_rng(seed)
    print(f"survey points seed {seed}")
    ix, iy = np.nonzero(np.isfinite(planted))
    ix, iy = np.repeat(ix, 3), np.repeat(iy, 3)
    x = g.origin_x_m + (ix + rng.uniform(0.05, 0.95, ix.size)) * g.cell_m
    y = g.origin_y_m + (iy + rng.uniform(0.05, 0.95, iy.size)) * g.cell_m
    laz = base / "flight.laz"
    write_laz(laz, [(x, y, top[ix, iy] + planted[ix, iy])], SITE)
    assert cli.main(["survey", "import", str(laz), "--ledger", str(ledger), "--pile", PILE,
                     "--time", TIME, "--no-progress"]) == 0
    out = base / "pile.rrd"
    render_ledger(str(ledger), None, Config(rrd=str(out), every_s=600.0))
    return Rrd(out), g, planted


def test_the_heat_map_holds_survey_minus_model_north_up(rendered):
    rrd, g, planted = rendered
    (row,) = rrd.rows("/surveys/difference_m", "Tensor:data")
    valid_ns, _seq, (tensor,) = row
    assert valid_ns == parse_time_ns(TIME)
    assert tensor["names"] == ["y", "x"]
    values = np.asarray(tensor["buffer"], dtype=np.float32).reshape(tensor["shape"])
    assert values.shape == (g.ny, g.nx)
    expected = planted.T[::-1, :]              # row 0: the northmost cells (largest y)
    assert np.array_equal(np.isfinite(values), np.isfinite(expected))
    err = np.abs(values - expected)[np.isfinite(expected)]
    # the LAZ's 1 mm quantum and float32
    assert err.max() < 2e-3, err.max()


def test_the_heat_map_is_red_where_the_survey_is_higher_and_blue_where_lower(rendered):
    rrd, g, planted = rendered
    assert "Image" in rrd.archetypes["/surveys/difference"]
    (row,) = rrd.rows("/surveys/difference", "Image:buffer")
    (fmt,) = [f for _v, _s, f in rrd.rows("/surveys/difference", "Image:format")]
    image = np.asarray(row[2][0], np.uint8).reshape(fmt[0]["height"], fmt[0]["width"], 4)
    expected = planted.T[::-1, :]
    above, below = expected > 0, expected < 0
    assert np.all(image[..., 3][np.isnan(expected)] == 0)          # transparent off the box
    assert np.all(image[..., 3][above | below] == 255)
    red, blue = image[..., 0].astype(int), image[..., 2].astype(int)
    assert np.all(red[above] > blue[above]) and np.all(blue[below] > red[below])


def test_the_report_and_the_log_name_the_survey(rendered):
    rrd, g, planted = rendered
    (doc,) = [x for _v, _s, x in rrd.rows("/surveys/report", "TextDocument:text")]
    text = doc[0]
    assert f"{PILE}-{parse_time_ns(TIME) // 10**9}" in text
    row = next(line for line in text.splitlines() if line.startswith(f"| {PILE}-"))
    cols = [c.strip().replace(",", "") for c in row.strip("|").split("|")]
    area = np.isfinite(planted).sum() * g.cell_area_m2
    assert float(cols[2]) == pytest.approx(area, abs=0.5)
    # the net difference: the planted heights (to the LAZ's 1 mm quantum) over the cells
    assert float(cols[5]) == pytest.approx(np.nansum(planted) * g.cell_area_m2, abs=0.5)
    logs = [x[0] for _v, _s, x in rrd.rows("/log", "TextLog:text")]
    assert any(line.startswith("survey ") and "difference" in line for line in logs)


def test_heat_map_checks_its_input():
    with pytest.raises(ValueError, match="2-D"):
        heat_map(np.zeros(3))
    image, values, scale = heat_map(np.full((2, 3), np.nan))
    assert image.shape == (3, 2, 4) and not image[..., 3].any() and scale == 0.05


def test_a_live_dashboard_draws_a_survey_from_the_ledger_service(small_yard_sim,
                                                                 tmp_path_factory, tmp_path):
    """A survey published while the dashboard follows a real ledger service over Zenoh:
    the dashboard folds the model through the service's queries (RemoteLedger) and draws
    survey minus model."""
    from surveys.grid import CellAccumulator, survey_message
    from services.ledger_client import LedgerClient
    from services.service import EventPublisher
    from zenoh_helpers import last_status, live_dashboard, wait_until

    site = "dash-survey"
    source, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    path = tmp_path / "ledger.duckdb"
    shutil.copy(source, path)
    with open_ledger(path, read_only=True) as store:
        head = store.head().global_seq
        model = project(store, PILE, parse_time_ns(TIME))
    g, top = model.geometry, model.state.stack.surface()
    ix, iy = np.meshgrid(np.arange(MARGIN, g.nx - MARGIN), np.arange(MARGIN, g.ny - MARGIN),
                         indexing="ij")
    acc = CellAccumulator(g)
    acc.add(g.origin_x_m + (ix.ravel() + 0.5) * g.cell_m,
            g.origin_y_m + (iy.ravel() + 0.5) * g.cell_m, top[ix, iy].ravel() + 0.10)
    msg = survey_message(acc, time_ns=parse_time_ns(TIME), survey_id="LIVE-1", pile_id=PILE,
                         provider="test", accuracy_m=0.03, source_sha256=bytes(32),
                         crs_epsg=7850)
    out = tmp_path / "live.rrd"
    with live_dashboard(path, site, (PILE,), out, tmp_path) as run:
        drone = EventPublisher(run.router, site, "survey.import",
                               epoch=parse_time_ns(TIME) // 10**9)
        drone.wait_matched("survey", 30)
        drone.publish(msg)
        LedgerClient(run.router, site).wait_for(lambda h: h["global_seq"] >= head + 1, 30)
        wait_until(lambda: int(last_status(run.log).get("records", 0)) >= head + 2
                   and int(last_status(run.log).get("updates", 0))
                   > int(run.caught["updates"]), 60, "the dashboard's update after the survey")
    assert run.codes == [0, 0]
    rrd = Rrd(out)
    (row,) = rrd.rows("/surveys/difference_m", "Tensor:data")
    values = np.asarray(row[2][0]["buffer"], dtype=np.float32)
    surveyed = values[np.isfinite(values)]
    assert row[1] == head + 1 and surveyed.size == ix.size
    np.testing.assert_allclose(surveyed, 0.10, atol=1e-5)     # float32 heights

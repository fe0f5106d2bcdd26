"""Exports for mine planning and GIS, each read back with its own library.

The ledger is the audit tests' small yard (one stacking pass and a reclaim cut, site
declared with EPSG:7850), projected at its head.  Every file is written by the real
``stockpile export`` command (in this process) and read back with rasterio, ezdxf,
pyarrow, the csv module and json; positions are taken back to the site frame through
the file's own georeferencing and compared with the pile's cells.  The site-frame
conversion itself is checked against pymap3d, the GNSS path's own library.
"""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from ledger import open_ledger
from projector.grid import cell_centres
from projector.query import project
from stockpile import cli
from test_audit import PILE, audit_ledger

pytest.importorskip("rasterio")

from geo.site_crs import SiteCrs  # noqa: E402
from exports.cuts import footprint_rings  # noqa: E402
from exports.dxf import mesh_step  # noqa: E402

#: the simulator's site (sim.scenario.Scenario's datum), on its declared grid
LAT, LON, ALT = -20.659739, 117.078497, 5.0
EPSG = 7850


@pytest.fixture(scope="module")
def yard(small_yard_sim, tmp_path_factory):
    path, _info = audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    with open_ledger(path, read_only=True) as store:
        pile = project(store, PILE)
    assert pile.cuts and pile.tonnes > 0
    return {"ledger": path, "pile": pile, "site": SiteCrs(LAT, LON, ALT, EPSG)}


def _export(yard, what: str, out, *extra: str, capsys=None) -> dict:
    argv = ["export", what, "--ledger", str(yard["ledger"]), "--pile", PILE, "--out", str(out),
            "--json", *extra]
    assert cli.main(argv) == 0
    return json.loads(capsys.readouterr().out) if capsys else {}


# -- the site frame -------------------------------------------------------------------------


@pytest.mark.parametrize("epsg", [7850, 28350, 32750])
def test_mine_grid_to_site_and_back_within_a_millimetre(epsg, seed):
    import pymap3d
    from pyproj import CRS, Transformer

    site = SiteCrs(LAT, LON, ALT, epsg)
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-3000, 3000, 500), rng.uniform(-3000, 3000, 500)
    z = rng.uniform(-50, 80, 500)
    e, n, h = site.to_grid(x, y, z)
    back = np.column_stack(site.to_site(e, n, h))
    assert np.abs(back - np.column_stack([x, y, z])).max() < 1e-3
    # the site frame is the GNSS path's: pymap3d's ENU of the same geodetic point
    lon, lat, alt = Transformer.from_crs(CRS.from_epsg(epsg).to_3d(), CRS.from_epsg(4979),
                                         always_xy=True).transform(e, n, h)
    enu = np.column_stack(pymap3d.geodetic2enu(lat, lon, alt, LAT, LON, ALT))
    assert np.abs(enu - np.column_stack([x, y, z])).max() < 1e-3


def test_a_crs_that_is_not_a_projected_grid_in_metres_is_refused():
    with pytest.raises(ValueError, match="not a projected CRS"):
        SiteCrs(LAT, LON, ALT, 4326)
    with pytest.raises(ValueError, match="not a CRS PROJ knows"):
        SiteCrs(LAT, LON, ALT, 1)
    with pytest.raises(ValueError, match="not metres"):
        SiteCrs(LAT, LON, ALT, 2229)            # California zone 5, US survey feet


# -- GeoTIFF --------------------------------------------------------------------------------


def test_geotiff_gives_every_surface_back_to_the_cell(yard, tmp_path, capsys):
    import rasterio

    out = tmp_path / "surfaces.tif"
    summary = _export(yard, "surfaces", out, capsys=capsys)
    pile, site = yard["pile"], yard["site"]
    stack, g = pile.state.stack, pile.geometry
    with rasterio.open(out) as src:
        assert src.crs.to_epsg() == EPSG
        assert (src.width, src.height) == (g.nx, g.ny)
        assert src.count == stack.n_deposits + 1 == len(summary["bands"])
        assert src.descriptions[0] == "ground"
        assert src.descriptions[-1].startswith("top surface: top of deposit")
        bands = src.read()
        transform = src.transform
    rows, cols = np.mgrid[0:g.ny, 0:g.nx]
    e, n = transform * (cols.ravel() + 0.5, rows.ravel() + 0.5)
    ix, iy = cols.ravel(), g.ny - 1 - rows.ravel()
    x, y = cell_centres(g)
    surfaces = [stack.surface_k(k) for k in range(stack.n_deposits + 1)]
    np.testing.assert_array_equal(surfaces[-1], stack.surface())
    for band, surface in zip(bands, surfaces):
        h = band[rows.ravel(), cols.ravel()].astype(np.float64)
        sx, sy, sz = site.to_site(e, n, h)
        # each pixel lies on its cell's centre, and its height is the cell's surface
        assert np.hypot(sx - x[ix, iy], sy - y[ix, iy]).max() < 0.01
        np.testing.assert_allclose(sz, surface[ix, iy], atol=2e-4)   # float32 at ~60 m
    assert summary["placement_residual_m"] < 0.005


# -- DXF ------------------------------------------------------------------------------------


def test_dxf_mesh_has_its_vertices_and_the_surfaces_extent(yard, tmp_path, capsys):
    import ezdxf

    out = tmp_path / "top.dxf"
    summary = _export(yard, "mesh", out, "--contour-m", "0.5", "--max-vertices", "5000",
                      capsys=capsys)
    pile, site, g = yard["pile"], yard["site"], yard["pile"].geometry
    doc = ezdxf.readfile(out)
    meshes = [p for p in doc.modelspace().query("POLYLINE[layer=='SURFACE']")
              if p.is_poly_face_mesh]
    assert len(meshes) == 1
    vertices, faces = meshes[0].indexed_faces()
    vertices, faces = list(vertices), list(faces)
    step = mesh_step(g.nx, g.ny, 5000)
    # every step-th cell each way and the last: intervals of the lattice, then its points
    gaps_x, gaps_y = len(range(0, g.nx - 1, step)), len(range(0, g.ny - 1, step))
    assert len(vertices) == summary["vertices"] == (gaps_x + 1) * (gaps_y + 1) <= 5000
    assert mesh_step(g.nx, g.ny, (gaps_x + 1) * (gaps_y + 1) - 1) > step   # the smallest
    assert len(faces) == summary["faces"] == gaps_x * gaps_y
    v = np.array([tuple(p.dxf.location) for p in vertices])
    sx, sy, sz = site.to_site(v[:, 0], v[:, 1], v[:, 2])
    x, y = cell_centres(g)
    assert abs(sx.min() - x[0, 0]) < 0.01 and abs(sx.max() - x[-1, 0]) < 0.01
    assert abs(sy.min() - y[0, 0]) < 0.01 and abs(sy.max() - y[0, -1]) < 0.01
    # every vertex is the top surface at its cell
    ix = np.rint((sx - x[0, 0]) / g.cell_m).astype(int)
    iy = np.rint((sy - y[0, 0]) / g.cell_m).astype(int)
    np.testing.assert_allclose(sz, pile.state.stack.surface()[ix, iy], atol=1e-6)
    # contours: each polyline at one multiple of 0.5 m, lying on the surface
    contours = list(doc.modelspace().query("POLYLINE[layer=='CONTOURS']"))
    assert len(contours) == summary["contours"] > 0
    from scipy.interpolate import RegularGridInterpolator
    top = RegularGridInterpolator((x[:, 0], y[0, :]), pile.state.stack.surface())
    heights = site.to_grid(x, y, pile.state.stack.surface())[2]
    span = float(np.ptp(heights))
    assert span > 1.0
    for line in contours[:: max(1, len(contours) // 20)]:
        pts = np.array([tuple(p) for p in line.points()])
        assert np.ptp(pts[:, 2]) == 0 and math.isclose(pts[0, 2] / 0.5, round(pts[0, 2] / 0.5))
        cx, cy, cz = site.to_site(pts[:, 0], pts[:, 1], pts[:, 2])
        inside = ((cx >= x[0, 0]) & (cx <= x[-1, 0]) & (cy >= y[0, 0]) & (cy <= y[0, -1]))
        np.testing.assert_allclose(top(np.column_stack([cx[inside], cy[inside]])),
                                   cz[inside], atol=0.01)


# -- the block model ------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", ["csv", "parquet"])
def test_block_model_adds_up_to_the_pile(yard, tmp_path, capsys, suffix):
    out = tmp_path / f"blocks.{suffix}"
    summary = _export(yard, "blocks", out, capsys=capsys)
    pile, site = yard["pile"], yard["site"]
    if suffix == "csv":
        with open(out, newline="") as f:
            rows = list(csv.DictReader(f))
        col = {k: np.array([float(r[k]) if r[k] != "" else math.nan for r in rows])
               for k in rows[0] if k != "DOMINANT_LOT"}
        lots = {r["DOMINANT_LOT"] for r in rows}
    else:
        import pyarrow.parquet as pq

        table = pq.read_table(out)
        meta = table.schema.metadata
        assert meta[b"crs"] == f"EPSG:{EPSG}".encode()
        assert float(meta[b"block_axes_from_grid_north_deg"]) != 0.0
        col = {k: np.array(table.column(k).to_pylist(), dtype=float)
               for k in table.column_names if k != "DOMINANT_LOT"}
        lots = set(table.column("DOMINANT_LOT").to_pylist())
    assert len(col["TONNES"]) == summary["rows"] > 0
    assert math.isclose(col["TONNES"].sum(), pile.tonnes, rel_tol=1e-6)
    assert math.isclose(col["VOLUME_M3"].sum(), pile.volume_m3, rel_tol=1e-6)
    fe = col["FE_PCT"]
    graded = np.isfinite(fe)
    assert graded.all()            # every lot of the small yard has a grade
    assert math.isclose((fe * col["TONNES"]).sum() / col["TONNES"].sum(), pile.grade["Fe"],
                        rel_tol=1e-6)
    assert lots <= {d.lot_id for d in pile.deposits}
    assert ((col["ASSAYED_FRACTION"] >= 0) & (col["ASSAYED_FRACTION"] <= 1 + 1e-12)).all()
    np.testing.assert_allclose(col["DENSITY_T_M3"], col["TONNES"] / col["VOLUME_M3"])
    # each block's centre, back in the site frame, is a voxel centre of the pile's grid
    x, y, z = site.to_site(col["X"], col["Y"], col["Z"])
    v, g = pile.state.pile.voxel_m, pile.geometry
    assert (col["VOLUME_M3"] <= col["DX"] * col["DY"] * col["DZ"] * (1 + 1e-9)).all()
    assert np.abs((x - g.origin_x_m - col["DX"] / 2) / v
                  - np.rint((x - g.origin_x_m - col["DX"] / 2) / v)).max() < 1e-4


def test_block_model_weights_grades_by_graded_tonnes(small_yard_sim, tmp_path_factory,
                                                     tmp_path, capsys):
    """The small yard with its second pass stacked from an undeclared lot: that material
    has no grade, so the pile's Fe is over the graded tonnes only, and so is the blocks'."""
    audit_ledger(small_yard_sim, tmp_path_factory.getbasetemp())
    lines = (tmp_path_factory.getbasetemp() / "audit-ledger.jsonl").read_text()
    second = '"lot_id":"LOT-A","machine_id":"stk1","pass_id":"LOT-A-P2"'
    assert lines.count(second) == 1
    jsonl = tmp_path / "undeclared.jsonl"
    jsonl.write_text(lines.replace(second, second.replace('"LOT-A",', '"LOT-X",')))
    ledger = tmp_path / "undeclared.duckdb"
    assert cli.main(["ledger", "import", str(jsonl), "--ledger", str(ledger),
                     "--clock", "events"]) == 0
    with open_ledger(ledger, read_only=True) as store:
        pile = project(store, PILE)
    ungraded = sum(d.tonnes for d in pile.deposits if d.lot_id == "LOT-X")
    assert ungraded > 1.0
    out = tmp_path / "blocks.csv"
    capsys.readouterr()
    _export({"ledger": ledger}, "blocks", out, capsys=capsys)
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    tonnes = np.array([float(r["TONNES"]) for r in rows])
    graded = np.array([float(r["GRADED_FRACTION"]) for r in rows]) * tonnes
    fe = np.array([float(r["FE_PCT"]) if r["FE_PCT"] else math.nan for r in rows])
    print(f"ungraded {ungraded:.1f} t of {pile.tonnes:.1f} t; pile Fe {pile.grade['Fe']:.4f}")
    assert math.isclose(tonnes.sum() - graded.sum(), ungraded, rel_tol=1e-6)
    assert np.isnan(fe[graded == 0]).all() and np.isfinite(fe[graded > 0]).all()
    ok = graded > 0
    assert math.isclose((fe[ok] * graded[ok]).sum() / graded.sum(), pile.grade["Fe"],
                        rel_tol=1e-6)
    # blocks that mix the two: their Fe is the graded material's (one lot, one grade), not
    # diluted by the ungraded tonnes
    mixed = ok & (graded < tonnes * (1 - 1e-9))
    assert mixed.sum() >= 3
    np.testing.assert_allclose(fe[mixed], pile.grade["Fe"], rtol=1e-9)


# -- GeoJSON --------------------------------------------------------------------------------


def _area(ring) -> float:
    r = np.asarray(ring)
    return 0.5 * float(np.sum(r[:-1, 0] * r[1:, 1] - r[1:, 0] * r[:-1, 1]))


def test_cut_footprints_and_grades_as_geojson(yard, tmp_path, capsys):
    out = tmp_path / "cuts.geojson"
    _export(yard, "cuts", out, capsys=capsys)
    pile, site = yard["pile"], yard["site"]
    doc = json.loads(out.read_text())
    assert doc["crs"]["properties"]["name"] == f"urn:ogc:def:crs:EPSG::{EPSG}"
    assert [f["properties"]["cut_id"] for f in doc["features"]] == [c.cut_id for c in pile.cuts]
    for feature, cut in zip(doc["features"], pile.cuts):
        p = feature["properties"]
        assert math.isclose(p["tonnes"], cut.tonnes, rel_tol=1e-12)
        assert math.isclose(p["Fe_pct"], cut.grade["Fe"], rel_tol=1e-12)
        polygons = feature["geometry"]["coordinates"]
        area = 0.0
        for rings in polygons:
            assert _area(rings[0]) > 0 and all(_area(h) < 0 for h in rings[1:])
            ring_site = [site.to_site(*np.asarray(r).T, 0.0) for r in rings]
            area += sum(_area(np.column_stack(r[:2])) for r in ring_site)
        # the outline's area (in the site frame) is the footprint's cells' area
        assert math.isclose(area, p["footprint_m2"], rel_tol=1e-3) and p["footprint_cells"] > 0


def test_footprint_rings_trace_holes_and_corner_touching_cells():
    mask = np.zeros((7, 6), bool)
    mask[1:6, 1:5] = True
    mask[3, 2] = False                 # a hole
    mask[0, 0] = True                  # touches the block only at a corner
    polygons = footprint_rings(mask)
    assert len(polygons) == 2
    areas = sorted((abs(_area(np.array(o + [o[0]], float))),
                    [abs(_area(np.array(h + [h[0]], float))) for h in hs]) for o, hs in polygons)
    assert areas == [(1.0, []), (20.0, [1.0])]
    for outer, holes in polygons:
        assert _area(np.array(outer + [outer[0]], float)) > 0
        assert all(_area(np.array(h + [h[0]], float)) < 0 for h in holes)
    assert footprint_rings(np.zeros((3, 3), bool)) == []


# -- the command's errors -------------------------------------------------------------------


def test_export_errors_are_one_line(yard, tmp_path, capsys):
    base = ["export", "surfaces", "--ledger", str(yard["ledger"]), "--out",
            str(tmp_path / "x.tif")]
    assert cli.main([*base, "--pile", "NOPE"]) == 2
    err = capsys.readouterr().err.strip()
    assert "NOPE" in err and "not declared" in err and "\n" not in err
    assert cli.main([*base, "--pile", PILE, "--crs", "4326"]) == 2
    err = capsys.readouterr().err.strip()
    assert "not a projected CRS" in err and "\n" not in err
    assert not (tmp_path / "x.tif").exists()
    assert not list(tmp_path.iterdir())          # no half-written file left


def test_a_site_declares_an_epsg_code_or_none():
    from schemas import pb
    from schemas.events import make_event
    from schemas.validate import InvalidEvent, check_event

    def site(code: int):
        return make_event(pb.SiteDeclared(site_id="s", datum_lat_deg=LAT, datum_lon_deg=LON,
                                          crs_epsg=code), source="yard.config", epoch=1, seq=0)
    for code in (0, 1024, EPSG, 32767):
        assert check_event(site(code)).crs_epsg == code
    for code in (1, 1023, 32768):
        with pytest.raises(InvalidEvent, match="crs_epsg"):
            check_event(site(code))

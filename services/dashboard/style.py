"""How the dashboard looks: colour maps, the default layout (blueprint) and the time
series' names and colours.

- :func:`colour_map`: grades -> RGB, blue low to red high, grey for no grade
- :func:`lot_colour`: a stable colour per lot (the deposit boundaries)
- :func:`blueprint`: the 3D pile beside the time series, the log and the documents
  (:func:`piles_blueprint`: several piles, a tab each)
- :func:`log_series_styles`: the static names and colours of the ``/series/...`` entities
"""

from __future__ import annotations

import zlib
from typing import Iterable

import numpy as np

GREY = (150, 150, 150)
#: "as known then" / "at the cut's end" lines and points
BLUE = [90, 160, 255]
#: "as known now" lines and points
ORANGE = [240, 120, 40]
#: the one-sd bands of "as known then" and "at the cut's end" (pale blue)
BAND = [170, 205, 255]

_ANCHORS = np.array([[49, 54, 149], [69, 117, 180], [116, 173, 209], [171, 217, 233],
                     [254, 224, 144], [253, 174, 97], [244, 109, 67], [215, 48, 39]], float)


def colour_map(values, lo: float, hi: float) -> np.ndarray:
    """Values -> RGB uint8 (n, 3): blue at ``lo``, red at ``hi``; NaN grey."""
    v = np.asarray(values, np.float64)
    out = np.empty(v.shape + (3,), np.uint8)
    ok = np.isfinite(v)
    span = hi - lo if hi > lo else 1.0
    t = np.clip((v[ok] - lo) / span, 0.0, 1.0) * (len(_ANCHORS) - 1)
    i = np.minimum(t.astype(int), len(_ANCHORS) - 2)
    f = (t - i)[:, None]
    out[ok] = np.round(_ANCHORS[i] * (1 - f) + _ANCHORS[i + 1] * f).astype(np.uint8)
    out[~ok] = GREY
    return out


def lot_colour(lot_id: str) -> tuple[int, int, int]:
    """A stable colour per lot id."""
    h = zlib.crc32(lot_id.encode()) & 0xFFFFFF
    return (64 + (h & 0x7F), 64 + ((h >> 8) & 0x7F), 64 + ((h >> 16) & 0x7F))


def _eye(pile: tuple[float, float, float, float, float]):
    """The 3D camera from the far side of the rail, looking down on the pile's footprint."""
    import rerun.blueprint as rrb   # deferred: rerun is heavy

    x0, y0, width, length, z0 = pile
    xc, yc, size = x0 + width / 2, y0 + length / 2, max(width, length)
    return rrb.EyeControls3D(position=[xc + 0.95 * size, yc - 1.15 * size, z0 + 0.8 * size],
                             look_target=[xc, yc, z0 + 2.0], eye_up=[0.0, 0.0, 1.0])


def blueprint(analytes: Iterable[str], analyte: str = "Fe", *, layers: bool = False,
              pile: tuple[float, float, float, float, float] | None = None):
    """The default layout of one pile: 3D pile | time series and logs.

    ``pile = (origin_x_m, origin_y_m, width_m, length_m, ground_z_m)`` aims the 3D camera at
    the declared footprint (from the far side of the rail, looking down on the pile).
    """
    return _with_time_panel(_pile_layout(analytes, analyte, layers=layers, pile=pile))


def piles_blueprint(piles: Iterable[tuple[str, str, Iterable[str], tuple | None]],
                    analyte: str = "Fe", *, layers: bool = False):
    """The default layout of several piles: one tab per pile, each the layout of
    :func:`blueprint` over the pile's entities; ``piles``: ``(pile_id, prefix, analytes,
    box)`` each (``prefix``: :func:`services.dashboard.recorder.entity_prefix`, ``box``
    as :func:`blueprint`'s ``pile``)."""
    import rerun.blueprint as rrb   # deferred: rerun is heavy

    return _with_time_panel(rrb.Tabs(*[
        _pile_layout(analytes, analyte, layers=layers, pile=box, prefix=prefix,
                     name=f"Pile {pile_id}") for pile_id, prefix, analytes, box in piles]))


def recording_blueprint(config, analytes: Iterable[str], *,
                        pile: tuple[float, float, float, float, float] | None = None,
                        boxes: dict[str, tuple] | None = None):
    """The blueprint a recording of ``config.piles`` (a :class:`Config`) starts with: one
    pile's :func:`blueprint` (``pile``: its footprint), or several piles'
    :func:`piles_blueprint` (``boxes``: their footprints by pile id, when known)."""
    from services.dashboard.recorder import entity_prefix

    analytes = tuple(analytes)
    if len(config.piles) <= 1:
        return blueprint(analytes, config.analyte, layers=config.layers, pile=pile)
    boxes = boxes or {}
    return piles_blueprint([(p, entity_prefix(p, config.piles), analytes, boxes.get(p))
                            for p in config.piles], config.analyte, layers=config.layers)


def _with_time_panel(root):
    import rerun.blueprint as rrb   # deferred: rerun is heavy

    return rrb.Blueprint(root, rrb.TimePanel(timeline="valid_time"), collapse_panels=True)


def _pile_layout(analytes: Iterable[str], analyte: str, *, layers: bool,
                 pile: tuple[float, float, float, float, float] | None, prefix: str = "",
                 name: str | None = None):
    """One pile's 3D view beside its time series and logs (its entities under ``prefix``;
    ``name``: the container's, and the start of the 3D view's)."""
    import rerun.blueprint as rrb   # deferred: rerun is heavy

    eye = _eye(pile) if pile is not None else None
    everything = rrb.TimeAxis(view_range=rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(),
                                                       end=rrb.TimeRangeBoundary.infinite()))

    def series(title: str, origin: str):
        return rrb.TimeSeriesView(name=title, origin=prefix + origin, axis_x=everything)

    analytes = list(analytes) or [analyte]
    shown = analyte if analyte in analytes else analytes[0]
    hidden = {f"{prefix}/site/pile/surface/{a}": rrb.EntityBehavior(visible=False)
              for a in analytes if a != shown}
    hidden[f"{prefix}/site/pile/voxels"] = rrb.EntityBehavior(visible=False)
    if not layers:
        hidden[f"{prefix}/site/pile/layers"] = rrb.EntityBehavior(visible=False)
    return rrb.Horizontal(
        rrb.Vertical(
            rrb.Spatial3DView(name=f"{name or 'Pile'}: surface coloured by {shown} (blue low, "
                              "red high)", origin=f"{prefix}/site", overrides=hidden,
                              eye_controls=eye),
            rrb.Tabs(rrb.TextLogView(name="Log", origin=f"{prefix}/log"),
                     rrb.TextDocumentView(name="Cuts", origin=f"{prefix}/cuts"),
                     rrb.TextDocumentView(name="Status", origin=f"{prefix}/status"),
                     rrb.TextDocumentView(name="Legend", origin=f"{prefix}/legend"),
                     rrb.Spatial2DView(name="Survey - model (red: model short)",
                                       origin=f"{prefix}/surveys/difference"),
                     rrb.TextDocumentView(name="Surveys", origin=f"{prefix}/surveys/report")),
            row_shares=[3, 1]),
        rrb.Vertical(
            series("Pile tonnes (t)", "/series/pile/tonnes_t"),
            series(f"Pile {shown} (%)", f"/series/pile/grade_pct/{shown}"),
            series("Cuts: tonnes (t), geometry vs belt scale", "/series/cuts/tonnes_t"),
            series(f"Cuts: {shown} (%) at the end vs known now",
                   f"/series/cuts/grade_pct/{shown}"),
            series("Assayed fraction", "/series/pile/assayed_fraction"),
        ),
        column_shares=[3, 2], name=name)


def log_series_styles(rec, analytes: Iterable[str], *, first: bool, prefix: str = "") -> None:
    """Log the static names and colours of the time series (``rec``: a RecordingStream):
    the pile's and the cuts' own (``first``: the first time) and those of each of
    ``analytes`` (newly known); every path under ``prefix``."""
    import rerun as rr   # deferred: rerun is heavy

    rec = _Prefixed(rec, prefix)

    if first:
        styles = {"/series/pile/tonnes_t/known_then": ("as known then", BLUE),
                  "/series/pile/tonnes_t/known_now": ("as known now", ORANGE),
                  "/series/pile/assayed_fraction/known_then": ("as known then", BLUE),
                  "/series/pile/assayed_fraction/known_now": ("as known now", ORANGE),
                  "/series/cuts/assayed_fraction/at_end": ("cuts at their end", BLUE),
                  "/series/cuts/assayed_fraction/known_now": ("cuts known now", ORANGE),
                  "/series/pile/volume_m3": ("pile volume m3", [200, 200, 200])}
        for path, (name, colour) in styles.items():
            rec.log(path, rr.SeriesLines(names=name, colors=[colour]), static=True)
        _log_bands(rr, rec, "/series/pile/tonnes_t/known_then", "as known then")
        _log_bands(rr, rec, "/series/cuts/tonnes_t/geometry", "geometry", points=True)
        for path, name, colour in (("/series/cuts/tonnes_t/geometry", "geometry", ORANGE),
                                   ("/series/cuts/tonnes_t/belt_scale", "belt scale", BLUE)):
            rec.log(path, rr.SeriesPoints(names=name, colors=[colour], marker_sizes=[4.0]),
                    static=True)
    for a in analytes:
        rec.log(f"/series/pile/grade_pct/{a}/known_then",
                rr.SeriesLines(names=f"{a} % as known then", colors=[BLUE]), static=True)
        rec.log(f"/series/pile/grade_pct/{a}/known_now",
                rr.SeriesLines(names=f"{a} % as known now", colors=[ORANGE]), static=True)
        rec.log(f"/series/cuts/grade_pct/{a}/at_end",
                rr.SeriesPoints(names=f"{a} % at the cut's end", colors=[BLUE],
                                marker_sizes=[4.0]), static=True)
        rec.log(f"/series/cuts/grade_pct/{a}/known_now",
                rr.SeriesPoints(names=f"{a} % known now", colors=[ORANGE],
                                marker_sizes=[4.0]), static=True)
        _log_bands(rr, rec, f"/series/pile/grade_pct/{a}/known_then", f"{a} % as known then")
        _log_bands(rr, rec, f"/series/cuts/grade_pct/{a}/at_end", f"{a} % at the cut's end",
                   points=True)


def _log_bands(rr, rec, path: str, name: str, *, points: bool = False) -> None:
    """The static style of a series' one-sd band, ``<path>_hi`` and ``<path>_lo``
    (:meth:`services.dashboard.recorder.Recorder.band`): thin pale lines (points for the
    cuts' series)."""
    for side, sign in (("hi", "+"), ("lo", "-")):
        label = f"{name} {sign}1 sd"
        style = (rr.SeriesPoints(names=label, colors=[BAND], marker_sizes=[2.0]) if points
                 else rr.SeriesLines(names=label, colors=[BAND], widths=[0.5]))
        rec.log(f"{path}_{side}", style, static=True)


class _Prefixed:
    """``log`` of a RecordingStream with every entity path under ``prefix``."""

    def __init__(self, rec, prefix: str) -> None:
        self.rec, self.prefix = rec, prefix

    def log(self, path: str, entity, **kwargs) -> None:
        self.rec.log(self.prefix + path, entity, **kwargs)

"""Mine grid <-> site frame: the site's projected CRS against its local ENU tangent plane.

The site frame (every ``_m`` coordinate of the ledger and the projector) is the
east-north-up tangent plane at the site's datum (WGS-84 latitude, longitude and
ellipsoidal height: ``SiteDeclared``), as the GNSS path computes it with
``pymap3d.geodetic2enu``.  The mine grid is the site's projected CRS (``SiteDeclared.
crs_epsg``, for example 28350, GDA94 / MGA zone 50), made three-dimensional with the
ellipsoidal height as its third axis.

Both directions go through one PROJ transformation each way (the CRS's own datum to
WGS-84, then geodetic -> geocentric -> topocentric), so a point taken to the site and back
returns to within a micrometre.  Heights: the grid's Z is the *ellipsoidal* height on the
CRS's datum, not a mine RL on a geoid (docs/surveys-and-exports.md says how to convert).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

__all__ = ["SiteCrs", "check_epsg"]

#: the site frame's ellipsoid (pymap3d's default, the GNSS path's)
_ELLIPSOID = "WGS84"
#: WGS-84 geographic 3D (lon, lat, ellipsoidal height)
_WGS84_3D = 4979


def check_epsg(epsg: int):
    """The ``pyproj.CRS`` of ``epsg`` if it is a projected CRS in metres, else ValueError."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        crs = CRS.from_epsg(int(epsg))
    except (CRSError, ValueError, TypeError) as exc:
        raise ValueError(f"EPSG:{epsg} is not a CRS PROJ knows ({exc})") from None
    if not crs.is_projected:
        raise ValueError(f"EPSG:{epsg} ({crs.name}) is not a projected CRS: a mine grid is "
                         "one (for example 28350, GDA94 / MGA zone 50, or a UTM zone)")
    units = {a.unit_name for a in crs.axis_info[:2]}
    if units != {"metre"}:
        raise ValueError(f"EPSG:{epsg} ({crs.name}) is in {', '.join(sorted(units))}, "
                         "not metres")
    return crs


@dataclass(frozen=True)
class SiteCrs:
    """A site's datum and mine-grid CRS, and the conversions between their frames.

    Parameters
    ----------
    datum_lat_deg, datum_lon_deg : float
        WGS-84 latitude and longitude of the site frame's origin (degrees).
    datum_alt_m : float
        Its ellipsoidal height (m).
    epsg : int
        The mine grid's projected CRS (metres).

    Raises
    ------
    ValueError
        A datum out of range, or an EPSG code that is not a projected CRS in metres.
    """

    datum_lat_deg: float
    datum_lon_deg: float
    datum_alt_m: float
    epsg: int

    def __post_init__(self) -> None:
        if not (-90.0 <= self.datum_lat_deg <= 90.0 and -180.0 <= self.datum_lon_deg <= 180.0
                and np.isfinite(self.datum_alt_m)):
            raise ValueError(f"bad datum ({self.datum_lat_deg}, {self.datum_lon_deg}, "
                             f"{self.datum_alt_m})")
        check_epsg(self.epsg)

    @classmethod
    def from_site_declared(cls, message) -> "SiteCrs":
        """From a ``SiteDeclared`` message; ValueError if it declares no CRS."""
        if not message.crs_epsg:
            raise ValueError(f"site {message.site_id!r} declares no mine-grid CRS "
                             "(SiteDeclared.crs_epsg)")
        return cls(message.datum_lat_deg, message.datum_lon_deg, message.datum_alt_m,
                   int(message.crs_epsg))

    @property
    def crs(self):
        """The mine grid's ``pyproj.CRS`` (2D, as a GeoTIFF or a GIS names it)."""
        return check_epsg(self.epsg)

    @cached_property
    def _to_geodetic(self):
        from pyproj import CRS, Transformer

        return Transformer.from_crs(self.crs.to_3d(), CRS.from_epsg(_WGS84_3D),
                                    always_xy=True)

    @cached_property
    def _to_topocentric(self):
        from pyproj import Transformer

        return Transformer.from_pipeline(
            "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
            f"+step +proj=cart +ellps={_ELLIPSOID} "
            f"+step +proj=topocentric +ellps={_ELLIPSOID} +lat_0={self.datum_lat_deg!r} "
            f"+lon_0={self.datum_lon_deg!r} +h_0={self.datum_alt_m!r}")

    def to_site(self, easting_m, northing_m, height_m=0.0):
        """Mine grid (E, N, ellipsoidal height; m) -> site frame (x east, y north, z up; m).

        Arrays broadcast together; returns three float64 arrays of their shape.
        """
        e, n, h = _arrays(easting_m, northing_m, height_m)
        lon, lat, alt = self._to_geodetic.transform(e, n, h)
        return _arrays(*self._to_topocentric.transform(lon, lat, alt))

    def to_grid(self, x_m, y_m, z_m=0.0):
        """Site frame (m) -> mine grid (E, N, ellipsoidal height; m): :meth:`to_site`'s inverse."""
        x, y, z = _arrays(x_m, y_m, z_m)
        lon, lat, alt = self._to_topocentric.transform(x, y, z, direction="INVERSE")
        return _arrays(*self._to_geodetic.transform(lon, lat, alt, direction="INVERSE"))


def _arrays(a, b, c) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a, b, c = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64),
                                  np.asarray(c, np.float64))
    out = tuple(np.array(v, dtype=np.float64) for v in (a, b, c))
    for v in out:
        if not np.all(np.isfinite(v)):
            raise ValueError("coordinates must be finite (a point outside the CRS's area "
                             "gives inf)")
    return out  # type: ignore[return-value]

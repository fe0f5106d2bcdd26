"""A ``survey`` event's cells on the pile's grid (:func:`survey_heights`).

A survey (``stockpile survey import``, :mod:`surveys`) holds the mean height and the point
count of each cell of a part of the pile's grid; this puts them back on the whole grid.
"""

from __future__ import annotations

import numpy as np

from projector.grid import GridGeometry

__all__ = ["survey_heights"]


def survey_heights(msg, geometry: GridGeometry) -> tuple[np.ndarray, np.ndarray]:
    """``(heights (nx, ny) m, NaN where none; counts (nx, ny))`` of a ``Survey`` on the
    pile's grid ``geometry`` (ValueError if the survey's grid is not that grid)."""
    if (msg.cell_m != geometry.cell_m or msg.origin_x_m != geometry.origin_x_m
            or msg.origin_y_m != geometry.origin_y_m
            or msg.ix0 + msg.nx > geometry.nx or msg.iy0 + msg.ny > geometry.ny):
        raise ValueError(f"survey {msg.survey_id!r} is not on this pile's grid")
    heights = np.full(geometry.shape, np.nan)
    counts = np.zeros(geometry.shape, np.int64)
    part = (slice(msg.ix0, msg.ix0 + msg.nx), slice(msg.iy0, msg.iy0 + msg.ny))
    heights[part] = np.frombuffer(msg.heights_m, "<f4").reshape(msg.nx, msg.ny)
    counts[part] = np.frombuffer(msg.counts, "<u2").reshape(msg.nx, msg.ny)
    return heights, counts

"""Figures with their standard deviations, for the commands' text output."""

from __future__ import annotations

import math
from collections.abc import Mapping

__all__ = ["plus_minus", "format_grades"]


def plus_minus(sd: float | None, fmt: str = ",.1f") -> str:
    """`` +/- 0.30``: a finite standard deviation in ``fmt``; nothing for None or a
    non-finite one."""
    if sd is None or not math.isfinite(sd):
        return ""
    return f" +/- {sd:{fmt}}"


def format_grades(grade: Mapping[str, float | None],
                  sd: Mapping[str, float] | None = None) -> str:
    """``Fe 62.10 +/- 0.30 %, SiO2 ...``: each finite grade (%) with its sd (pp) where
    ``sd`` has one; ``-`` when none is finite."""
    sd = sd or {}
    return ", ".join(f"{a} {g:.2f}{plus_minus(sd.get(a), '.2f')} %" for a, g in grade.items()
                     if g is not None and math.isfinite(g)) or "-"

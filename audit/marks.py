"""The valid times of an audit history: epoch-aligned steps between two ends, and their count.

:func:`history_count` says how many rows a range gives by arithmetic, so that a command can
refuse a range that is too long before :func:`history_marks` lists it.
"""

from __future__ import annotations


def history_count(first_ns: int, last_ns: int, every_ns: int) -> int:
    """How many valid times :func:`history_marks` returns, computed without listing them."""
    if every_ns <= 0:
        raise ValueError("the interval must be positive")
    if last_ns <= first_ns:
        return 1
    inside = max(0, -(-last_ns // every_ns) - 1 - first_ns // every_ns)
    return inside + 2


def history_marks(first_ns: int, last_ns: int, every_ns: int) -> list[int]:
    """Valid times from ``first_ns`` to ``last_ns``: whole multiples of ``every_ns`` (UTC
    epoch aligned, so hourly marks fall on the hour) strictly inside, plus both ends."""
    if every_ns <= 0:
        raise ValueError("the interval must be positive")
    if last_ns <= first_ns:
        return [first_ns]
    inside = range((first_ns // every_ns + 1) * every_ns, last_ns, every_ns)
    return [first_ns, *inside, last_ns]

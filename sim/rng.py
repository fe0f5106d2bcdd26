"""The simulator's random-number streams.

Every model of the simulator takes a :class:`numpy.random.Generator`, never the global
RNG. :func:`named_rng` gives each concern of a run (belt, stacking, encoders, GNSS,
scanner) its own stream from the run's seed and the concern's name, so one concern's draws
never shift another's; :func:`check_rng` is the models' argument check.
"""

from __future__ import annotations

import zlib

import numpy as np


def named_rng(seed: int, name: str) -> np.random.Generator:
    """The stream of the concern ``name`` in a run seeded with ``seed``."""
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def check_rng(rng) -> np.random.Generator:
    """``rng`` if it is a numpy Generator; TypeError otherwise."""
    if not isinstance(rng, np.random.Generator):
        raise TypeError("rng must be a numpy.random.Generator, e.g. numpy.random.default_rng(seed)")
    return rng

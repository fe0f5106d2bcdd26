"""The one seed of a test run: every random test draws from it.

``pytest --seed N`` or ``STOCKPILE_TEST_SEED=N`` sets it (the option wins); without either,
each run draws a fresh one.  ``tests/conftest.py`` resolves it once per run
(:func:`resolve`), prints it in the header and the summary, and writes
``re-run with --seed N`` into the report of every failing test that used it (the ``seed``
fixture, :func:`rng`, a module constant taken from :func:`session_seed`, or a Hypothesis
test, which conftest seeds from it too).
"""

from __future__ import annotations

import os
import random

import numpy as np

ENV = "STOCKPILE_TEST_SEED"

_seed: int | None = None


def resolve(option: int | None) -> int:
    """The run's seed: ``option`` (``--seed``), else ``$STOCKPILE_TEST_SEED``, else fresh."""
    global _seed
    if option is not None:
        _seed = int(option)
    elif os.environ.get(ENV, "").strip():
        _seed = int(os.environ[ENV])
    else:
        _seed = random.SystemRandom().randrange(2 ** 32)
    return _seed


def session_seed() -> int:
    """The run's seed (resolved by conftest before collection; resolved here otherwise)."""
    return _seed if _seed is not None else resolve(None)


def rerun_hint(seed: int | None = None) -> str:
    seed = session_seed() if seed is None else seed
    return f"random seed {seed}: re-run with --seed {seed} (or {ENV}={seed})"


def rng(*keys: int) -> np.random.Generator:
    """A generator from the run's seed and ``keys`` (independent streams for distinct keys)."""
    return np.random.default_rng([session_seed(), *keys])

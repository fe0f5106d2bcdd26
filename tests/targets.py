"""The accuracy targets, from the one place they are written: the bench scripts' constants.

``bench/`` is not a package and two of its scripts share a name with a product package
(``bench/planner.py``, ``bench/projector.py``), so each script is loaded from its file
under a ``bench_`` name, and ``sys.path`` is put back as it was (the scripts add ``bench/``
to its front for their own helpers, ``_truth_tables`` and the like, which stay loaded).

- :data:`accuracy`: ``bench/accuracy.py`` (volume of the analytic piles,
  ``TARGET_PCT``: 0.05 % noise-free, 0.3 % noisy);
- :data:`projector_truth`: ``bench/projector_truth.py`` (pile tonnes ``TARGET_PILE_PCT``
  1 %, each cut's tonnes ``TARGET_CUT_PCT`` 3 % and Fe ``TARGET_FE_PP`` 0.3 pp);
- :data:`localizer`: ``bench/localizer.py`` (UKF RMSE <= ``TARGET_RATIO`` = 1/3 of each
  sensor's alone);
- :data:`planner_truth`: ``bench/planner_truth.py`` (a planned cut's tonnes within
  ``TARGET_T_PCT`` 5 % and Fe within ``TARGET_FE_PP`` 0.5 pp).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"


def _load(script: str):
    name = f"bench_{script}"
    if name in sys.modules:
        return sys.modules[name]
    saved = list(sys.path)
    sys.path.append(str(BENCH))          # its helpers; after the packages, never before
    try:
        spec = importlib.util.spec_from_file_location(name, BENCH / f"{script}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    finally:
        sys.path[:] = saved
    return module


accuracy = _load("accuracy")
projector_truth = _load("projector_truth")
localizer = _load("localizer")
planner_truth = _load("planner_truth")

#: volume of a pile, % (bench/accuracy.py)
VOLUME_NOISE_FREE_PCT = accuracy.TARGET_PCT["noise-free"]
VOLUME_NOISY_PCT = accuracy.TARGET_PCT["noisy"]
#: the projector against the simulator's truth (bench/projector_truth.py)
PILE_TONNES_PCT = projector_truth.TARGET_PILE_PCT
CUT_TONNES_PCT = projector_truth.TARGET_CUT_PCT
CUT_FE_PP = projector_truth.TARGET_FE_PP
#: UKF RMSE over each sensor's alone (bench/localizer.py)
LOCALIZER_RATIO = localizer.TARGET_RATIO
#: a planned cut against the simulator's (bench/planner_truth.py)
PLANNED_TONNES_PCT = planner_truth.TARGET_T_PCT
PLANNED_FE_PP = planner_truth.TARGET_FE_PP

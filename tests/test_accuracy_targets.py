"""The accuracy targets, enforced: the bench scripts' own cases against their own targets.

- ``bench/accuracy.py``: every analytic pile (prism, hyperbolic, cone; bench and full
  scale; noise-free and noisy) scanned and projected to a volume, against its closed-form
  volume: within ``TARGET_PCT`` (0.05 % noise-free, 0.3 % noisy).  The range noise is
  drawn from the run's seed (``--seed``, tests/seeding.py), one stream per case.
- ``bench/projector_truth.py``: the demo scenario at the script's default seed, simulated,
  imported into a DuckDB ledger with the simulator's true scanner poses (``--poses
  truth``: the projector's targets apart from the localizer's error) and projected: the pile's tonnes within
  ``TARGET_PILE_PCT`` (1 %), every cut's tonnes within ``TARGET_CUT_PCT`` (3 %) and Fe
  within ``TARGET_FE_PP`` (0.3 pp) of the simulator's truth, and no cut missing.

``make accuracy`` runs only these (``pytest -m accuracy``); ``make test`` runs them with the
rest.  About 2.5 minutes on one core, nearly all of it simulating the demo yard.
"""

from __future__ import annotations

import numpy as np
import pytest

import targets

accuracy = targets.accuracy
projector_truth = targets.projector_truth

pytestmark = pytest.mark.accuracy

CASES = accuracy.cases(quick=False)

#: the demo seed of ``bench/projector_truth.py`` (its default)
DEMO_SEED = projector_truth.DEFAULT_SEED


def _case_id(case) -> str:
    return f"{case.pile.name}-{case.scale}-{case.noise}"


@pytest.mark.parametrize("index", range(len(CASES)), ids=[_case_id(c) for c in CASES])
def test_analytic_pile_volume_within_target(index, seed):
    case = CASES[index]
    result = accuracy.run_case(case, np.random.default_rng([seed, index]))
    target = accuracy.TARGET_PCT[case.noise]
    print(f"{_case_id(case)}: true {result.true_m3:.6g} m3, ours {result.ours_m3:.6g} m3, "
          f"error {result.error_pct:+.4f} % (target <= {target} %)")
    assert abs(result.error_pct) <= target


@pytest.fixture(scope="module")
def demo_truth(tmp_path_factory):
    """``bench/projector_truth.py --scenario demo --seed 1 --poses truth``: the run and its
    figures."""
    out = tmp_path_factory.mktemp("projector-truth")
    result = projector_truth.run("demo", DEMO_SEED, out, poses="truth")
    figures = projector_truth.report(result)
    return result, figures


def test_demo_pile_tonnes_within_target(demo_truth):
    _result, figures = demo_truth
    assert abs(figures["pile_pct"]) <= projector_truth.TARGET_PILE_PCT, figures["pile_pct"]


def test_demo_every_cut_is_projected(demo_truth):
    result, figures = demo_truth
    true_cuts = [c["cut_id"] for c in result["truth"]["cuts"]]
    assert len(true_cuts) >= 10
    assert sorted(figures["cut_errors"]) == sorted(true_cuts)


def test_demo_cut_tonnes_and_fe_within_target(demo_truth):
    _result, figures = demo_truth
    misses = [f"{cut}: tonnes {t_pct:+.2f} % (target {projector_truth.TARGET_CUT_PCT:g} %), "
              f"Fe {fe_pp:+.2f} pp (target {projector_truth.TARGET_FE_PP:g} pp)"
              for cut, (t_pct, fe_pp, _met) in figures["cut_errors"].items()
              if not (abs(t_pct) <= projector_truth.TARGET_CUT_PCT
                      and abs(fe_pp) <= projector_truth.TARGET_FE_PP)]
    assert not misses, "\n".join(misses)
    # the bench script's own verdict agrees
    assert figures["ok"]

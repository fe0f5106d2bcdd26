"""The fixed-lag Rauch-Tung-Striebel smoother (``services/localizer_smoother.py``) against
the exact answer of a linear Gaussian model: a random walk seen through a decaying
correlated error, the shape of the localizer's bias and GNSS-error states.  A held
state's smoothed mean must equal the conditional mean of that state given every
measurement up to the one after which it was returned, computed at once from the joint
Gaussian."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from services.localizer_smoother import FixedLagSmoother

SEED = 20261129
#: the random walk's step sd, the correlated error's stationary sd, its decay per step,
#: the measurement's white sd
WALK_SD, MARKOV_SD, DECAY, WHITE_SD = 0.05, 0.2, math.exp(-1 / 60), 0.4
STEPS = 40


def _truth_and_measurements(rng):
    w = np.cumsum(rng.normal(0.0, WALK_SD, STEPS)) + rng.normal(0.0, 1.0)
    g = np.empty(STEPS)
    g[0] = rng.normal(0.0, MARKOV_SD)
    for k in range(1, STEPS):
        g[k] = DECAY * g[k - 1] + rng.normal(0.0, MARKOV_SD * math.sqrt(1 - DECAY ** 2))
    return w + g + rng.normal(0.0, WHITE_SD, STEPS)


def _filtered(z, lag_steps=math.inf, block_steps=None):
    """A linear Kalman filter over state (walk, error), one step a second, recording into
    a FixedLagSmoother that holds every step; returns ``{step: (state, newest step)}``
    for what it returned, with the newest step recorded when each was returned."""
    ns = 1e9
    rec = FixedLagSmoother(2, slice(1, 2), lag_steps * ns,
                           None if block_steps is None else block_steps * ns)
    returned = {}
    f = np.diag([1.0, DECAY])
    q = np.diag([WALK_SD ** 2, MARKOV_SD ** 2 * (1 - DECAY ** 2)])
    h = np.array([[1.0, 1.0]])
    x, p = np.zeros(2), np.diag([1.0, MARKOV_SD ** 2])
    for k, zk in enumerate(z):
        if k:
            rec.transition(DECAY)
            x, p = f @ x, f @ p @ f.T + q
        s = h @ p @ h.T + WHITE_SD ** 2
        gain = p @ h.T / s
        x_new = x + (gain * (zk - h @ x)).ravel()
        p_new = (np.eye(2) - gain @ h) @ p
        rec.update(int(k * ns), x, p, x_new, p_new)
        rec.hold(k)
        for step, state in rec.due():
            returned[step] = (state, k)
        x, p = x_new, p_new
    for step, state in rec.due(flush=True):
        returned[step] = (state, STEPS - 1)
    return returned, rec


@functools.cache
def _state_covariance() -> np.ndarray:
    """The joint covariance of every state (walk, error) of the STEPS steps."""
    n = 2 * STEPS
    cov = np.zeros((n, n))
    f = np.diag([1.0, DECAY])
    q = np.diag([WALK_SD ** 2, MARKOV_SD ** 2 * (1 - DECAY ** 2)])
    # states x_k = F^k x_0 + sum_j F^(k-j) u_j: covariance block (k, l)
    p0 = np.diag([1.0, MARKOV_SD ** 2])

    def power(m):
        return np.linalg.matrix_power(f, m)
    for k in range(STEPS):
        for l in range(STEPS):
            c = power(k) @ p0 @ power(l).T
            for j in range(1, min(k, l) + 1):
                c = c + power(k - j) @ q @ power(l - j).T
            cov[2 * k:2 * k + 2, 2 * l:2 * l + 2] = c
    return cov


def _batch_mean(z):
    """E[states | every z given] from the joint Gaussian of the states and measurements
    (the first ``len(z)`` steps)."""
    steps = len(z)
    n = 2 * steps
    cov = _state_covariance()[:n, :n]
    h = np.zeros((steps, n))
    h[np.arange(steps), 2 * np.arange(steps)] = 1.0
    h[np.arange(steps), 2 * np.arange(steps) + 1] = 1.0
    s = h @ cov @ h.T + WHITE_SD ** 2 * np.eye(steps)
    return (cov @ h.T @ np.linalg.solve(s, z)).reshape(steps, 2)


def test_flushed_means_are_the_conditional_means_given_every_measurement():
    print(f"smoother test seed {SEED}")
    z = _truth_and_measurements(np.random.default_rng(SEED))
    returned, rec = _filtered(z)
    assert sorted(returned) == list(range(STEPS)) and rec.held == 0
    smoothed = np.array([returned[k][0] for k in range(STEPS)])
    np.testing.assert_allclose(smoothed, _batch_mean(z), atol=1e-9)


@pytest.mark.parametrize("lag, block", [(5, None), (8, 3), (0, 0)])
def test_a_held_state_is_smoothed_over_the_measurements_up_to_its_return(lag, block):
    """Each state comes back once the newest step is ``lag`` past it (a block at a
    time), as the conditional mean given the measurements up to then; the smoother then
    keeps only the steps a held state still needs."""
    print(f"smoother test seed {SEED}")
    z = _truth_and_measurements(np.random.default_rng(SEED))
    returned, rec = _filtered(z, lag, block)
    assert sorted(returned) == list(range(STEPS))
    block_steps = lag / 2 if block is None else block
    late_returned = 0
    exact_given = {newest: _batch_mean(z[:newest + 1]) for _state, newest in returned.values()}
    for k, (state, newest) in returned.items():
        if newest < STEPS - 1:               # returned before the flush
            assert lag <= newest - k <= math.ceil(lag + block_steps)   # one step a second
            late_returned += 1
        np.testing.assert_allclose(state, exact_given[newest][k], atol=1e-9)
    assert late_returned >= STEPS - lag - block_steps - 1
    assert rec.kept == 1 and len(rec) == STEPS
    # a lag over the filter's own (lag 0) is a different, smoothed estimate
    if lag:
        assert not np.allclose(returned[0][0], _batch_mean(z[:1])[0], atol=1e-3)


def test_the_window_stays_bounded_by_the_lag_and_block():
    z = _truth_and_measurements(np.random.default_rng(SEED + 1))
    rec = FixedLagSmoother(2, slice(1, 2), 4e9, 2e9)
    x, p = np.zeros(2), np.eye(2)
    most = 0
    for k in range(len(z)):
        rec.update(k * 10 ** 9, x, p, x, p)
        rec.hold(k)
        most = max(most, rec.kept)
        rec.due()
    assert most == 4 + 2 + 1


def test_holding_before_any_update_is_a_lookup_error_and_a_negative_lag_a_value_error():
    with pytest.raises(LookupError):
        FixedLagSmoother(2, slice(1, 2), 1e9).hold("x")
    with pytest.raises(ValueError):
        FixedLagSmoother(2, slice(1, 2), -1.0)

"""The Rauch-Tung-Striebel smoother (``services/localizer_smoother.py``) against the exact
answer of a linear Gaussian model: a random walk seen through a decaying correlated
error, the shape of the localizer's bias and GNSS-error states.  Its smoothed means must
equal the conditional mean of every state given every measurement, computed at once."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.localizer_smoother import RtsRecorder

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


def _filtered(z):
    """A linear Kalman filter over state (walk, error), recording into an RtsRecorder."""
    rec = RtsRecorder(2, slice(1, 2))
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
        rec.update(x, p, x_new, p_new)
        x, p = x_new, p_new
    return rec


def _batch_mean(z):
    """E[states | all z] from the joint Gaussian of every state and measurement."""
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
    h = np.zeros((STEPS, n))
    h[np.arange(STEPS), 2 * np.arange(STEPS)] = 1.0
    h[np.arange(STEPS), 2 * np.arange(STEPS) + 1] = 1.0
    s = h @ cov @ h.T + WHITE_SD ** 2 * np.eye(STEPS)
    return (cov @ h.T @ np.linalg.solve(s, z)).reshape(STEPS, 2)


def test_smoothed_means_are_the_conditional_means_given_every_measurement():
    print(f"smoother test seed {SEED}")
    z = _truth_and_measurements(np.random.default_rng(SEED))
    rec = _filtered(z)
    smoothed = rec.smoothed_states()
    exact = _batch_mean(z)
    np.testing.assert_allclose(smoothed, exact, atol=1e-9)
    # the filter's own last estimate is the smoothed one; earlier ones differ
    assert not np.allclose(smoothed[: STEPS // 2], np.array(rec._x_post[: STEPS // 2]),
                           atol=1e-3)


def test_nothing_recorded_is_a_lookup_error():
    with pytest.raises(LookupError):
        RtsRecorder(2, slice(1, 2)).smoothed_states()

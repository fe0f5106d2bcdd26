"""A fixed-lag Rauch-Tung-Striebel smoother over the updates of :class:`LocalizerFilter`.

The filter's estimate at a time uses only the measurements up to it.  An estimate held
back until the filter is ``lag_ns`` past it can use the fixes after it too: the
localizer publishes each pose that late, smoothed (``--smooth-lag``).

:class:`FixedLagSmoother`, attached to a filter (``LocalizerFilter.recorder``), keeps
each accepted update's prior and posterior and the state transition since the update
before.  :meth:`~FixedLagSmoother.hold` parks a payload (an estimate to publish) at the
latest update; :meth:`~FixedLagSmoother.due` runs the backward pass from the newest
update and returns each held payload that is ``lag_ns`` old with its smoothed state,
then forgets the updates no held payload needs.  The pass runs once the oldest held
payload is ``lag_ns + block_ns`` old, so each update is smoothed about
``(lag + block) / block`` times; ``due(flush=True)`` returns every held payload (at the
end of a run: smoothed over all of it).

The filter's transition between updates is linear: the joints and the biases are random
walks (identity), the correlated GNSS error decays by ``exp(-dt / tau)``; everything else
the filter does between two updates (process noise, the biases' drift with motion, a
re-opened bias covariance) only adds covariance, which the next update's recorded prior
holds.  So the backward step is the linear one,
``x_s[k] = x[k] + C (x_s[k+1] - x_prior[k+1])`` with
``C = P[k] F' P_prior[k+1]^-1``, for the means; the covariances are not smoothed.
Memory: about 1.4 kB per update in the window (two 9 x 9 covariances).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

__all__ = ["FixedLagSmoother"]


class FixedLagSmoother:
    """The recent updates of one filter run, and the payloads held for smoothing.

    Parameters
    ----------
    n_state : int
        The filter's state size.
    decaying : slice
        The states the transition decays (the correlated GNSS error); the rest are
        random walks.
    lag_ns : float
        How far past a held payload's update the newest update must be before the
        payload is returned (ns; ``math.inf``: only on flush).
    block_ns : float, optional
        How much older than ``lag_ns`` the oldest held payload waits, so that one
        backward pass returns a block of them (ns; default ``lag_ns / 2``).
    """

    def __init__(self, n_state: int, decaying: slice, lag_ns: float,
                 block_ns: float | None = None) -> None:
        if not lag_ns >= 0:
            raise ValueError(f"lag_ns must be >= 0, got {lag_ns}")
        self.n_state = int(n_state)
        self.lag_ns = float(lag_ns)
        self.block_ns = float(lag_ns / 2 if block_ns is None else block_ns)
        self._decaying = decaying
        self._decay = 1.0
        self._base = 0                    # the run index of the first update kept
        self._t_ns: list[int] = []
        self._decays: list[float] = []
        self._x_prior: list[np.ndarray] = []
        self._p_prior: list[np.ndarray] = []
        self._x_post: list[np.ndarray] = []
        self._p_post: list[np.ndarray] = []
        self._held: deque[tuple[int, int, Any]] = deque()   # (run index, t_ns, payload)

    def __len__(self) -> int:
        """Updates recorded over the run (not only those kept)."""
        return self._base + len(self._x_post)

    @property
    def kept(self) -> int:
        """Updates kept in memory now."""
        return len(self._x_post)

    @property
    def held(self) -> int:
        """Payloads held, not yet returned."""
        return len(self._held)

    def transition(self, decay: float) -> None:
        """The filter predicted: the decaying states were multiplied by ``decay``."""
        self._decay *= float(decay)

    def update(self, t_ns: int, x_prior, p_prior, x_post, p_post) -> None:
        """The filter fused a measurement at ``t_ns`` (UTC ns): its state and covariance
        before and after."""
        self._t_ns.append(int(t_ns))
        self._decays.append(self._decay)
        self._decay = 1.0
        self._x_prior.append(np.array(x_prior, float))
        self._p_prior.append(np.array(p_prior, float))
        self._x_post.append(np.array(x_post, float))
        self._p_post.append(np.array(p_post, float))

    def hold(self, payload: Any) -> None:
        """Hold ``payload`` at the latest update; LookupError before the first."""
        if not self._x_post:
            raise LookupError("no update recorded")
        self._held.append((len(self) - 1, self._t_ns[-1], payload))

    def due(self, *, flush: bool = False) -> list[tuple[Any, np.ndarray]]:
        """The held payloads now due, oldest first, each with its smoothed state
        ((n_state,) array): those ``lag_ns`` older than the newest update, once the
        oldest is ``lag_ns + block_ns`` old; every one with ``flush``."""
        if not self._held:
            self._forget(len(self) - 1)
            return []
        newest_ns = self._t_ns[-1]
        if not flush and (math.isinf(self.lag_ns)
                          or newest_ns - self._held[0][1] < self.lag_ns + self.block_ns):
            return []
        first = self._held[0][0] - self._base
        states = self._backward(first)
        out = []
        while self._held and (flush or newest_ns - self._held[0][1] >= self.lag_ns):
            index, _t_ns, payload = self._held.popleft()
            out.append((payload, states[index - self._base - first]))
        self._forget(self._held[0][0] if self._held else len(self) - 1)
        return out

    def _backward(self, first: int) -> np.ndarray:
        """The smoothed states of the kept updates from ``first`` (a kept index) to the
        newest, shape (kept - first, n_state)."""
        m = len(self._x_post)
        out = np.empty((m - first, self.n_state))
        out[-1] = self._x_post[-1]
        for k in range(m - 2, first - 1, -1):
            f = np.ones(self.n_state)
            f[self._decaying] = self._decays[k + 1]
            # C = P[k] F' P_prior[k+1]^-1, P_prior symmetric: C' = P_prior^-1 (F P[k])
            fp = f[:, None] * self._p_post[k]
            try:
                c_t = np.linalg.solve(self._p_prior[k + 1], fp)
            except np.linalg.LinAlgError:
                c_t = np.linalg.lstsq(self._p_prior[k + 1], fp, rcond=None)[0]
            out[k - first] = self._x_post[k] + c_t.T @ (out[k + 1 - first]
                                                         - self._x_prior[k + 1])
        return out

    def _forget(self, keep_from: int) -> None:
        """Drop the updates before run index ``keep_from``."""
        n = keep_from - self._base
        if n <= 0:
            return
        for seq in (self._t_ns, self._decays, self._x_prior, self._p_prior, self._x_post,
                    self._p_post):
            del seq[:n]
        self._base = keep_from

"""A Rauch-Tung-Striebel smoother over a recorded run of :class:`LocalizerFilter`.

The filter's estimate at a time uses only the measurements up to it; a scan placed long
after it was taken (a recorded run, a ledger imported later) can use the fixes after it
too.  :class:`RtsRecorder`, attached to a filter (``LocalizerFilter.recorder``), keeps
each accepted update's prior and posterior and the state transition since the update
before; :meth:`RtsRecorder.smoothed_states` runs the backward pass and returns every
update's smoothed state.

The filter's transition between updates is linear: the joints, the biases are random
walks (identity), the correlated GNSS error decays by ``exp(-dt / tau)``; everything else
the filter does between two updates (process noise, the biases' drift with motion, a
re-opened bias covariance) only adds covariance, which the next update's recorded prior
holds.  So the backward step is the linear one,
``x_s[k] = x[k] + C (x_s[k+1] - x_prior[k+1])`` with
``C = P[k] F' P_prior[k+1]^-1``, for the means; the covariances are not smoothed.
Memory: about 1.4 kB per update (two 9 x 9 covariances), for one recorded run.
"""

from __future__ import annotations

import numpy as np

__all__ = ["RtsRecorder"]


class RtsRecorder:
    """The updates of one filter run, for :meth:`smoothed_states`.

    Parameters
    ----------
    n_state : int
        The filter's state size.
    decaying : slice
        The states the transition decays (the correlated GNSS error); the rest are
        random walks.
    """

    def __init__(self, n_state: int, decaying: slice) -> None:
        self.n_state = int(n_state)
        self._decaying = decaying
        self._decay = 1.0
        self._decays: list[float] = []
        self._x_prior: list[np.ndarray] = []
        self._p_prior: list[np.ndarray] = []
        self._x_post: list[np.ndarray] = []
        self._p_post: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._x_post)

    def transition(self, decay: float) -> None:
        """The filter predicted: the decaying states were multiplied by ``decay``."""
        self._decay *= float(decay)

    def update(self, x_prior, p_prior, x_post, p_post) -> None:
        """The filter fused a measurement: its state and covariance before and after."""
        self._decays.append(self._decay)
        self._decay = 1.0
        self._x_prior.append(np.array(x_prior, float))
        self._p_prior.append(np.array(p_prior, float))
        self._x_post.append(np.array(x_post, float))
        self._p_post.append(np.array(p_post, float))

    def smoothed_states(self) -> np.ndarray:
        """Every recorded update's smoothed state, shape (updates, n_state).

        Raises
        ------
        LookupError
            If nothing was recorded.
        """
        m = len(self._x_post)
        if m == 0:
            raise LookupError("no update recorded")
        out = np.empty((m, self.n_state))
        out[-1] = self._x_post[-1]
        for k in range(m - 2, -1, -1):
            f = np.ones(self.n_state)
            f[self._decaying] = self._decays[k + 1]
            # C = P[k] F' P_prior[k+1]^-1, P_prior symmetric: C' = P_prior^-1 (F P[k])
            fp = f[:, None] * self._p_post[k]
            try:
                c_t = np.linalg.solve(self._p_prior[k + 1], fp)
            except np.linalg.LinAlgError:
                c_t = np.linalg.lstsq(self._p_prior[k + 1], fp, rcond=None)[0]
            out[k] = self._x_post[k] + c_t.T @ (out[k + 1] - self._x_prior[k + 1])
        return out

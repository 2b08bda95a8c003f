"""Ridge regression of the cloud-side cost on per-action context vectors, updated online.

α̂ = Q⁻¹p with Q = γI + Σ v vᵀ and p = Σ v y. Only Q⁻¹ is kept, current through the
Sherman–Morrison identity, so an update costs O(d²) and no inverse is ever computed. The
predictions α̂ᵀv_a and the widths sqrt(v_aᵀQ⁻¹v_a) of every action change only when Q does, so
they are cached at update time and a decision only reads them.
"""

from __future__ import annotations

import numpy as np

from robotd.policies.base import FloatArray

# Recompute the cached quadratic forms from Q⁻¹ this often, so incremental round-off cannot pile up.
EXACT_REFRESH_SAMPLES = 1024


class RidgeEstimator:
    """Online ridge regression over a fixed set of context vectors (one row per action)."""

    def __init__(self, contexts: FloatArray, gamma: float) -> None:
        if contexts.ndim != 2:
            raise ValueError("contexts must be a (actions, d) matrix")
        self.contexts = np.ascontiguousarray(contexts, dtype=np.float64)
        self.gamma = float(gamma)
        self.d = self.contexts.shape[1]
        self.q_inv = np.empty((self.d, self.d))
        self.p = np.empty(self.d)
        self.alpha = np.empty(self.d)
        self.pred = np.empty(self.contexts.shape[0])
        self.width = np.empty(self.contexts.shape[0])
        self._quad = np.empty(self.contexts.shape[0])
        self.samples = 0
        self.reset()

    def reset(self) -> None:
        """Forget all evidence: Q = γI, p = 0."""
        self.q_inv = np.eye(self.d) / self.gamma
        self.p = np.zeros(self.d)
        self.samples = 0
        self.refresh()

    def update(self, row: int, y: float) -> None:
        """Add the observation y for the action in `row`."""
        self.update_vector(self.contexts[row], y)

    def update_vector(self, v: FloatArray, y: float) -> None:
        """Add the observation y for context v (Sherman–Morrison on Q⁻¹)."""
        qv = self.q_inv @ v
        scale = 1.0 / (1.0 + float(v @ qv))
        self.q_inv -= np.multiply.outer(qv, qv * scale)
        self.p += v * y
        self.samples += 1
        if self.samples % EXACT_REFRESH_SAMPLES == 0:
            self.refresh()
            return
        # The same identity updates every action's quadratic form v_aᵀQ⁻¹v_a in O(K·d).
        u = self.contexts @ qv
        self._quad -= u * u * scale
        self._predict()

    def refresh(self) -> None:
        """Recompute α̂ and the cached per-action predictions and widths from Q⁻¹."""
        self._quad = np.einsum("ij,jk,ik->i", self.contexts, self.q_inv, self.contexts)
        self._predict()

    def _predict(self) -> None:
        self.alpha = self.q_inv @ self.p
        self.pred = self.contexts @ self.alpha
        # Round-off can leave a tiny negative quadratic form once Q is large.
        self.width = np.sqrt(np.maximum(self._quad, 0.0))

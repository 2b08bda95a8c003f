"""Ridge regression of the cloud-side cost on per-action context vectors, updated online.

α̂ = Q⁻¹p with Q = γI + Σ v vᵀ and p = Σ v y. Only Q⁻¹ is kept, current through the
Sherman–Morrison identity, so an update costs O(d²) and no inverse is ever computed.

An update runs once per offloaded frame with d = 3, where a numpy call costs more than the
arithmetic it does: Q⁻¹ (row-major), p and α̂ are plain Python floats, updated by unrolled
arithmetic for d = 3 (loops otherwise). Every action's prediction α̂ᵀv_a and quadratic form
v_aᵀQ⁻¹v_a are linear in [α̂, vec Q⁻¹] (`coefficients()`), so one matrix-vector product with a
fixed feature matrix (`quadratic_features`) gives them all, exactly, whenever they are needed.
"""

from __future__ import annotations

from operator import mul

import numpy as np

from robotd.policies.base import FloatArray


def quadratic_features(contexts: FloatArray) -> FloatArray:
    """(actions, d²) matrix whose row a is vec(v_a v_aᵀ), so row · vec Q⁻¹ = v_aᵀQ⁻¹v_a."""
    k, d = contexts.shape
    return np.einsum("ai,aj->aij", contexts, contexts).reshape(k, d * d)


class RidgeEstimator:
    """Online ridge regression over a fixed set of context vectors (one row per action).

    `alpha` and `p` are lists of d floats (read them, do not modify them).
    """

    def __init__(self, contexts: FloatArray, gamma: float) -> None:
        if contexts.ndim != 2:
            raise ValueError("contexts must be a (actions, d) matrix")
        self.contexts = np.ascontiguousarray(contexts, dtype=np.float64)
        self.gamma = float(gamma)
        self.d = self.contexts.shape[1]
        self._rows: list[list[float]] = self.contexts.tolist()
        self._pairs = quadratic_features(self.contexts)
        self._q: list[float] = []  # Q⁻¹, row-major
        self.p: list[float] = []
        self.alpha: list[float] = []
        self.samples = 0
        self.reset()

    @property
    def q_inv(self) -> FloatArray:
        """Q⁻¹ as a (d, d) array (a copy, for inspection)."""
        return np.array(self._q).reshape(self.d, self.d)

    @property
    def pred(self) -> FloatArray:
        """α̂ᵀv_a of every action."""
        return self.contexts @ np.array(self.alpha)

    @property
    def width(self) -> FloatArray:
        """Confidence width sqrt(v_aᵀQ⁻¹v_a) of every action."""
        # Round-off can leave a tiny negative quadratic form once Q is large.
        return np.sqrt(np.maximum(self._pairs @ np.array(self._q), 0.0))

    def coefficients(self) -> list[float]:
        """[α̂, vec Q⁻¹]: the predictions are `contexts @ [:d]`, the quadratic forms
        `quadratic_features(contexts) @ [d:]`."""
        return self.alpha + self._q

    def reset(self) -> None:
        """Forget all evidence: Q = γI, p = 0."""
        d = self.d
        diag = 1.0 / self.gamma
        self._q = [diag if i == j else 0.0 for i in range(d) for j in range(d)]
        self.p = [0.0] * d
        self.alpha = [0.0] * d
        self.samples = 0

    def set_context(self, row: int, v: FloatArray | list[float]) -> None:
        """Replace the context of the action in `row` (e.g. the bytes it sends, learned online);
        the evidence gathered so far is kept."""
        self.contexts[row] = v
        self._rows[row] = [float(x) for x in v]
        self._pairs[row] = quadratic_features(self.contexts[row : row + 1])[0]

    def update(self, row: int, y: float) -> None:
        """Add the observation y for the action in `row`."""
        # float(): numpy scalars would make every later operation on Q⁻¹, p and α̂ slower.
        self._add(self._rows[row], float(y))

    def update_vector(self, v: FloatArray | list[float], y: float) -> None:
        """Add the observation y for context v."""
        self._add([float(x) for x in v], float(y))

    def _add(self, v: list[float], y: float) -> None:
        """Q⁻¹ ← Q⁻¹ − (Q⁻¹v)(Q⁻¹v)ᵀ / (1 + vᵀQ⁻¹v) (Sherman–Morrison), p ← p + v·y, α̂ = Q⁻¹p."""
        self.samples += 1
        if self.d != 3:
            self._add_any(v, y)
            return
        q00, q01, q02, q10, q11, q12, q20, q21, q22 = self._q
        v0, v1, v2 = v
        a0 = q00 * v0 + q01 * v1 + q02 * v2
        a1 = q10 * v0 + q11 * v1 + q12 * v2
        a2 = q20 * v0 + q21 * v1 + q22 * v2
        scale = 1.0 / (1.0 + (v0 * a0 + v1 * a1 + v2 * a2))
        b0, b1, b2 = a0 * scale, a1 * scale, a2 * scale
        q00, q01, q02 = q00 - a0 * b0, q01 - a0 * b1, q02 - a0 * b2
        q10, q11, q12 = q10 - a1 * b0, q11 - a1 * b1, q12 - a1 * b2
        q20, q21, q22 = q20 - a2 * b0, q21 - a2 * b1, q22 - a2 * b2
        self._q = [q00, q01, q02, q10, q11, q12, q20, q21, q22]
        p0, p1, p2 = self.p
        p0, p1, p2 = p0 + v0 * y, p1 + v1 * y, p2 + v2 * y
        self.p = [p0, p1, p2]
        self.alpha = [
            q00 * p0 + q01 * p1 + q02 * p2,
            q10 * p0 + q11 * p1 + q12 * p2,
            q20 * p0 + q21 * p1 + q22 * p2,
        ]

    def _add_any(self, v: list[float], y: float) -> None:
        """`_add` for any d."""
        d = self.d
        rows = [self._q[i * d : (i + 1) * d] for i in range(d)]
        qv = [sum(map(mul, row, v)) for row in rows]
        scale = 1.0 / (1.0 + sum(map(mul, v, qv)))
        scaled = [x * scale for x in qv]
        rows = [
            [q - a * b for q, b in zip(row, scaled, strict=True)]
            for row, a in zip(rows, qv, strict=True)
        ]
        self._q = [q for row in rows for q in row]
        self.p = [p + x * y for p, x in zip(self.p, v, strict=True)]
        self.alpha = [sum(map(mul, row, self.p)) for row in rows]

"""One set of ElasticAction's score parts (`robotd.policies.elastic`) and the choices they give."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field


@dataclass
class Scores:
    """Score parts, cut order: `base` = E^c + bytes cost + α̂ᵀv, `pred` = α̂ᵀv, `width` =
    sqrt(vᵀQ⁻¹v), `allowed` = `base` with inf where the direction restriction left the action
    out; a frame's score = allowed − sqrt(1−σ)·β·E_P·width.

    The parts change only when the policy learns, and σ takes two values: `choose` then sets
    the best score for key and for other frames and the cheapest allowed action, so each
    frame's choice is ready before the frame comes and `decide` costs the same for 4 actions
    or 64. Pairs are (value, column; the first of equal ones)."""

    base: list[float] = field(default_factory=list)
    pred: list[float] = field(default_factory=list)
    width: list[float] = field(default_factory=list)
    allowed: list[float] = field(default_factory=list)
    best_key: tuple[float, int] = (math.inf, 0)
    best_nonkey: tuple[float, int] = (math.inf, 0)
    cheapest: tuple[float, int] = (math.inf, 0)

    def choose(self, mask: Sequence[bool] | None, key_bonus: float, nonkey_bonus: float) -> None:
        """Restrict `base` to the actions `mask` allows (None: all) and choose; `*_bonus`:
        sqrt(1−σ)·β·E_P of key and of other frames."""
        base = self.base
        self.allowed = (
            base
            if mask is None
            else [b if ok else math.inf for b, ok in zip(base, mask, strict=True)]
        )
        self.best_key = self._best(key_bonus)
        self.best_nonkey = self._best(nonkey_bonus)
        cheapest = min(self.allowed)
        self.cheapest = (cheapest, self.allowed.index(cheapest))

    def _best(self, bonus: float) -> tuple[float, int]:
        """The lowest score at this exploration bonus per unit of width, and its column."""
        # Equal lengths by construction (strict=True would cost a check on every refresh).
        scores = [b - bonus * w for b, w in zip(self.allowed, self.width, strict=False)]
        best = min(scores)
        return best, scores.index(best)

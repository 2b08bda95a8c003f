"""What a video action's keyframe costs ElasticAction (`robotd.policies.elastic`), learned apart.

A keyframe sends several times a P-frame's bytes. Each video action keeps its keyframes' bytes
(`CutTable.keys`, then learned from the keyframes sent) and their cloud-side cost as an excess
over the P-frame's prediction (EWMA; before the first keyframe is answered, α̂'s seconds per
context unit times its extra bytes in that unit, `segment_actions.context_unit_bytes`): a
keyframe's excess is measured directly, while the regression's bytes coefficient rests on the
P-frames and whatever else is sent.
"""

from __future__ import annotations

import math

from common.wire.tensor_codecs import is_video
from robotd.policies.base import BYTES_PER_MB, CutTable, FloatArray
from robotd.policies.objective import Objective
from robotd.policies.params import ElasticParams
from robotd.policies.ridge import RidgeEstimator
from robotd.policies.scores import Scores


class KeyframeCosts:
    """The video actions' keyframe bytes and cost excess, and the scores they give a frame
    whose video frame would be a keyframe. `contexts` and `p_bytes` (the P-frames' learned
    bytes) are the policy's, read as they move."""

    def __init__(
        self,
        cuts: CutTable,
        params: ElasticParams,
        objective: Objective,
        ridge: RidgeEstimator,
        contexts: FloatArray,
        p_bytes: list[float],
        unit: float = BYTES_PER_MB,
    ) -> None:
        self.video = [j for j, codec in enumerate(cuts.codecs) if is_video(codec)]
        self.key_bytes: list[float] = list(cuts.keys)
        # Each one's keyframe cost over its P-frame's prediction (None: no keyframe seen yet).
        self._extra: dict[int, float | None] = dict.fromkeys(self.video)
        self._ewma = params.bytes_ewma
        self._objective = objective
        self._ridge = ridge
        self._contexts = contexts
        self._p_bytes = p_bytes
        self._unit = unit  # bytes per unit of the contexts' first column

    def learn_bytes(self, j: int, sent: int) -> None:
        """Follow the bytes video action j's keyframes really send (EWMA)."""
        if sent > 0:
            self.key_bytes[j] += self._ewma * (sent - self.key_bytes[j])

    def learn_cost(self, j: int, target: float, p_pred: float) -> None:
        """A keyframe of j cost `target` on the cloud side; its P-frame is predicted at `p_pred`."""
        excess = target - p_pred
        known = self._extra[j]
        self._extra[j] = excess if known is None else known + self._ewma * (excess - known)

    def rescore(self, frames: Scores, keyframes: Scores, learned: bool) -> None:
        """Set `keyframes`' parts from the ordinary `frames`': each video action's prediction
        moved by its keyframe's learned excess (before one was answered, its extra bytes at α̂'s
        seconds per context unit), its base cost by that and its extra bytes' cost, its width
        at its keyframe's context (`learned`: the regression changed; else the widths are kept)."""
        alpha_unit = self._ridge.alpha[0]
        base, pred = list(frames.base), list(frames.pred)
        width = list(frames.width) if learned or not keyframes.width else keyframes.width
        q_inv = self._ridge.q_inv if learned else None
        for j in self.video:
            extra_bytes = self.key_bytes[j] - self._p_bytes[j]
            known = self._extra[j]
            extra = extra_bytes / self._unit * alpha_unit if known is None else max(known, 0.0)
            base[j] += extra + extra_bytes / BYTES_PER_MB * self._objective.bytes
            pred[j] += extra
            if q_inv is not None:
                v = self._contexts[j].copy()
                v[0] = self.key_bytes[j] / self._unit
                width[j] = math.sqrt(max(float(v @ q_inv @ v), 0.0))
        keyframes.base, keyframes.pred, keyframes.width = base, pred, width

"""Sends a frame's cut tensors on the robot's anycast service key, through the emulated uplink.

`RequestSender.send` builds the frame's `InferRequest` (model digest, cut, encoded tensors,
deadline, route epoch, and for a segment the end cut) and starts a
`robotd.frame_path.offload.CloudCall` with it. With `--uplink-mbit` the request first waits its
bytes' time in a token bucket (`robotd.frame_path.pacing.TokenBucket`): a request that cannot get
through before its deadline is never sent (it would only queue ahead of the next frames; the call
still times out at the deadline, so the policy learns what that cut costs), and one that can is sent
with the deadline budget left after the emulated link.

A video frame (`h264`) carries its stream position (`video`) and, in `keyframe`, what codes it
again as a keyframe: the call resends it so when the deployment cannot decode it
(`robotd.frame_path.offload`), through the same emulated uplink, with the budget left.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import zenoh

from common.wire.robot_to_cloud import InferRequest, VideoStream
from common.wire.tensor_codecs import EncodedTensor
from robotd.frame_path.offload import CloudCall
from robotd.frame_path.pacing import TokenBucket


class RequestSender:
    """`RequestSender(session, key, robot=..., model_digest=..., deadline_s=...)`; `uplink`
    paces requests (None: sent at once); `member_key(deployment)` is the key of one member of
    the robot's round-robin pool (None: only the anycast key is used); `served(timeout_s)` waits for
    a deployment serving the key, so a query that found none is sent again within its deadline
    (`robotd.frame_path.offload.CloudCall`; None: it falls back at once)."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        *,
        robot: str,
        model_digest: str,
        deadline_s: float,
        max_reply_bytes: int,
        uplink: TokenBucket | None = None,
        member_key: Callable[[str], str] | None = None,
        served: Callable[[float], bool] | None = None,
    ) -> None:
        self._session = session
        self.key = key
        self._member_key = member_key
        self._robot = robot
        self._model_digest = model_digest
        self._deadline_s = deadline_s
        self._max_reply_bytes = max_reply_bytes
        self.uplink = uplink
        # Waits for a deployment serving the key: a query that found none is resent (a move).
        self._served = served

    def send(
        self,
        frame: int,
        cut: int,
        tensors: dict[str, EncodedTensor],
        epoch: int,
        *,
        background: bool = False,
        end: int | None = None,
        member: str | None = None,
        video: VideoStream | None = None,
        keyframe: Callable[[], tuple[dict[str, EncodedTensor], VideoStream]] | None = None,
    ) -> CloudCall:
        """Send frame `frame`'s tensors after cut index `cut`; the call is under way on return
        (`background`: handed to Zenoh from a thread of its own, see `CloudCall.start`). `end`:
        the cloud runs only the segment up to that cut and replies with its tensors. `member`:
        the pool member that computes it (round robin); None: the anycast key. `video`: the
        video tensors' stream position; `keyframe`: what codes them again as a keyframe, for a
        resend when the deployment cannot decode them."""
        request = InferRequest(
            robot=self._robot,
            frame=frame,
            model_digest=self._model_digest,
            cut=cut,
            tensors=tensors,
            deadline_s=self._deadline_s,
            sent_at=time.time(),
            epoch=epoch,
            end_cut=end,
            video=video,
        )
        payload = request.to_wire()
        delay = 0.0
        if self.uplink is not None:
            # A frame that cannot get through the emulated uplink before its deadline is not
            # sent: it would only queue ahead of the next frames (the call then times out at the
            # deadline, so the policy still learns what this cut costs).
            delay = self.uplink.delay_for(len(payload))
            if delay < self._deadline_s:
                delay = self.uplink.reserve(len(payload))
            # The encoded size does not depend on the deadline's value (a float is 9 bytes), so
            # re-encoding with the budget left after the emulated uplink keeps the size reserved.
            if 0 < delay < self._deadline_s:
                budget = self._deadline_s - delay
                payload = dataclasses.replace(request, deadline_s=budget).to_wire()
        key = self.key
        if member is not None and self._member_key is not None:
            key = self._member_key(member)
        rekey = None
        if keyframe is not None:

            def rekey(budget_s: float) -> tuple[bytes | None, float, VideoStream]:
                return self._keyframe_payload(request, keyframe, budget_s)

        call = CloudCall(
            self._session,
            key,
            payload,
            frame=frame,
            budget_s=self._deadline_s,
            delay_s=delay,
            max_reply_bytes=self._max_reply_bytes,
            served=self._served,
            video=video,
            rekey=rekey,
        )
        call.start(background=background)
        return call

    def _keyframe_payload(
        self,
        request: InferRequest,
        keyframe: Callable[[], tuple[dict[str, EncodedTensor], VideoStream]],
        budget_s: float,
    ) -> tuple[bytes | None, float, VideoStream]:
        """`request` again with its video tensors coded as a keyframe, its deadline the
        `budget_s` left: (its payload, its emulated uplink delay, its stream position); the
        payload None when the uplink cannot carry it within the budget (the frame is then
        finished on the robot, and the keyframe's stream marked unseen by the frame loop)."""
        tensors, video = keyframe()
        again = dataclasses.replace(
            request, tensors={**request.tensors, **tensors}, video=video, deadline_s=budget_s
        )
        payload = again.to_wire()
        delay = 0.0
        if self.uplink is not None:
            if self.uplink.delay_for(len(payload)) >= budget_s:
                return None, 0.0, video
            delay = self.uplink.reserve(len(payload))
            if delay > 0:
                payload = dataclasses.replace(again, deadline_s=budget_s - delay).to_wire()
        return payload, delay, video

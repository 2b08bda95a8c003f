"""`nav assist` on real Zenoh sessions: operator Twists on one rmw_zenoh topic, the robot's d_coll
(a Float32MultiArray with its frame's stamp in the attachment, as the robot publishes it), safe
Twists out on another; the node and its topics are on the ROS 2 graph."""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Callable

import numpy as np
import zenoh

from common import rmw_zenoh
from common.ros2_messages import (
    MessageType,
    Twist,
    decode_twist,
    encode_float32_multi_array,
    encode_twist,
)
from deploy.readiness import wait_until
from nav.assist import AssistNode

WAIT_S = 10.0
PREFIX = "/elasticfog/robot_1"


def _key(topic: str, message: MessageType) -> str:
    return rmw_zenoh.topic_key(0, topic, rmw_zenoh.TopicType.of(message.value))


def _wait_tokens(session: zenoh.Session, patterns: list[str]) -> None:
    """Wait until a liveliness token matching each pattern is alive (or fail naming those not)."""
    seen: set[str] = set()
    done = threading.Event()

    def on_token(sample: zenoh.Sample) -> None:
        key = zenoh.KeyExpr(str(sample.key_expr))
        seen.update(p for p in patterns if zenoh.KeyExpr(p).intersects(key))
        if len(seen) == len(patterns):
            done.set()

    sub = session.liveliness().declare_subscriber("@ros2_lv/**", on_token, history=True)
    try:
        assert done.wait(WAIT_S), f"no token for {sorted(set(patterns) - seen)}"
    finally:
        sub.undeclare()


def test_safe_commands_follow_d_coll(open_peer: Callable[..., zenoh.Session]) -> None:
    assist_session, peer = open_peer(), open_peer()
    node = AssistNode(
        assist_session,
        domain=0,
        robot="robot-1",
        results_prefix=PREFIX,
        cmd_in="/cmd_vel_teleop",
        cmd_out="/cmd_vel",
    )
    out: queue.Queue[Twist] = queue.Queue()
    sub = peer.declare_subscriber(
        _key("/cmd_vel", MessageType.TWIST),
        lambda s: out.put(decode_twist(s.payload.to_bytes())),
    )
    cmd_key = _key("/cmd_vel_teleop", MessageType.TWIST)
    d_coll_key = _key(f"{PREFIX}/d_coll", MessageType.FLOAT32_MULTI_ARRAY)
    try:
        # The assistant's tokens are on the graph (what `ros2 node list` reads).
        graph = "@ros2_lv/0/*/0"
        _wait_tokens(
            peer,
            [
                f"{graph}/0/NN/%/%/elasticfog_assist_robot_1",
                f"{graph}/*/MP/%/%/elasticfog_assist_robot_1/%cmd_vel/**",
                f"{graph}/*/MS/%/%/elasticfog_assist_robot_1/%cmd_vel_teleop/**",
            ],
        )
        # Until matched, commands may not arrive: publish until the first safe command comes.
        forward = encode_twist(Twist((0.3, 0.0, 0.0), (0.0, 0.0, 0.0)))
        first = None
        deadline = time.monotonic() + WAIT_S
        while first is None and time.monotonic() < deadline:  # bounded
            peer.put(cmd_key, forward)
            with contextlib.suppress(queue.Empty):
                first = out.get(timeout=0.2)
        assert first is not None, "no safe command"
        assert first.linear[0] == 0.0, "no d_coll yet: no forward motion"
        # A near obstacle, from a frame captured now: the command is limited, not stopped.
        gid = bytes(16)
        # Stamped half a second ahead, so that the time a message takes on a loaded host does not
        # count as the robot's motion since the frame (the age counts from 0): s_j = d_coll.
        stamp = time.time_ns() + 500_000_000
        attachment = rmw_zenoh.Attachment(1, stamp, gid).encode()
        d_coll = encode_float32_multi_array(np.full((1, 31), 0.002, np.float32))
        deadline = time.monotonic() + WAIT_S
        limited = 0.0
        while not 0.0 < limited < 0.3 and time.monotonic() < deadline:  # bounded
            peer.put(d_coll_key, d_coll, attachment=attachment)
            peer.put(cmd_key, forward)
            limited = out.get(timeout=WAIT_S).linear[0]
        assert 0.0 < limited < 0.3, limited
        # Garbage on both topics: refused by name, nothing forwarded for it: every safe command
        # out since is one of the good commands put before (regression: counting forwards raced
        # with a good command still in flight).
        peer.put(cmd_key, b"\x00\x01\x00\x00\x01")
        peer.put(d_coll_key, b"garbage", attachment=attachment)
        wait_until(lambda: node.refused >= 2 or None, timeout_s=WAIT_S, what="2 refusals")
        assert node.refused == 2
        while not out.empty():  # bounded: what was forwarded, no more
            late = out.get_nowait()
            assert 0.0 <= late.linear[0] <= 0.3 and late.angular == (0.0, 0.0, 0.0), late
    finally:
        sub.undeclare()
        node.close()


def test_stamped_commands_keep_their_header_and_a_future_stamp_is_refused(
    open_peer: Callable[..., zenoh.Session],
) -> None:
    """`--stamped`: TwistStamped in and out, each safe command with its command's header; a
    command stamped ahead of this host's clock is refused by name and not forwarded."""
    from common.ros2_messages import Header, decode_twist_stamped, encode_twist_stamped

    assist_session, peer = open_peer(), open_peer()
    node = AssistNode(
        assist_session,
        domain=0,
        robot="robot-1",
        results_prefix=PREFIX,
        cmd_in="/cmd_vel_nav",
        cmd_out="/cmd_vel",
        stamped=True,
    )
    out: queue.Queue[tuple[Header, Twist]] = queue.Queue()
    sub = peer.declare_subscriber(
        _key("/cmd_vel", MessageType.TWIST_STAMPED),
        lambda s: out.put(decode_twist_stamped(s.payload.to_bytes())),
    )
    cmd_key = _key("/cmd_vel_nav", MessageType.TWIST_STAMPED)
    try:
        _wait_tokens(
            peer,
            [
                "@ros2_lv/0/*/0/*/MS/%/%/elasticfog_assist_robot_1/%cmd_vel_nav/"
                "geometry_msgs::msg::dds_::TwistStamped_/**"
            ],
        )
        reverse = Twist((-0.2, 0.0, 0.0), (0.0, 0.0, 0.0))  # reverse passes unchanged
        got = None
        deadline = time.monotonic() + WAIT_S
        while got is None and time.monotonic() < deadline:  # bounded
            header = Header(time.time_ns(), "base_link")
            peer.put(cmd_key, encode_twist_stamped(reverse, header))
            with contextlib.suppress(queue.Empty):
                got = out.get(timeout=0.2)
        assert got is not None, "no safe command"
        assert got[1] == reverse and got[0].frame_id == "base_link"
        future = Header(time.time_ns() + 5_000_000_000, "base_link")
        peer.put(cmd_key, encode_twist_stamped(reverse, future))
        wait_until(lambda: node.refused >= 1 or None, timeout_s=WAIT_S, what="the refusal")
        while not out.empty():  # bounded: commands forwarded before, never the future one
            assert out.get_nowait()[0].stamp_ns != future.stamp_ns
    finally:
        sub.undeclare()
        node.close()

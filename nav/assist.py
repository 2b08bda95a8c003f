"""`elasticfog nav assist`: the navigation assistant as a ROS 2 safety filter on `cmd_vel`.

The operator's `geometry_msgs/msg/Twist` comes in on `--cmd-in` (e.g. `/cmd_vel_teleop`, from a
joystick or `teleop_twist_keyboard`); the safe command goes out on `--cmd-out` (`/cmd_vel`, what
the robot's base drives by). Between them, the shared control of `nav.shared_control`: the
Twist's forward speed `linear.x` and turn rate `angular.z` are the joystick's (v_j, ω_j), limited
with the newest d_coll(K) the fleet computed for the robot's stereo frames so that the robot can
stop before the obstacle on its path, on the same path (ω scaled with v). The other components
(`linear.y`, `linear.z`, `angular.x`, `angular.y`) pass unchanged.

d_coll comes from the robot's results on ROS 2 (`results: {ros2: PREFIX}` on a robot running
`zoo:stereo`): the `Float32MultiArray` on `PREFIX/d_coll` (one distance per curvature bin: the
bins the fleet's model names in its metadata, `nav.bins.k_max_per_m` and `nav.bins.count`, else
`nav.curvature.CurvatureBins`' default k_max with as many bins as values), its frame's capture
stamp in the rmw_zenoh attachment's source timestamp. An older frame than the one
held is ignored. The stamps are wall-clock time of the camera's host: its clock and this host's
must agree (NTP/PTP) within a fraction of the deadline.

With no d_coll newer than the deadline (`--deadline-s`, default 1 s: the cloud is late, the robot
stopped publishing, nothing came yet), forward speed ramps down from the last speed sent at
`--deadline-decel` (1 m/s²) to a stop; before the first d_coll the robot does not move forward.
Reverse motion and turns on the spot pass unchanged (a frontal camera says nothing about them).
One safe command is published per operator command: if the operator stops publishing, so does
the assistant (a base stops on its own `cmd_vel` timeout).

With `stamped` (`--stamped`) the commands are `geometry_msgs/msg/TwistStamped` on both topics
(Nav2's `enable_stamped_cmd_vel`, ros2_control's controllers): each safe command carries its
operator command's header. A command stamped more than `MAX_FUTURE_S` ahead of this host's clock
is refused (`FutureStamp`): its clock and the operator's disagree, so its age means nothing.

Which session: the robot's ROS 2 settings (`FleetConfig.ros2_for`): with `ros2.endpoint` the
assistant speaks ROS 2 on a session of its own to that router (the robot host's rmw_zenohd) and
opens no fleet session at all; without it, on a fleet session as before.

Bad input (a Twist or d_coll that does not decode, a non-finite velocity, a d_coll of the wrong
length, a future stamp) is one throttled line naming it; the command is not forwarded (nothing
unsafe is sent).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from common import rmw_zenoh
from common.errors import UserError
from common.ros2_messages import (
    Header,
    MessageType,
    Ros2MessageError,
    Twist,
    decode_float32_multi_array,
    decode_twist,
    decode_twist_stamped,
    encode_twist,
    encode_twist_stamped,
    typestore,
)
from common.throttled_log import ThrottledLog
from common.wire.errors import ErrorCode
from nav.curvature import CurvatureBins, DcollProfile
from nav.shared_control import AssistantParams, Command, Limit, SharedControl

if TYPE_CHECKING:
    import zenoh

    from common.config import FleetConfig
    from robotd.ros2_node import Ros2Node, Ros2Publisher, Ros2Subscription

log = logging.getLogger("nav.assist")

D_COLL_OUTPUT = "d_coll"
NS_PER_S = 1e9
# A TwistStamped may be stamped this far ahead of this host's clock (clocks synchronized by
# NTP/PTP agree much better); past it the command is refused.
MAX_FUTURE_S = 0.5


class FutureStamp(Ros2MessageError):
    """A command stamped ahead of this host's clock by more than MAX_FUTURE_S."""

    code = ErrorCode.BAD_VALUE


def check_stamp(header: Header, now_ns: int, max_future_s: float = MAX_FUTURE_S) -> None:
    """FutureStamp when `header` is stamped more than `max_future_s` after `now_ns`."""
    ahead_s = (header.stamp_ns - now_ns) / NS_PER_S
    if ahead_s > max_future_s:
        raise FutureStamp(
            f"command stamped {ahead_s:.3f} s ahead of this host's clock (at most "
            f"{max_future_s} s): the clocks disagree"
        )


@dataclass(frozen=True)
class SafeCommand:
    """The Twist to send and why it differs from the operator's (Limit.NONE: it does not)."""

    twist: Twist
    limit: Limit


class TeleopAssist:
    """Operator Twists in, safe Twists out, with the newest d_coll (see the module docstring).
    Thread-safe: d_coll and commands arrive on different Zenoh threads."""

    def __init__(
        self, params: AssistantParams | None = None, bins: CurvatureBins | None = None
    ) -> None:
        self.control = SharedControl(params=params)
        self.bins = bins
        self._lock = threading.Lock()
        self.limit = Limit.NONE

    def observe(self, d_coll: np.ndarray, stamp_ns: int) -> bool:
        """Take d_coll of the frame captured at `stamp_ns` (ns since the epoch); False when it
        is older than the one held. A UserError for values that are not one distance per bin."""
        values = np.asarray(d_coll, dtype=np.float64).reshape(-1)
        if self.bins is None and (values.size < 3 or values.size % 2 == 0):
            raise UserError(f"d_coll has {values.size} values; expected an odd number >= 3")
        bins = self.bins if self.bins is not None else CurvatureBins(count=values.size)
        profile = DcollProfile.from_bins(bins, values)
        with self._lock:
            return self.control.observe(profile, stamp_ns / NS_PER_S)

    def command(self, twist: Twist, now_s: float | None = None) -> SafeCommand:
        """The safe command for the operator's `twist` at `now_s` (wall clock, s)."""
        linear, angular = twist.linear, twist.angular
        joystick = Command(linear[0], angular[2])
        with self._lock:
            decision = self.control.command(joystick, time.time() if now_s is None else now_s)
        safe = Twist(
            (decision.command.v_mps, linear[1], linear[2]),
            (angular[0], angular[1], decision.command.w_radps),
        )
        return SafeCommand(safe, decision.limit)


def bins_of_model(props: dict[str, str]) -> CurvatureBins | None:
    """The curvature bins a model's metadata names (`nav.bins.*`, as zoo:stereo writes them);
    None when it names none."""
    if "nav.bins.count" not in props or "nav.bins.k_max_per_m" not in props:
        return None
    try:
        return CurvatureBins(float(props["nav.bins.k_max_per_m"]), int(props["nav.bins.count"]))
    except ValueError:
        raise UserError(f"the model's nav.bins metadata is not numbers: {props}") from None


def _model_props(cfg: FleetConfig) -> dict[str, str]:
    """The metadata of the fleet's model (a zoo model is exported once into the cache, for the
    fleet's camera geometry: the very file its robot and deployments run)."""
    import onnx

    from common.models import resolve_model

    shape = tuple(cfg.input_shape) if cfg.input_shape else None
    ref = resolve_model(cfg.model_spec, shape, cfg.zoo_options)
    model = onnx.load(str(ref.path), load_external_data=False)
    return {p.key: p.value for p in model.metadata_props}


class AssistNode:
    """The assistant on the ROS 2 graph: node `elasticfog_assist_<robot>` with the two Twist
    topics and the d_coll subscription, on a Zenoh session the caller owns."""

    def __init__(
        self,
        session: zenoh.Session,
        *,
        domain: int,
        robot: str,
        results_prefix: str,
        cmd_in: str,
        cmd_out: str,
        params: AssistantParams | None = None,
        bins: CurvatureBins | None = None,
        stamped: bool = False,
        namespace: str = rmw_zenoh.ROOT_NAMESPACE,
    ) -> None:
        from robotd.results.ros2 import results_topic
        from robotd.ros2_node import acquire_node

        self.cmd_in, self.cmd_out = rmw_zenoh.topic_name(cmd_in), rmw_zenoh.topic_name(cmd_out)
        if self.cmd_in == self.cmd_out:
            raise UserError(f"--cmd-in and --cmd-out are both {self.cmd_in}")
        self.d_coll_topic = results_topic(rmw_zenoh.topic_name(results_prefix), D_COLL_OUTPUT)
        self.assist = TeleopAssist(params, bins)
        self.forwarded = 0
        self.refused = 0
        self._throttled = ThrottledLog(log, label=lambda: "nav assist")
        self.stamped = stamped
        command = MessageType.TWIST_STAMPED if stamped else MessageType.TWIST
        twist = rmw_zenoh.TopicType.of(command.value, typestore())
        array = rmw_zenoh.TopicType.of(MessageType.FLOAT32_MULTI_ARRAY.value, typestore())
        self._node: Ros2Node = acquire_node(session, domain, f"assist_{robot}", namespace=namespace)
        self._entities: list[Ros2Publisher | Ros2Subscription] = []
        try:
            self._out = self._node.publisher(self.cmd_out, twist, rmw_zenoh.DEFAULT_QOS)
            self._entities.append(self._out)
            for topic, topic_type, handler in (
                (self.d_coll_topic, array, self._on_d_coll),
                (self.cmd_in, twist, self._on_cmd),
            ):
                key = rmw_zenoh.topic_key(domain, topic, topic_type)
                sub = self._node.subscription(
                    topic, topic_type, rmw_zenoh.DEFAULT_QOS, key, handler
                )
                self._entities.append(sub)
        except BaseException:
            self.close()
            raise

    def _on_d_coll(self, sample: zenoh.Sample) -> None:
        try:
            attachment = sample.attachment
            if attachment is None:
                raise UserError("d_coll without an rmw_zenoh attachment: no capture stamp")
            stamp_ns = rmw_zenoh.Attachment.decode(attachment.to_bytes()).stamp_ns
            values, _ = decode_float32_multi_array(sample.payload.to_bytes())
            self.assist.observe(values, stamp_ns)
        except (Ros2MessageError, rmw_zenoh.AttachmentError, UserError) as exc:
            self.refused += 1
            self._throttled.warning("nav assist: d_coll refused: %s: %s", type(exc).__name__, exc)
        except Exception:
            self._throttled.error("nav assist: d_coll not taken", exc_info=True)

    def _on_cmd(self, sample: zenoh.Sample) -> None:
        try:
            if self.stamped:
                header, twist = decode_twist_stamped(sample.payload.to_bytes())
                check_stamp(header, time.time_ns())
                safe = self.assist.command(twist)
                self._out.put(encode_twist_stamped(safe.twist, header))
            else:
                safe = self.assist.command(decode_twist(sample.payload.to_bytes()))
                self._out.put(encode_twist(safe.twist))
            self.forwarded += 1
            if safe.limit is not self.assist.limit:
                log.info("nav assist: %s -> %s", self.assist.limit.value, safe.limit.value)
                self.assist.limit = safe.limit
        except (Ros2MessageError, UserError) as exc:
            self.refused += 1
            self._throttled.warning("nav assist: command refused: %s: %s", type(exc).__name__, exc)
        except Exception:
            self._throttled.error("nav assist: command not taken", exc_info=True)

    def close(self) -> None:
        for entity in reversed(self._entities):
            entity.close()
        self._entities.clear()
        self._node.release()


def run_assist(
    config_path: str,
    robot: str,
    cmd_in: str,
    cmd_out: str,
    *,
    results_prefix: str | None,
    params: AssistantParams,
    stop: threading.Event,
    stamped: bool = False,
) -> AssistNode:
    """Run the assistant of `robot` until `stop`; returns the node (closed) for its counts."""
    from common.config import load_fleet
    from common.keys import Role
    from common.session import open_ros2_session, open_session

    cfg = load_fleet(config_path)
    machine = cfg.machine(robot, role=Role.ROBOT)
    prefix = results_prefix or machine.results.ros2
    if prefix is None:
        raise UserError(
            f"robot {robot} publishes no ROS 2 results: set machines.{robot}.results.ros2 in "
            "the fleet file (the robot's d_coll comes from there) or give --results PREFIX"
        )
    ros2 = cfg.ros2_for(robot)
    # With the ROS 2 graph's own router, the assistant needs nothing of the fleet's.
    session = open_session(cfg) if ros2.endpoint is None else open_ros2_session(ros2)
    try:
        node = AssistNode(
            session,
            domain=ros2.domain(),
            robot=robot,
            results_prefix=prefix,
            cmd_in=cmd_in,
            cmd_out=cmd_out,
            params=params,
            bins=bins_of_model(_model_props(cfg)),
            stamped=stamped,
            namespace=ros2.namespace,
        )
        log.info(
            "nav assist for %s: %s -> %s, d_coll from %s, deadline %.2f s",
            robot,
            node.cmd_in,
            node.cmd_out,
            node.d_coll_topic,
            params.deadline_s,
        )
        try:
            stop.wait()
        finally:
            node.close()
    finally:
        session.close()
    log.info("nav assist: %d commands forwarded, %d refused", node.forwarded, node.refused)
    return node

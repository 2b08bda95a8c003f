"""The robot daemon as a ROS 2 node over rmw_zenoh, on the fleet's session or on one of its own.

A `ros2:` source and a `results: {ros2: ...}` sink are entities of one node (`ros2 node list`
shows `elasticfog_<robot>` once, whatever uses it): `acquire_node` hands out the node of a
session, domain and namespace, made by its first user (the node's liveliness token declared
then) and closed by its last (`Ros2Node.release`). Like rmw_zenoh's context, the node numbers
its entities from one counter (node 0, then 1, 2, ...) and declares, for each subscription and
publisher, the liveliness token a ROS 2 graph cache reads (`common.rmw_zenoh`). Each publisher
attaches rmw_zenoh's 33 bytes (sequence number from 1, publication time, GID) to every sample.

Which session: `acquire_robot_node` reads the machine's ROS 2 settings (`FleetConfig.ros2_for`).
Without `ros2.endpoint` the node lives on the daemon's fleet session (one router for both, on one
host). With it, on a ROS 2 session of the process's own (`common.session.open_ros2_session`),
connected to that endpoint only (the robot host's rmw_zenohd) and shared by every node of the
process that names it: opened by its first node, closed after its last. The fleet session then
keeps its TLS, mutual TLS and access control, and no key of one reaches the other: nothing in
this process forwards between them.

The process also remembers, for the frames a ROS 2 source took, the input frame by capture stamp
(`remember_frame`, bounded): its header (frame id), the camera image's size and the camera's
intrinsics when its CameraInfo came. Every result message with a header carries the input's
(`robotd.results.ros2`), and the model view's CameraInfo is the camera's, cropped and scaled.
Process-wide, so that a robot whose services each publish on a session of their own finds the
frames its one source took.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import zenoh

from common import rmw_zenoh
from common.rmw_zenoh import Attachment, EntityKind, Qos, TopicType

if TYPE_CHECKING:
    from common.config import FleetConfig
    from common.ros2_messages import CameraInfo, Header

# Frames remembered by capture stamp: more than the frames a robot has in flight at once.
MAX_REMEMBERED_FRAMES = 256

_lock = threading.Lock()
_nodes: dict[tuple[int, int, str, str], Ros2Node] = {}
# ROS 2 sessions of this process by endpoint: [session, users].
_sessions: dict[str, list[Any]] = {}


@dataclass(frozen=True)
class InputFrame:
    """What a result's messages say of the frame they were computed on: its header, the size of
    the camera image it came as (the left one of a pair) and the camera's intrinsics, if known."""

    header: Header
    height: int
    width: int
    camera: CameraInfo | None = None


_frames: OrderedDict[int, InputFrame] = OrderedDict()
_frames_lock = threading.Lock()


def remember_frame(frame: InputFrame) -> None:
    """A ROS 2 source took `frame` (by its header's stamp)."""
    with _frames_lock:
        _frames[frame.header.stamp_ns] = frame
        _frames.move_to_end(frame.header.stamp_ns)
        while len(_frames) > MAX_REMEMBERED_FRAMES:
            _frames.popitem(last=False)


def input_frame(stamp_ns: int) -> InputFrame | None:
    """The frame a ROS 2 source took at capture stamp `stamp_ns`; None for a frame no ROS 2
    source took (a photo, a camera: then results carry the stamp and an empty frame id)."""
    with _frames_lock:
        return _frames.get(stamp_ns)


class Ros2Publisher:
    """A Zenoh publisher on a topic's data key, with its MP token and rmw_zenoh's attachment."""

    def __init__(self, node: Ros2Node, topic: str, topic_type: TopicType, qos: Qos) -> None:
        self.topic = topic
        self.key = rmw_zenoh.topic_key(node.node.domain, topic, topic_type)
        token = node.node.entity_token(
            node.next_entity_id(), EntityKind.PUBLISHER, topic, topic_type, qos
        )
        self.gid = rmw_zenoh.gid_of(token)
        self._sequence = itertools.count(1)
        self._publisher = node.session.declare_publisher(self.key)
        self._token = node.session.liveliness().declare_token(token)

    def put(self, payload: bytes, stamp_ns: int | None = None) -> None:
        """Publish one CDR message with its sequence number and source timestamp: `stamp_ns`,
        else the time now (rmw_zenoh's, which a receiver reads as the message's
        `source_timestamp`)."""
        stamp = time.time_ns() if stamp_ns is None else stamp_ns
        attachment = Attachment(next(self._sequence), stamp, self.gid).encode()
        self._publisher.put(payload, attachment=attachment)

    def close(self) -> None:
        self._token.undeclare()
        self._publisher.undeclare()


class Ros2Subscription:
    """A Zenoh subscriber on `key` with the MS token of `topic` (its `topic_type`)."""

    def __init__(
        self,
        node: Ros2Node,
        topic: str,
        topic_type: TopicType,
        qos: Qos,
        key: str,
        handler: Callable[[zenoh.Sample], None],
    ) -> None:
        token = node.node.entity_token(
            node.next_entity_id(), EntityKind.SUBSCRIPTION, topic, topic_type, qos
        )
        self._subscriber = node.session.declare_subscriber(key, handler)
        self._token = node.session.liveliness().declare_token(token)

    def close(self) -> None:
        self._token.undeclare()
        self._subscriber.undeclare()


class Ros2Node:
    """One ROS 2 node on a Zenoh session (see the module docstring). Get it with `acquire_node`
    or `acquire_robot_node` and give it back with `release`."""

    def __init__(
        self,
        session: zenoh.Session,
        domain: int,
        name: str,
        namespace: str = rmw_zenoh.ROOT_NAMESPACE,
        *,
        endpoint: str | None = None,
    ) -> None:
        self.session = session
        self._ids = itertools.count(0)
        self.node = rmw_zenoh.Node(
            domain, str(session.info.zid()), next(self._ids), name, namespace=namespace
        )
        # The ROS 2 session's endpoint when the node lives on one of this process's own.
        self.endpoint = endpoint
        self._token = session.liveliness().declare_token(self.node.token())
        self._users = 0

    @property
    def key(self) -> tuple[int, int, str, str]:
        return (id(self.session), self.node.domain, self.node.namespace, self.node.name)

    def next_entity_id(self) -> int:
        return next(self._ids)

    def publisher(self, topic: str, topic_type: TopicType, qos: Qos) -> Ros2Publisher:
        return Ros2Publisher(self, topic, topic_type, qos)

    def subscription(
        self,
        topic: str,
        topic_type: TopicType,
        qos: Qos,
        key: str,
        handler: Callable[[zenoh.Sample], Any],
    ) -> Ros2Subscription:
        return Ros2Subscription(self, topic, topic_type, qos, key, handler)

    def release(self) -> None:
        """A user is done with the node; the last one takes its token down (and a ROS 2
        session of the process's own is closed after its last node)."""
        with _lock:
            self._users -= 1
            last = self._users <= 0
            if last:
                _nodes.pop(self.key, None)
        if last:
            self._token.undeclare()
        if self.endpoint is not None:
            _release_session(self.endpoint)


def acquire_node(
    session: zenoh.Session,
    domain: int,
    machine: str,
    *,
    namespace: str = rmw_zenoh.ROOT_NAMESPACE,
    endpoint: str | None = None,
) -> Ros2Node:
    """The ROS 2 node of `machine` on `session` in `domain` and `namespace` (made on first use);
    `endpoint`: the session is the process's ROS 2 session of that endpoint."""
    name = rmw_zenoh.node_name_for(machine)
    with _lock:
        key = (id(session), domain, namespace, name)
        node = _nodes.get(key)
        if node is None:
            node = Ros2Node(session, domain, name, namespace, endpoint=endpoint)
            _nodes[key] = node
        node._users += 1
        return node


def acquire_robot_node(
    cfg: FleetConfig,
    machine: str,
    fleet_session: zenoh.Session | None,
    *,
    name: str | None = None,
    domain: int | None = None,
) -> Ros2Node:
    """The ROS 2 node of `machine` (node `elasticfog_<name or machine>`) with the machine's ROS 2
    settings: on the process's ROS 2 session when `ros2.endpoint` is set, else on
    `fleet_session`; in `domain` (None: the settings')."""
    from common.errors import UserError

    ros2 = cfg.ros2_for(machine)
    node_domain = ros2.domain() if domain is None else domain
    if ros2.endpoint is None:
        if fleet_session is None:
            raise UserError(
                f"{machine}: no ros2.endpoint and no fleet session to speak ROS 2 on: set "
                "ros2.endpoint to the ROS 2 graph's router"
            )
        return acquire_node(fleet_session, node_domain, name or machine, namespace=ros2.namespace)
    session = _acquire_session(ros2)
    try:
        return acquire_node(
            session,
            node_domain,
            name or machine,
            namespace=ros2.namespace,
            endpoint=ros2.endpoint,
        )
    except BaseException:
        _release_session(ros2.endpoint)
        raise


def ros2_session_open(endpoint: str) -> bool:
    """Whether this process holds a ROS 2 session to `endpoint` (for tests and logs)."""
    with _lock:
        return endpoint in _sessions


def _acquire_session(ros2: Any) -> zenoh.Session:
    from common.session import open_ros2_session

    with _lock:
        entry = _sessions.get(ros2.endpoint)
        if entry is None:
            entry = [open_ros2_session(ros2), 0]
            _sessions[ros2.endpoint] = entry
        entry[1] += 1
        session: zenoh.Session = entry[0]
        return session


def _release_session(endpoint: str) -> None:
    with _lock:
        entry = _sessions.get(endpoint)
        if entry is None:
            return
        entry[1] -= 1
        if entry[1] > 0:
            return
        del _sessions[endpoint]
    entry[0].close()

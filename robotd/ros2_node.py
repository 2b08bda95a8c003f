"""The robot daemon as a ROS 2 node over rmw_zenoh, on its own Zenoh session.

A `ros2:` source and a `results: {ros2: ...}` sink are entities of one node (`ros2 node list`
shows `elasticfog_<robot>` once, whatever uses it): `acquire_node` hands out the node of a
session and domain, made by its first user (the node's liveliness token declared then) and
closed by its last (`Ros2Node.release`). Like rmw_zenoh's context, the node numbers its entities
from one counter (node 0, then 1, 2, ...) and declares, for each subscription and publisher, the
liveliness token a ROS 2 graph cache reads (`common.rmw_zenoh`). Each publisher attaches
rmw_zenoh's 33 bytes (sequence number from 1, publication time, GID) to every sample.

The node also remembers, for the frames a source took, the header's frame id by capture stamp
(`remember_frame`, bounded): a result published as an Image carries the input frame's header.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import zenoh

from common import rmw_zenoh
from common.rmw_zenoh import Attachment, EntityKind, Qos, TopicType

# Frame ids remembered by capture stamp: more than the frames a robot has in flight at once.
MAX_REMEMBERED_FRAMES = 256

_lock = threading.Lock()
_nodes: dict[tuple[int, int], Ros2Node] = {}


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
    and give it back with `release`."""

    def __init__(self, session: zenoh.Session, domain: int, name: str) -> None:
        self.session = session
        self._ids = itertools.count(0)
        self.node = rmw_zenoh.Node(domain, str(session.info.zid()), next(self._ids), name)
        self._token = session.liveliness().declare_token(self.node.token())
        self._users = 0
        self._frame_ids: OrderedDict[int, str] = OrderedDict()
        self._frames_lock = threading.Lock()

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

    def remember_frame(self, stamp_ns: int, frame_id: str) -> None:
        """The frame captured at `stamp_ns` came with header frame id `frame_id`."""
        with self._frames_lock:
            self._frame_ids[stamp_ns] = frame_id
            while len(self._frame_ids) > MAX_REMEMBERED_FRAMES:
                self._frame_ids.popitem(last=False)

    def frame_id(self, stamp_ns: int) -> str:
        """The frame id of the frame captured at `stamp_ns` ("" for a frame no ROS 2 source
        took)."""
        with self._frames_lock:
            return self._frame_ids.get(stamp_ns, "")

    def release(self) -> None:
        """A user is done with the node; the last one takes its token down."""
        with _lock:
            self._users -= 1
            if self._users > 0:
                return
            _nodes.pop((id(self.session), self.node.domain), None)
        self._token.undeclare()


def acquire_node(session: zenoh.Session, domain: int, machine: str) -> Ros2Node:
    """The ROS 2 node of `machine` on `session` in `domain` (made on first use)."""
    with _lock:
        node = _nodes.get((id(session), domain))
        if node is None:
            node = Ros2Node(session, domain, rmw_zenoh.node_name_for(machine))
            _nodes[(id(session), domain)] = node
        node._users += 1
        return node

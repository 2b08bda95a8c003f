"""rmw_zenoh's key space, formatted in one place: how ROS 2 over Zenoh names its data and graph.

ROS 2's Zenoh middleware (ros2/rmw_zenoh, `docs/design.md`) puts every topic on a Zenoh key and
announces every node, publisher and subscription with a liveliness token, so a process that speaks
Zenoh is a ROS 2 participant without any ROS installed. This module is for rmw_zenoh's keys what
`common.keys` is for ours: no other module formats one.

- Data key: `<domain_id>/<topic without its leading and trailing '/'>/<DDS type name>/<type hash>`,
  e.g. `0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...1a18`. The type hash is REP-2016's
  RIHS01 hash, from rosbags' type store (never computed here by hand), so a publisher whose
  message definition differs (another ROS distribution) is on another key.
- Liveliness tokens, one per entity, under the hermetic `@ros2_lv` prefix:
  `@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>` for a node,
  and for its publishers (MP) and subscriptions (MS)
  `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<MP|MS>/<enclave>/<namespace>/<node name>/`
  `<topic>/<DDS type name>/<type hash>/<qos>`, names mangled (`/` -> `%`), the QoS in
  rmw_zenoh's compact form (`qos_to_keyexpr`: a value is written only where it differs from
  rmw_zenoh's default, e.g. `::,10:,:,:,,` for reliable, volatile, keep-last 10).
- The attachment of every published sample (33 bytes, little endian): int64 sequence number
  (from 1), int64 source timestamp (ns since the epoch), 1 byte GID length (16), 16 GID bytes:
  zenoh-ext's serialization of (int64, int64, bytes), rmw_zenoh_cpp >= 0.2.4 (Jazzy). Earlier
  rmw_zenoh builds on Zenoh 1.x wrote a labelled attachment (77 bytes: each value after its name,
  `sequence_number`, `source_timestamp`, `source_gid`, in the same serialization); both are read,
  the 33-byte one is written.
- A publisher's GID: XXH3-128 of its liveliness token, the low 64 bits then the high 64 bits,
  little endian (rmw_zenoh's `liveliness_utils.cpp`), so a ROS 2 tool that compares the GID of a
  message with the GID its graph cache derives from the token finds the same.

Payloads are CDR with its 4-byte encapsulation header, made and read by rosbags
(`common.ros2_messages`).
"""

from __future__ import annotations

import enum
import functools
import os
import re
import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING

from common.errors import UserError

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

ADMIN_SPACE = "@ros2_lv"
DOMAIN_ID_ENV = "ROS_DOMAIN_ID"
DEFAULT_DOMAIN_ID = 0
# ROS 2's domain ids: 0..232 (the largest that maps to valid DDS ports; rmw_zenoh keeps the range).
MAX_DOMAIN_ID = 232
SLASH_REPLACEMENT = "%"
GID_BYTES = 16
# <q: sequence number, <q: source timestamp (ns), B: GID length, then the GID.
_ATTACHMENT = struct.Struct("<qqB")
ATTACHMENT_BYTES = _ATTACHMENT.size + GID_BYTES
# The labelled attachment of rmw_zenoh builds before 0.2.4: each name as zenoh-ext serializes a
# string (its length, one byte here, then its bytes) before its value.


def _label(name: str) -> bytes:
    return bytes([len(name)]) + name.encode()


_LABELLED = struct.Struct(
    f"<{len(_label('sequence_number'))}sq{len(_label('source_timestamp'))}sq"
    f"{len(_label('source_gid'))}sB{GID_BYTES}s"
)
_LABELS = (_label("sequence_number"), _label("source_timestamp"), _label("source_gid"))
LABELLED_ATTACHMENT_BYTES = _LABELLED.size
# The namespace and enclave of a node that has none: rcl's "/" (mangled to "%").
ROOT_NAMESPACE = "/"
# The deepest keep-last history a publisher may announce (a bound on what a file may ask).
MAX_QOS_DEPTH = 10_000

# A ROS 2 name token: a letter or underscore, then letters, digits, underscores.
_TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
_TOPIC = re.compile(rf"^/?{_TOKEN}(/{_TOKEN})*$")
_NODE_NAME = re.compile(rf"^{_TOKEN}$")


class Ros2NameError(UserError, ValueError):
    """A topic, node name or domain id that ROS 2 does not accept."""


class AttachmentError(ValueError):
    """An rmw_zenoh attachment that is neither 33 bytes of sequence, stamp, GID length 16 and GID
    nor the labelled form of the same."""


class EntityKind(str, enum.Enum):
    """The kind chunk of a liveliness token."""

    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


class Reliability(enum.IntEnum):
    """rmw_qos_reliability_policy_e."""

    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(enum.IntEnum):
    """rmw_qos_durability_policy_e."""

    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2


class History(enum.IntEnum):
    """rmw_qos_history_policy_e."""

    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2


# rmw_zenoh's default QoS (`qos.cpp`): what its compact form leaves out.
_DEFAULT_RELIABILITY = Reliability.RELIABLE
_DEFAULT_DURABILITY = Durability.VOLATILE
_DEFAULT_HISTORY = History.KEEP_LAST
_DEFAULT_DEPTH = 42


@dataclass(frozen=True)
class Qos:
    """The QoS an entity announces. Deadline, lifespan and liveliness stay rmw_zenoh's defaults
    (infinite, automatic): rmw_zenoh implements none of them but AUTOMATIC liveliness."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = 10

    def encode(self) -> str:
        """rmw_zenoh's `qos_to_keyexpr`: `<rel>:<dur>:<hist>,<depth>:<deadline s>,<ns>:`
        `<lifespan s>,<ns>:<liveliness>,<lease s>,<ns>`, each value empty where it is the
        default."""

        def differs(value: int, default: int) -> str:
            return "" if value == default else str(int(value))

        return (
            f"{differs(self.reliability, _DEFAULT_RELIABILITY)}:"
            f"{differs(self.durability, _DEFAULT_DURABILITY)}:"
            f"{differs(self.history, _DEFAULT_HISTORY)},{differs(self.depth, _DEFAULT_DEPTH)}:"
            ",:,:,,"
        )


# rclcpp's default (`rclcpp::QoS(10)`): reliable, volatile, keep last 10. The results publishers.
DEFAULT_QOS = Qos()
# A camera subscription that keeps only the newest frame; best effort matches any camera
# publisher (a reliable subscription would be "incompatible" with a best-effort camera in DDS).
NEWEST_FRAME_QOS = Qos(reliability=Reliability.BEST_EFFORT, depth=1)


# -- names -----------------------------------------------------------------------------------------
def mangle(name: str) -> str:
    """A name as one key chunk: each '/' replaced by '%'."""
    return name.replace("/", SLASH_REPLACEMENT)


def topic_name(name: str) -> str:
    """`name` as a fully qualified ROS 2 topic name (leading '/'), or Ros2NameError. Relative
    names are taken from the root namespace; '~' and substitutions are not accepted."""
    text = name.strip()
    if not _TOPIC.match(text) or "__" in text:
        raise Ros2NameError(
            f"{name!r} is not a ROS 2 topic name: tokens of letters, digits and '_' (not starting "
            "with a digit, no '__') separated by single '/', e.g. /camera/image_raw"
        )
    return text if text.startswith("/") else "/" + text


def is_within(topic: str, prefix: str) -> bool:
    """Whether `topic` is `prefix` or a topic below it (both fully qualified)."""
    return topic == prefix or topic.startswith(prefix.rstrip("/") + "/")


CAMERA_INFO = "camera_info"
COMPRESSED_SUFFIX = "/compressed"


def camera_info_topic(image_topic: str) -> str:
    """The CameraInfo topic of a camera image topic, as image_transport names it: a sibling of
    the base image topic (`/camera/image_raw` and `/camera/image_raw/compressed` ->
    `/camera/camera_info`)."""
    topic = topic_name(image_topic)
    if topic.endswith(COMPRESSED_SUFFIX):
        topic = topic[: -len(COMPRESSED_SUFFIX)]
    parent = topic.rsplit("/", 1)[0]
    return f"{parent}/{CAMERA_INFO}"


def name_token(name: str) -> str:
    """`name` (e.g. an ONNX output's, `output.1`) as one ROS 2 name token: every character other
    than letters, digits and '_' becomes '_', and a leading digit gets a '_' before it."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", name) or "_"
    return "_" + token if token[0].isdigit() else token


def namespace(name: str) -> str:
    """`name` as a node namespace: `/`, or a fully qualified ROS 2 name without a trailing '/'
    (`robot1` is `/robot1`); Ros2NameError otherwise."""
    text = name.strip()
    if text in ("", ROOT_NAMESPACE):
        return ROOT_NAMESPACE
    try:
        return topic_name(text.rstrip("/"))
    except Ros2NameError:
        raise Ros2NameError(
            f"{name!r} is not a ROS 2 namespace: '/' or tokens of letters, digits and '_' "
            "separated by single '/', e.g. /robot1"
        ) from None


def node_name(name: str) -> str:
    """`name` if it is a valid ROS 2 node name, else Ros2NameError."""
    if not _NODE_NAME.match(name):
        raise Ros2NameError(
            f"{name!r} is not a ROS 2 node name: letters, digits and '_', not starting with a digit"
        )
    return name


def node_name_for(machine: str, prefix: str = "elasticfog") -> str:
    """The ROS 2 node name of one of our machines: `<prefix>_<id>` with every character that a
    node name cannot hold (our ids may hold '-' and '.') replaced by '_'."""
    return node_name(re.sub(r"[^A-Za-z0-9_]", "_", f"{prefix}_{machine}"))


def domain_id(value: int | str | None = None) -> int:
    """The ROS 2 domain id: `value` if given, else `ROS_DOMAIN_ID`, else 0; Ros2NameError when it
    is not an integer in 0..232."""
    source = "domain id"
    if value is None:
        value = os.environ.get(DOMAIN_ID_ENV, "").strip() or DEFAULT_DOMAIN_ID
        source = DOMAIN_ID_ENV
    try:
        number = int(value)
    except (TypeError, ValueError):
        raise Ros2NameError(f"{source} {value!r} is not an integer") from None
    if not DEFAULT_DOMAIN_ID <= number <= MAX_DOMAIN_ID:
        raise Ros2NameError(f"{source} must be in 0..{MAX_DOMAIN_ID}, got {number}")
    return number


# -- types -----------------------------------------------------------------------------------------
@functools.cache
def _jazzy() -> Typestore:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@dataclass(frozen=True)
class TopicType:
    """A message type as rmw_zenoh names it: `ros` (`sensor_msgs/msg/Image`), `dds`
    (`sensor_msgs::msg::dds_::Image_`) and `hash` (`RIHS01_<sha256 hex>`)."""

    ros: str
    dds: str
    hash: str

    @classmethod
    def of(cls, ros_type: str, typestore: Typestore | None = None) -> TopicType:
        """The names of `ros_type` from rosbags' type store (Jazzy's unless another is given)."""
        store = typestore if typestore is not None else _jazzy()
        package, kind, name = ros_type.split("/")
        return cls(ros_type, f"{package}::{kind}::dds_::{name}_", store.hash_rihs01(ros_type))


# -- keys ------------------------------------------------------------------------------------------
def topic_key(domain: int, topic: str, topic_type: TopicType) -> str:
    """The data key of `topic` carrying `topic_type` in `domain`."""
    return f"{domain}/{topic_name(topic).strip('/')}/{topic_type.dds}/{topic_type.hash}"


def topic_any_type_key(domain: int, topic: str) -> str:
    """`<domain>/<topic>/*/*`: `topic` whatever its type and hash (exactly that topic: a topic
    below it has more chunks). A subscriber on it sees a publisher of another type or type hash
    and can say so, where one on `topic_key` would hear nothing."""
    return f"{domain}/{topic_name(topic).strip('/')}/*/*"


def split_topic_key(key: str) -> tuple[int, str, str, str]:
    """(domain, topic with its leading '/', DDS type name, type hash) of a data key; ValueError
    when `key` is not one."""
    chunks = key.split("/")
    if len(chunks) < 4 or not chunks[0].isdigit():
        raise ValueError(f"{key!r} is not an rmw_zenoh data key")
    return int(chunks[0]), "/" + "/".join(chunks[1:-2]), chunks[-2], chunks[-1]


@dataclass(frozen=True)
class Node:
    """One ROS 2 node of a Zenoh session (`zid`: the session's id as Zenoh prints it)."""

    domain: int
    zid: str
    node_id: int
    name: str
    namespace: str = ROOT_NAMESPACE
    enclave: str = ROOT_NAMESPACE

    def _chunks(self, entity_id: int, kind: EntityKind) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain}/{self.zid}/{self.node_id}/{entity_id}/{kind.value}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{mangle(node_name(self.name))}"
        )

    def token(self) -> str:
        """The node's liveliness token (its entity id is its node id)."""
        return self._chunks(self.node_id, EntityKind.NODE)

    def entity_token(
        self, entity_id: int, kind: EntityKind, topic: str, topic_type: TopicType, qos: Qos
    ) -> str:
        """The liveliness token of one of the node's publishers or subscriptions."""
        if kind not in (EntityKind.PUBLISHER, EntityKind.SUBSCRIPTION):
            raise ValueError(f"{kind} is not a topic entity")
        return (
            f"{self._chunks(entity_id, kind)}/{mangle(topic_name(topic))}/"
            f"{topic_type.dds}/{topic_type.hash}/{qos.encode()}"
        )


def node_tokens_key(domain: int) -> str:
    """Every liveliness token of `domain` (what rmw_zenoh's graph cache follows)."""
    return f"{ADMIN_SPACE}/{domain}/**"


# -- attachment ------------------------------------------------------------------------------------
def gid_of(token: str) -> bytes:
    """A publisher's 16-byte GID as rmw_zenoh derives it from the liveliness token: XXH3-128 of
    the token, the low 64 bits then the high 64 bits, little endian."""
    import xxhash  # the one user: a publisher's GID

    digest: int = xxhash.xxh3_128_intdigest(token.encode())
    return digest.to_bytes(GID_BYTES, "little")


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every sample."""

    sequence: int
    stamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) != GID_BYTES:
            raise AttachmentError(f"a GID is {GID_BYTES} bytes, got {len(self.gid)}")
        return _ATTACHMENT.pack(self.sequence, self.stamp_ns, GID_BYTES) + self.gid

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        """The 33-byte attachment, or the labelled one of earlier rmw_zenoh builds."""
        if len(data) == LABELLED_ATTACHMENT_BYTES and data.startswith(_LABELS[0]):
            return cls._decode_labelled(data)
        if len(data) != ATTACHMENT_BYTES:
            raise AttachmentError(
                f"an rmw_zenoh attachment is {ATTACHMENT_BYTES} bytes (or "
                f"{LABELLED_ATTACHMENT_BYTES}, labelled), got {len(data)}"
            )
        sequence, stamp_ns, gid_len = _ATTACHMENT.unpack_from(data)
        if gid_len != GID_BYTES:
            raise AttachmentError(f"attachment GID length {gid_len}, expected {GID_BYTES}")
        return cls(sequence, stamp_ns, bytes(data[_ATTACHMENT.size :]))

    @classmethod
    def _decode_labelled(cls, data: bytes) -> Attachment:
        seq_label, sequence, stamp_label, stamp_ns, gid_label, gid_len, gid = _LABELLED.unpack(data)
        if (seq_label, stamp_label, gid_label) != _LABELS:
            raise AttachmentError(
                "a labelled rmw_zenoh attachment names sequence_number, source_timestamp and "
                f"source_gid in that order, got {seq_label[1:]!r}, {stamp_label[1:]!r}, "
                f"{gid_label[1:]!r}"
            )
        if gid_len != GID_BYTES:
            raise AttachmentError(f"attachment GID length {gid_len}, expected {GID_BYTES}")
        return cls(sequence, stamp_ns, gid)

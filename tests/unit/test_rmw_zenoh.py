"""rmw_zenoh's key space byte for byte: the data keys, liveliness tokens and attachment exactly as
ros2/rmw_zenoh `docs/design.md` writes its examples, and as an independent implementation
(zenoh-ros2-sdk) reads and writes them."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from common import rmw_zenoh
from common.rmw_zenoh import (
    Attachment,
    AttachmentError,
    Durability,
    EntityKind,
    History,
    Node,
    Qos,
    Reliability,
    Ros2NameError,
    TopicType,
)

# design.md, "Topic and Service name mapping to Zenoh key expressions" and "Graph Cache".
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
STRING_DDS = "std_msgs::msg::dds_::String_"
LISTENER_ZID = "aac3178e146ba6f1fc6e6a4085e77f21"
TALKER_ZID = "8b20917502ee955ac4476e0266340d5c"


def test_type_names_and_hash_from_the_type_store() -> None:
    t = TopicType.of("std_msgs/msg/String")
    assert (t.ros, t.dds, t.hash) == ("std_msgs/msg/String", STRING_DDS, STRING_HASH)
    image = TopicType.of("sensor_msgs/msg/Image")
    assert image.dds == "sensor_msgs::msg::dds_::Image_"
    assert image.hash.startswith("RIHS01_") and len(image.hash) == len("RIHS01_") + 64


def test_data_keys_as_design_md() -> None:
    t = TopicType.of("std_msgs/msg/String")
    assert rmw_zenoh.topic_key(0, "chatter", t) == f"0/chatter/{STRING_DDS}/{STRING_HASH}"
    assert rmw_zenoh.topic_key(0, "/chatter", t) == f"0/chatter/{STRING_DDS}/{STRING_HASH}"
    assert (
        rmw_zenoh.topic_key(0, "/robot1/chatter", t)
        == f"0/robot1/chatter/{STRING_DDS}/{STRING_HASH}"
    )


def test_node_token_as_design_md() -> None:
    node = Node(domain=2, zid=LISTENER_ZID, node_id=0, name="listener")
    assert node.token() == f"@ros2_lv/2/{LISTENER_ZID}/0/0/NN/%/%/listener"


def test_subscription_and_publisher_tokens_as_design_md() -> None:
    t = TopicType.of("std_msgs/msg/String")
    listener = Node(domain=2, zid=LISTENER_ZID, node_id=0, name="listener")
    assert listener.entity_token(10, EntityKind.SUBSCRIPTION, "/chatter", t, Qos()) == (
        f"@ros2_lv/2/{LISTENER_ZID}/0/10/MS/%/%/listener/%chatter/{STRING_DDS}/{STRING_HASH}"
        "/::,10:,:,:,,"
    )
    talker = Node(domain=2, zid=TALKER_ZID, node_id=0, name="talker")
    assert talker.entity_token(10, EntityKind.PUBLISHER, "/chatter", t, Qos(depth=7)) == (
        f"@ros2_lv/2/{TALKER_ZID}/0/10/MP/%/%/talker/%chatter/{STRING_DDS}/{STRING_HASH}"
        "/::,7:,:,:,,"
    )


def test_namespace_and_enclave_are_mangled() -> None:
    node = Node(domain=0, zid="1", node_id=3, name="cam", namespace="/robot1/front", enclave="/e")
    assert node.token() == "@ros2_lv/0/1/3/3/NN/%e/%robot1%front/cam"


def test_qos_compact_form_writes_only_what_differs_from_rmw_zenoh_defaults() -> None:
    # rmw_zenoh's defaults: reliable, volatile, keep last, depth 42, the rest infinite/automatic.
    assert Qos(depth=42).encode() == "::,:,:,:,,"
    assert rmw_zenoh.NEWEST_FRAME_QOS.encode() == "2::,1:,:,:,,"
    transient_all = Qos(Reliability.BEST_EFFORT, Durability.TRANSIENT_LOCAL, History.KEEP_ALL, 5)
    assert transient_all.encode() == "2:1:2,5:,:,:,,"


def test_the_qos_string_parses_back_in_an_independent_implementation() -> None:
    from zenoh_ros2_sdk.qos import QosProfile

    for qos in (
        Qos(),
        rmw_zenoh.NEWEST_FRAME_QOS,
        Qos(durability=Durability.TRANSIENT_LOCAL, depth=3),
    ):
        profile = QosProfile.decode(qos.encode())
        assert profile.reliability.value == qos.reliability
        assert profile.durability.value == qos.durability
        assert (profile.history_kind.value, profile.history_depth) == (qos.history, qos.depth)


def test_attachment_bytes() -> None:
    gid = bytes(range(16))
    data = Attachment(sequence=1, stamp_ns=0x0102030405060708, gid=gid).encode()
    assert data == (
        bytes.fromhex("0100000000000000")  # int64 sequence, little endian
        + bytes.fromhex("0807060504030201")  # int64 source timestamp, ns
        + bytes([16])  # GID length
        + gid
    )
    assert len(data) == rmw_zenoh.ATTACHMENT_BYTES == 33
    assert Attachment.decode(data) == Attachment(1, 0x0102030405060708, gid)


def test_attachment_read_and_written_by_an_independent_implementation() -> None:
    from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment

    gid = bytes(range(100, 116))
    theirs = SdkAttachment(sequence_id=7, timestamp_ns=1_700_000_000_123_456_789, gid=gid)
    assert Attachment.decode(theirs.to_bytes()) == Attachment(7, 1_700_000_000_123_456_789, gid)
    ours = Attachment(3, 42, gid).encode()
    back = SdkAttachment.from_bytes(ours)
    assert (back.sequence_id, back.timestamp_ns, back.gid) == (3, 42, gid)


@pytest.mark.parametrize(
    "data",
    [b"", bytes(32), bytes(34), bytes(16) + bytes([8]) + bytes(16)],
    ids=["empty", "short", "long", "gid-length-8"],
)
def test_bad_attachments_are_named_errors(data: bytes) -> None:
    with pytest.raises(AttachmentError):
        Attachment.decode(data)


def test_both_attachment_forms_as_zenoh_serializes_them() -> None:
    """The 33-byte form is zenoh-ext's serialization of (int64, int64, bytes); the labelled form
    of rmw_zenoh builds before 0.2.4 names each value first. Both made by zenoh's own
    serializer, both read; a labelled one with other names is refused."""
    from zenoh.ext import Int64, z_serialize

    gid = bytes(range(40, 56))
    plain = z_serialize((Int64(9), Int64(1_700_000_000_000_000_001), gid)).to_bytes()
    assert plain == Attachment(9, 1_700_000_000_000_000_001, gid).encode()
    labelled = z_serialize(
        (
            "sequence_number",
            Int64(9),
            "source_timestamp",
            Int64(1_700_000_000_000_000_001),
            "source_gid",
            gid,
        )
    ).to_bytes()
    assert len(labelled) == rmw_zenoh.LABELLED_ATTACHMENT_BYTES
    assert Attachment.decode(labelled) == Attachment(9, 1_700_000_000_000_000_001, gid)
    wrong = labelled.replace(b"source_gid", b"source_xid")
    with pytest.raises(AttachmentError, match="names sequence_number, source_timestamp"):
        Attachment.decode(wrong)


def test_gid_is_rmw_zenohs_xxh3_128_of_the_token() -> None:
    import xxhash

    token = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/11/MP/%/%/talker/%chatter"
    canonical = xxhash.xxh3_128(token.encode()).digest()  # big endian: high 64, low 64
    assert rmw_zenoh.gid_of(token) == canonical[8:][::-1] + canonical[:8][::-1]


@given(st.binary(max_size=96))
def test_any_bytes_decode_or_raise_attachment_error(data: bytes) -> None:
    with contextlib.suppress(AttachmentError):
        Attachment.decode(data)


def test_gid_is_16_bytes_stable_per_token() -> None:
    a, b = rmw_zenoh.gid_of("@ros2_lv/0/x/0/1/MP/a"), rmw_zenoh.gid_of("@ros2_lv/0/x/0/2/MP/a")
    assert len(a) == 16 and a != b and a == rmw_zenoh.gid_of("@ros2_lv/0/x/0/1/MP/a")


@pytest.mark.parametrize(
    "name", ["", "/", "//a", "a//b", "a/", "1abc", "a b", "~/x", "a/{n}", "a__b"]
)
def test_bad_topic_names(name: str) -> None:
    with pytest.raises(Ros2NameError):
        rmw_zenoh.topic_name(name)


def test_node_names_of_our_machines() -> None:
    assert rmw_zenoh.node_name_for("robot-1") == "elasticfog_robot_1"
    assert rmw_zenoh.node_name_for("arm.2") == "elasticfog_arm_2"


def test_domain_id_from_value_env_or_zero(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(rmw_zenoh.DOMAIN_ID_ENV, raising=False)
    assert rmw_zenoh.domain_id() == 0
    monkeypatch.setenv(rmw_zenoh.DOMAIN_ID_ENV, "17")
    assert rmw_zenoh.domain_id() == 17
    assert rmw_zenoh.domain_id(3) == 3
    monkeypatch.setenv(rmw_zenoh.DOMAIN_ID_ENV, "x")
    with pytest.raises(Ros2NameError, match="ROS_DOMAIN_ID"):
        rmw_zenoh.domain_id()
    with pytest.raises(Ros2NameError, match=r"0\.\.232"):
        rmw_zenoh.domain_id(233)


def test_any_type_key_matches_only_that_topic() -> None:
    zenoh = pytest.importorskip("zenoh")
    t = TopicType.of("sensor_msgs/msg/Image")
    wild = zenoh.KeyExpr(rmw_zenoh.topic_any_type_key(0, "/camera"))
    assert wild.intersects(zenoh.KeyExpr(rmw_zenoh.topic_key(0, "/camera", t)))
    assert not wild.intersects(zenoh.KeyExpr(rmw_zenoh.topic_key(0, "/camera/left", t)))
    assert not wild.intersects(zenoh.KeyExpr(rmw_zenoh.topic_key(1, "/camera", t)))
    assert rmw_zenoh.split_topic_key(rmw_zenoh.topic_key(4, "/a/b", t)) == (
        4,
        "/a/b",
        t.dds,
        t.hash,
    )

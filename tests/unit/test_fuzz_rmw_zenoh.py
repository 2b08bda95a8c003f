"""Fuzzing what a ROS 2 peer controls on rmw_zenoh's side of a `ros2:` topic: the data key a
sample arrives on (parsed to check its type and hash), the 33-byte attachment, and the names a
user writes (topics, domain ids, the `ros2:` spec). Whatever the input, each returns a value or
raises its named error (`ValueError`/`AttachmentError`, `UserError`) with a one-line message,
within the time bound."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from common import rmw_zenoh
from common.errors import UserError
from common.rmw_zenoh import Attachment, AttachmentError, TopicType
from common.source_spec import SourceError, parse_source
from tests.unit.fuzz_support import budget, byte_edits, mutate, run_decoder

_IMAGE = TopicType.of("sensor_msgs/msg/Image")
_KEY = rmw_zenoh.topic_key(0, "/camera/image_raw", _IMAGE)
_KEY_CHARS = st.sampled_from("ab0_/:*%@$#?-. ")


@budget(300)
@given(
    st.text(_KEY_CHARS, max_size=80)
    | st.builds(lambda k, s: k[:s], st.just(_KEY), st.integers(0, 120))
)
def test_data_keys_parse_or_raise_value_error(key: str) -> None:
    parts = run_decoder(lambda: rmw_zenoh.split_topic_key(key), (ValueError,))
    if parts is not None:
        domain, topic, _, _ = parts
        assert domain >= 0 and topic.startswith("/")


@budget(300)
@given(byte_edits)
def test_attachments_decode_or_raise_attachment_error(edits: list[tuple[int, int, bytes]]) -> None:
    data = mutate(Attachment(1, 2, bytes(16)).encode(), edits)
    value = run_decoder(lambda: Attachment.decode(data), (AttachmentError,))
    if value is not None:
        assert len(value.gid) == rmw_zenoh.GID_BYTES and value.encode() == data


@budget(300)
@given(st.text(max_size=60))
def test_topic_names_and_domains_are_checked(text: str) -> None:
    name = run_decoder(lambda: rmw_zenoh.topic_name(text), (UserError,))
    if name is not None:
        assert name.startswith("/") and "//" not in name and "__" not in name
    run_decoder(lambda: rmw_zenoh.domain_id(text), (UserError,))


@budget(300)
@given(st.text(_KEY_CHARS, max_size=60).map(lambda t: "ros2:" + t.replace(":", ",type=")))
def test_ros2_specs_parse_or_raise_source_error(spec: str) -> None:
    run_decoder(lambda: parse_source(spec), (SourceError,))

"""h264 crossings: the codec (`common.wire.video_codec`), the robot's streams
(`robotd.frame_path.video_streams`), a deployment's decoders (`cloudd.video_streams`), the
request's stream position, and keyframes priced apart by the policy and the simulator."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from cloudd.video_streams import VideoDecoders
from common.codec_profile import Fidelity, profile_codecs
from common.partition import TensorSpec, load_partition
from common.partition.runtime import SplitModel
from common.wire import CorruptPayload, InvalidValue, NeedKeyframe, ShapeMismatch
from common.wire.robot_to_cloud import InferRequest, VideoStream
from common.wire.tensor_codecs import EncodedTensor, decode_encoded, encode_tensor_as
from common.wire.video_codec import H264Decoder, H264Encoder
from robotd.frame_path.video_streams import VideoEncoders
from robotd.policies import make_policy
from robotd.policies.base import CutTable, Decision, Outcome
from robotd.policies.elastic import ElasticPolicy
from robotd.sim.simulator import Simulator
from robotd.sim.trace import trace_from_dict
from robotd.sources.frame_sources import PhotoSource
from tests.helpers.onnx_graphs import camera_classifier, save

H, W = 240, 320
SHAPE = [1, H, W, 3]
SPECS = [TensorSpec("image", "uint8", tuple(SHAPE))]


def camera(frames: int, *, height: int = H, width: int = W, speed: float = 1.0) -> list[np.ndarray]:
    """A camera panning over a real photograph (the `photo` source), as 1×H×W×3 RGB."""
    source = PhotoSource(height, width, seed=3, name="astronaut", motion="pan", speed=speed)
    return [cv2.cvtColor(source.read(), cv2.COLOR_BGR2RGB)[None] for _ in range(frames)]


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255**2 / mse)


def request(
    tensors: dict[str, EncodedTensor], video: VideoStream | None, robot: str = "r1", frame: int = 0
) -> InferRequest:
    return InferRequest(
        robot=robot,
        frame=frame,
        model_digest="d" * 64,
        cut=0,
        tensors=tensors,
        deadline_s=1.0,
        sent_at=0.0,
        video=video,
    )


# -- the codec -------------------------------------------------------------------------------------
def test_a_stream_of_a_moving_camera_decodes_in_order_and_p_frames_are_small() -> None:
    frames = camera(12)
    encoder, decoder = H264Encoder(H, W, 3), H264Decoder(H, W, 3)
    sizes = []
    for i, frame in enumerate(frames):
        data, key = encoder.encode(frame, keyframe=False)
        assert key == (i == 0)  # the first frame of a stream is always a keyframe
        got = decoder.decode(data, keyframe=key)
        assert got.shape == (H, W, 3)
        assert psnr_db(got, frame[0]) > 30.0
        sizes.append(len(data))
    jpeg50 = np.median([encode_tensor_as(f, "jpeg50").nbytes for f in frames])
    assert np.median(sizes[1:]) * 5 < sizes[0]  # a P-frame is a small share of a keyframe
    assert np.median(sizes[1:]) * 3 < jpeg50  # 4.8x here; 24x at 640×480 (docs/video.md)


def test_a_keyframe_asked_of_a_running_encoder_starts_a_fresh_decoder() -> None:
    frames = camera(5)
    encoder = H264Encoder(H, W, 3)
    for frame in frames[:3]:
        encoder.encode(frame, keyframe=False)
    data, key = encoder.encode(frames[3], keyframe=True)
    assert key
    got = H264Decoder(H, W, 3).decode(data, keyframe=True)  # SPS and PPS in band
    assert psnr_db(got, frames[3][0]) > 30.0
    p_frame, key = encoder.encode(frames[4], keyframe=False)
    assert not key
    # Alone, a P-frame is not decodable: named, never a guessed picture.
    with pytest.raises(CorruptPayload):
        H264Decoder(H, W, 3).decode(p_frame, keyframe=True)
    with pytest.raises(CorruptPayload, match="without its reference"):
        H264Decoder(H, W, 3).decode(p_frame, keyframe=False)


def test_stateless_h264_is_a_keyframe_of_its_own() -> None:
    frame = camera(1)[0]
    enc = encode_tensor_as(frame, "h264")
    assert enc.codec == "h264" and enc.shape == SHAPE
    got = decode_encoded(enc, max_bytes=frame.nbytes)
    assert got.shape == frame.shape and psnr_db(got, frame) > 30.0
    gray = np.ascontiguousarray(frame[0, :, :, 1])
    assert decode_encoded(encode_tensor_as(gray, "h264"), max_bytes=gray.nbytes).shape == (H, W)


@pytest.mark.parametrize(
    ("label", "mangle"),
    [
        ("truncated", lambda d: d[: len(d) // 2]),
        ("garbage", lambda d: bytes(range(256)) * 8),
        ("empty", lambda d: b""),
        ("flipped bits", lambda d: d[:300] + bytes(b ^ 0xFF for b in d[300:400]) + d[400:]),
        ("two pictures", lambda d: d + d),
    ],
)
def test_corrupt_h264_is_a_named_error(label: str, mangle: object) -> None:
    data = encode_tensor_as(camera(1)[0], "h264").data
    assert callable(mangle)
    with pytest.raises(CorruptPayload):
        H264Decoder(H, W, 3).decode(mangle(bytes(data)), keyframe=True)


def test_a_picture_bigger_than_declared_is_refused_before_it_is_allocated() -> None:
    big = np.zeros((2 * H, 2 * W, 3), np.uint8)
    data, _ = H264Encoder(2 * H, 2 * W, 3).encode(big, keyframe=True)
    with pytest.raises(CorruptPayload):  # max_pixels: the declared picture's
        H264Decoder(H, W, 3).decode(data, keyframe=True)
    small, _ = H264Encoder(H // 2, W, 3).encode(big[: H // 2, :W], keyframe=True)
    with pytest.raises(ShapeMismatch):
        H264Decoder(H, W, 3).decode(small, keyframe=True)


def test_odd_sides_are_not_h264() -> None:
    with pytest.raises(Exception, match="does not apply"):
        encode_tensor_as(np.zeros((1, 239, 320, 3), np.uint8), "h264")


# -- the request -----------------------------------------------------------------------------------
def test_video_tensors_need_their_stream_position_and_only_they_have_one() -> None:
    frame = camera(1)[0]
    video = VideoStream(stream=7, seq=0, keyframe=True)
    with pytest.raises(InvalidValue, match="stream position"):
        request({"image": encode_tensor_as(frame, "h264")}, None)
    with pytest.raises(InvalidValue, match="no tensor is a video"):
        request({"image": encode_tensor_as(frame, "jpeg50")}, video)
    sent = request({"image": encode_tensor_as(frame, "h264")}, video)
    got = InferRequest.from_wire(sent.to_wire())
    assert got.video == video and got.tensors["image"].codec == "h264"
    with pytest.raises(InvalidValue):
        VideoStream(stream=1, seq=-1, keyframe=False)


# -- the robot's streams ---------------------------------------------------------------------------
def test_the_robots_streams_send_a_keyframe_whenever_the_decoder_may_lack_the_last_picture() -> (
    None
):
    frames = camera(12)
    streams = VideoEncoders()
    seen = []

    def send(n: int, where: str = "edge-1", epoch: int = 1) -> VideoStream:
        due = streams.keyframe_due(where, epoch)
        _, video = streams.encode(n, where, epoch, {"image": frames[n]})
        assert video.keyframe == due  # the policy is told what will be sent
        seen.append(video)
        return video

    assert send(0).keyframe  # a new stream
    assert not send(1).keyframe and seen[1].seq == seen[0].seq + 1
    streams.skipped()  # a frame served on the robot (P, or another codec)
    assert send(2).keyframe
    video = send(3)
    assert not video.keyframe
    streams.unseen("edge-1", video)  # refused, lost or timed out
    assert send(4).keyframe
    old = seen[-1]
    assert not send(5).keyframe
    streams.unseen("edge-1", VideoStream(stream=old.stream - 1, seq=0, keyframe=True))
    assert not send(6).keyframe  # an older stream's loss does not touch this one
    assert send(7, epoch=2).keyframe  # a route change (a move, failover)
    # Round robin: each member has its own stream; the turns need no keyframe.
    assert send(8, "edge-2", 2).keyframe
    assert not send(9, "edge-1", 2).keyframe
    assert not send(10, "edge-2", 2).keyframe
    _, again = streams.encode(10, "edge-2", 2, {"image": frames[10]}, keyframe=True)
    assert again.keyframe and again.stream != seen[-1].stream  # a resend's keyframe: new stream
    assert streams.keyframes == 6 and streams.pframes == 6


# -- a deployment's decoders -----------------------------------------------------------------------
class Robot:
    """A robot's h264 requests for the decoder tests."""

    def __init__(self, name: str = "r1") -> None:
        self.name = name
        self.streams = VideoEncoders()
        self.frames = camera(8)
        self.n = 0

    def next(self, *, keyframe: bool = False, where: str = "edge-1") -> InferRequest:
        tensors, video = self.streams.encode(
            self.n, where, 1, {"image": self.frames[self.n % 8]}, keyframe=keyframe
        )
        self.n += 1
        return request(tensors, video, robot=self.name, frame=self.n)


def test_a_deployment_decodes_a_stream_in_order_and_refuses_what_it_cannot_decode() -> None:
    decoders = VideoDecoders()
    robot = Robot()
    key = robot.next()
    got = decoders.decode("r1", key, SPECS)["image"]
    assert got.shape == tuple(SHAPE) and psnr_db(got, robot.frames[0]) > 30.0
    decoders.decode("r1", robot.next(), SPECS)
    robot.next()  # lost on the way: the next P-frame's reference is missing here
    with pytest.raises(NeedKeyframe, match="send a keyframe"):
        decoders.decode("r1", robot.next(), SPECS)
    decoders.decode("r1", robot.next(keyframe=True), SPECS)
    corrupt = robot.next()
    data = bytes(corrupt.tensors["image"].data)
    broken = request(
        {"image": EncodedTensor(codec="h264", dtype="uint8", shape=SHAPE, data=data[:10])},
        corrupt.video,
        frame=corrupt.frame,
    )
    with pytest.raises(CorruptPayload):
        decoders.decode("r1", broken, SPECS)
    # The picture is broken: the next P-frame is refused, never answered from it.
    with pytest.raises(NeedKeyframe):
        decoders.decode("r1", robot.next(), SPECS)


def test_a_p_frame_of_a_stream_the_deployment_never_saw_is_refused_without_a_decoder() -> None:
    decoders = VideoDecoders()
    robot = Robot()
    robot.next()
    with pytest.raises(NeedKeyframe, match="no decoder here"):
        decoders.decode("r1", robot.next(), SPECS)
    assert len(decoders) == 0  # a P-frame makes no room for itself


def test_a_robot_cannot_continue_another_robots_stream() -> None:
    decoders = VideoDecoders()
    one, two = Robot("r1"), Robot("r2")
    decoders.decode("r1", one.next(), SPECS)
    decoders.decode("r2", two.next(), SPECS)
    # r2's P-frame arriving on r1's key (its body naming r1: the admission checks the body)
    # meets r1's stream, whose number it does not carry.
    with pytest.raises(NeedKeyframe):
        decoders.decode("r1", two.next(), SPECS)
    decoders.decode("r1", one.next(), SPECS)  # r1's own stream goes on


def test_decoders_are_bounded_in_count_and_idle_time_and_freed_on_standby() -> None:
    now = [0.0]
    decoders = VideoDecoders(max_streams=2, idle_s=10.0, clock=lambda: now[0])
    robots = [Robot(f"r{i}") for i in range(3)]
    decoders.decode("r0", robots[0].next(), SPECS)
    now[0] = 1.0
    decoders.decode("r1", robots[1].next(), SPECS)
    now[0] = 2.0
    decoders.decode("r2", robots[2].next(), SPECS)  # a flood: the one idle longest goes
    assert decoders.robots() == ["r1", "r2"] and decoders.evicted == 1
    with pytest.raises(NeedKeyframe):
        decoders.decode("r0", robots[0].next(), SPECS)
    now[0] = 20.0
    decoders.decode("r2", robots[2].next(keyframe=True), SPECS)
    assert decoders.robots() == ["r2"] and decoders.expired == 2
    decoders.forget("r2")
    assert len(decoders) == 0


def test_a_flood_of_new_robots_keeps_decoder_memory_bounded() -> None:
    decoders = VideoDecoders(max_streams=4)
    frame = camera(1)[0]
    key = encode_tensor_as(frame, "h264")
    for i in range(40):
        decoders.decode(
            f"r{i}",
            request({"image": key}, VideoStream(stream=i, seq=0, keyframe=True), robot=f"r{i}"),
            SPECS,
        )
    assert len(decoders) == 4 and decoders.evicted == 36


# -- the policy and the simulator ------------------------------------------------------------------
def video_profile() -> dict[str, object]:
    """A profile whose cut 0 crosses as JPEG (30 KB) or h264 (1.3 KB P-frames, 31 KB keyframes)."""
    return {
        "full_ms": 60.0,
        "output_bytes": 4000,
        "cuts": [
            {
                "index": 0,
                "bytes": 921_600,
                "prefix_ms": 0.0,
                "suffix_ms": 60.0,
                "codecs": [
                    {"name": "jpeg50", "bytes": 30_000, "encode_ms": 2.0, "decode_ms": 2.0},
                    {
                        "name": "h264",
                        "bytes": 1_300,
                        "key_bytes": 31_000,
                        "encode_ms": 2.0,
                        "decode_ms": 2.0,
                    },
                ],
            }
        ],
    }


def test_the_cut_table_keeps_keyframe_bytes_apart() -> None:
    cuts = CutTable.from_profile(video_profile())
    assert cuts.codecs == ("jpeg50", "h264")
    assert cuts.bytes.tolist() == [30_000, 1_300] and cuts.keys == (30_000.0, 31_000.0)
    assert cuts.subset([1]).keys == (31_000.0,)


def test_elastic_prices_a_keyframe_at_its_bytes_and_learns_both_kinds() -> None:
    policy = make_policy("elastic", video_profile(), {"hedge": False, "prune_dominated": False})
    assert isinstance(policy, ElasticPolicy)
    # A 1 Mbit/s uplink: 8 s per MB, and 20 ms of round trip.
    seen = [("jpeg50", 30_000, None), ("h264", 1_300, False), ("h264", 31_000, True)]
    for t in range(90):
        codec, sent, key = seen[t % 3]
        sent += 100 * (t % 7)  # the content moves the sizes a little
        y = 0.02 + sent * 8 / 1e6
        outcome = Outcome(prefix_s=0.002, cloud_s=y, bytes_up=sent, latency_s=y, keyframe=key)
        policy.observe(Decision(0, codec=codec), outcome)
    assert policy.learned_key_bytes()["0:h264"] > 25_000
    assert policy.learned_bytes()["0:h264"] < 2_000
    p_frame = policy.predicted_cloud_cost()["0:h264"]
    keyframe = policy.predicted_cloud_cost(keyframe=True)["0:h264"]
    # A keyframe (~31 KB: 0.27 s on this link) is predicted at what it costs: its excess over
    # the P-frame's prediction is learned directly.
    assert keyframe == pytest.approx(0.27, abs=0.03)
    assert keyframe > p_frame + 0.1
    assert policy.predicted_cloud_cost(keyframe=True)["0:jpeg50"] == pytest.approx(
        policy.predicted_cloud_cost()["0:jpeg50"]
    )


def test_the_simulator_sends_a_keyframe_after_every_frame_not_served_from_the_stream() -> None:
    segment = {
        "frames": 50,
        "uplink_mbit": 2,
        "downlink_mbit": 20,
        "rtt_ms": 10,
        "robot_cpu": 1.0,
        "cloud_speedup": 1.0,
    }
    trace = trace_from_dict(
        {"frames_per_second": 10, "segments": [segment], "noise": {"jitter": 0.0}}
    )
    sim = Simulator(CutTable.from_profile(video_profile()), trace, seed=1)
    result = sim.run("static:0:h264")
    latency = result.latency_s
    # The first frame is a keyframe (31 KB at 2 Mbit/s: ~0.12 s), the rest P-frames.
    assert latency[0] > latency[1:].max() + 0.1
    assert np.allclose(latency[1:], latency[1])


def test_elastic_moves_from_jpeg_to_h264_where_its_p_frames_pay() -> None:
    """JPEG 50 and h264 at cut 0, h264's coding 5 ms dearer (so neither is pruned): on a
    1.5 Mbit/s uplink its P-frames save ~0.14 s a frame. Elastic must take h264 although its
    first frame after JPEG frames is a keyframe as big as a JPEG (priced frame by frame the move
    never pays), and although both send a few KB (in MB the regression could not tell them
    apart: docs/video.md)."""
    profile = video_profile()
    profile["full_ms"] = 100.0
    cut = profile["cuts"][0]  # type: ignore[index]
    cut["suffix_ms"] = 100.0
    jpeg, h264 = cut["codecs"]
    jpeg.update(bytes=27_500, encode_ms=0.8, decode_ms=0.7)
    h264.update(bytes=2_000, key_bytes=28_000, encode_ms=3.5, decode_ms=3.1)
    segment = {
        "frames": 150,
        "uplink_mbit": 1.5,
        "downlink_mbit": 20,
        "rtt_ms": 10,
        "robot_cpu": 0.5,
        "cloud_speedup": 1.0,
    }
    trace = trace_from_dict({"frames_per_second": 5, "segments": [segment]})
    sim = Simulator(CutTable.from_profile(profile), trace, seed=1)
    assert CutTable.from_profile(profile).undominated(0.05).codecs == ("jpeg50", "h264")
    elastic, h264_only = sim.run("elastic"), sim.run("static:0:h264")
    robot, jpeg_only = sim.run("robot"), sim.run("static:0:jpeg50")
    served = [elastic.actions[c] for c in elastic.column[50:].tolist()]
    assert served.count("0:h264") >= 0.9 * len(served)
    mean = float(elastic.latency_s[50:].mean())
    assert mean <= 1.1 * float(h264_only.latency_s[50:].mean())
    best_without_video = min(float(robot.latency_s.mean()), float(jpeg_only.latency_s.mean()))
    assert mean < 0.75 * best_without_video


# -- the fidelity gate -----------------------------------------------------------------------------
def test_the_fidelity_gate_measures_h264_as_a_stream_of_the_robots_frames(tmp_path: Path) -> None:
    model = SplitModel(
        load_partition(str(save(camera_classifier(48, 64), tmp_path / "camera.onnx")))
    )
    frames = [{"image": f} for f in camera(6, height=48, width=64)]
    table = profile_codecs(model, frames, Fidelity(video=True))
    entry = {e["name"]: e for e in table[0]}["h264"]
    assert entry["lossy"] and entry["top1_agreement"] is not None
    assert entry["key_bytes"] > entry["bytes"]  # P-frames: the stream's, keyframes: alone
    assert entry["action"] == Fidelity().admits(entry["top1_agreement"], entry["rel_err"])
    # Off by default; a baseline that names it has it measured and kept whatever the bound.
    assert "h264" not in {e["name"] for e in profile_codecs(model, frames, Fidelity())[0]}
    strict = Fidelity(min_top1_agreement=1.0, max_output_rel_err=1e-9)
    named = {e["name"]: e for e in profile_codecs(model, frames, strict, {0: ["h264"]})[0]}
    assert named["h264"]["action"]

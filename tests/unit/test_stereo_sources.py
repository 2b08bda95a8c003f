"""Stereo frame sources and two image inputs: `stereo:world` (rendered along a bounded, seeded
loop), `stereo:LEFT,RIGHT` and `stereo:motorcycle` (a pair repeated, still or moving alike), their
errors, the views matched to a model's image inputs by name (a one-line error when they do not
fit), and cut 0 of zoo:stereo crossing as one JPEG or PNG per view that the cloud's decoder reads
back."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cloudd.validate import decode_tensors
from common.codec_profile import Fidelity, profile_codecs
from common.errors import UserError
from common.image_input import ImageInputs
from common.partition import TensorSpec, load_partition
from common.partition.runtime import SplitModel
from common.source_spec import SourceError
from common.wire.robot_to_cloud import InferRequest
from common.wire.tensor_codecs import encode_tensor_as
from nav.stereo_graph import LEFT_INPUT, RIGHT_INPUT
from nav.stereo_sources import LOOP_RADIUS_M, StereoPairSource, StereoWorldSource
from robotd.frame_path.entropy import frame_entropy
from robotd.robot_model import RobotModel
from robotd.sources.opening import open_source
from robotd.sources.stereo_frame import STEREO_VIEWS, StereoFrame, first_view

H, W = 120, 160
ROBOT_RADIUS_M = 0.2  # the closed loop's robot (nav.closed_loop.DEFAULT_ROBOT_RADIUS_M)
FRAMES_PER_LAP = round(2 * np.pi * LOOP_RADIUS_M / (0.3 * 0.1))  # default speed, 10 fps
MAX_D_COLL_M = 5.0  # nothing seen (nav.curvature's cap)
STEREO_SHAPE = (3, H, W)


def stereo_model() -> SplitModel:
    return SplitModel(load_partition("zoo:stereo", "auto", 3, STEREO_SHAPE))


def image_specs(*names: str, height: int = H, width: int = W) -> list[TensorSpec]:
    return [TensorSpec(n, "uint8", (1, height, width, 3)) for n in names]


def test_the_views_are_named_like_zoo_stereo_inputs() -> None:
    assert (LEFT_INPUT, RIGHT_INPUT) == STEREO_VIEWS


def test_world_frames_are_seeded_stereo_pairs_with_a_timestamp() -> None:
    source = open_source("stereo:world", height=H, width=W, seed=3)
    assert isinstance(source, StereoWorldSource) and source.views == STEREO_VIEWS
    frames = [source.read() for _ in range(3)]
    for f in frames:
        assert isinstance(f, StereoFrame) and tuple(f.views) == STEREO_VIEWS
        assert all(v.shape == (H, W, 3) and v.dtype == np.uint8 for v in f.views.values())
        assert first_view(f) is f.views["left"]
    assert frames[0].stamp_s <= frames[1].stamp_s <= frames[2].stamp_s
    # Two cameras a baseline apart see different images; consecutive frames differ (it moves).
    assert not np.array_equal(frames[0].views["left"], frames[0].views["right"])
    assert not np.array_equal(frames[0].views["left"], frames[1].views["left"])
    again = open_source("stereo:world", height=H, width=W, seed=3).read()
    other = open_source("stereo:world", height=H, width=W, seed=4).read()
    assert np.array_equal(again.views["left"], frames[0].views["left"])
    assert not np.array_equal(other.views["left"], frames[0].views["left"])
    assert 0.5 < frame_entropy(first_view(frames[0])) <= 1.0  # textured, camera-like


def test_world_path_stays_on_its_loop_and_never_touches_a_face() -> None:
    source = StereoWorldSource(H, W, seed=0, speed=2.0)  # the fastest: the most ground per frame
    poses = [source.pose_at(n) for n in range(0, 3 * FRAMES_PER_LAP)]
    assert all(abs(np.hypot(p.x, p.y) - LOOP_RADIUS_M) < 1e-9 for p in poses)
    clearance = min(source.world.clearance(p.x, p.y) for p in poses)
    assert clearance > ROBOT_RADIUS_M + 0.5, clearance
    still = StereoWorldSource(H, W, seed=0, speed=0.0)
    assert still.pose_at(0) == still.pose_at(100)


def test_world_pairs_are_rectified_the_stereo_model_sees_obstacles() -> None:
    """zoo:stereo on the source's frames, fed through the robot's input side: obstacles in
    range in every frame (a pair that did not match would give d_coll = 5 m everywhere)."""
    model = stereo_model()
    robot = RobotModel(model, "zoo:stereo")
    source = robot.open_source("stereo:world", seed=0)
    for _ in range(3):
        frame = source.read()
        for _ in range(9):  # a second apart
            source.read()
        (d_coll,) = model.run_full(robot.feeds(frame)).values()
        assert d_coll.shape == (1, 41)
        assert float(d_coll.min()) < MAX_D_COLL_M - 1.0, d_coll


def _write_pair(tmp_path: Path) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    right = np.roll(left, -4, axis=1)  # a plane 4 px of disparity away
    paths = tmp_path / "l.png", tmp_path / "r.png"
    for path, image in zip(paths, (left, right), strict=True):
        assert cv2.imwrite(str(path), image)
    return paths[0], paths[1], left, right


def test_a_pair_of_files_is_repeated_whole_without_motion(tmp_path: Path) -> None:
    lp, rp, left, right = _write_pair(tmp_path)
    source = open_source(f"stereo:{lp},{rp}", height=60, width=80)
    assert isinstance(source, StereoPairSource) and "still" in source.description
    a, b = source.read(), source.read()
    assert np.array_equal(a.views["left"], left) and np.array_equal(a.views["right"], right)
    assert np.array_equal(b.views["left"], left)
    small = open_source(f"stereo:{lp},{rp}", height=30, width=40).read()
    assert small.views["right"].shape == (30, 40, 3)


def test_a_moving_pair_moves_both_views_alike(tmp_path: Path) -> None:
    lp, _, _, _ = _write_pair(tmp_path)
    # The same file twice: whatever the camera does, the two views must stay identical.
    source = open_source(f"stereo:{lp},{lp},motion=mixed,speed=3", height=48, width=64, seed=2)
    frames = [source.read() for _ in range(4)]
    assert all(np.array_equal(f.views["left"], f.views["right"]) for f in frames)
    assert not np.array_equal(frames[0].views["left"], frames[3].views["left"])


def test_the_motorcycle_pair_opens_at_the_frame_size() -> None:
    frame = open_source("stereo:motorcycle,motion=pan", height=H, width=W).read()
    assert all(v.shape == (H, W, 3) for v in frame.views.values())
    assert not np.array_equal(frame.views["left"], frame.views["right"])


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("stereo:", "expected stereo:world"),
        ("stereo:world,speed=9", "speed must be in"),
        ("stereo:world,motion=pan", "unknown option 'motion'; known: speed"),
        ("stereo:world,speed", "expected name=value"),
        ("stereo:motorcycle,motion=spin", "motion='spin' is not one of"),
        ("stereo:motorcycle,speed=fast", "speed='fast' is not a number"),
        ("stereo:only-one.png", "needs two paths"),
        ("stereo:nope-left.png,nope-right.png", "image file not found: nope-left.png"),
    ],
)
def test_bad_stereo_specs_are_one_line_errors(spec: str, message: str) -> None:
    with pytest.raises(SourceError, match=message) as err:
        open_source(spec, height=H, width=W)
    assert "\n" not in str(err.value)


def test_a_pair_of_two_sizes_or_a_file_that_is_no_image_is_refused(tmp_path: Path) -> None:
    lp, _, _, _ = _write_pair(tmp_path)
    other = tmp_path / "small.png"
    cv2.imwrite(str(other), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(SourceError, match="views of a pair must be one size"):
        open_source(f"stereo:{lp},{other}", height=H, width=W)
    text = tmp_path / "notes.png"
    text.write_text("not an image")
    with pytest.raises(SourceError, match="not an image OpenCV can read"):
        open_source(f"stereo:{lp},{text}", height=H, width=W)


def test_views_feed_the_inputs_of_their_names_in_any_order() -> None:
    inputs = ImageInputs(image_specs("left", "right"), "stereo")
    left = np.full((H, W, 3), (10, 20, 30), np.uint8)  # BGR
    right = np.full((H, W, 3), 200, np.uint8)
    feeds = inputs.feeds({"right": right, "left": left})
    assert set(feeds) == {"left", "right"}
    assert feeds["left"].shape == (1, H, W, 3)
    assert tuple(feeds["left"][0, 0, 0]) == (30, 20, 10)  # RGB, the zoo's order
    assert int(feeds["right"].min()) == 200


def test_sources_that_do_not_fit_the_model_are_one_line_errors() -> None:
    stereo = ImageInputs(image_specs("left", "right"), "zoo:stereo")
    mono = ImageInputs(image_specs("input"), "zoo:vgg")
    mono.check_views(None, "synthetic")
    stereo.check_views(("right", "left"), "stereo:world")
    cases = [
        (stereo, None, "source synthetic gives one image a frame; model zoo:stereo takes 2"),
        (mono, STEREO_VIEWS, "gives 2 views a frame \\(left, right\\); model zoo:vgg takes one"),
        (ImageInputs(image_specs("a", "b"), "m"), STEREO_VIEWS, "matched to inputs by name"),
    ]
    for inputs, views, message in cases:
        with pytest.raises(UserError, match=message) as err:
            inputs.check_views(views, "synthetic" if views is None else "stereo:world")
        assert "\n" not in str(err.value)
    with pytest.raises(UserError, match="gives one image a frame"):
        stereo.feeds(np.zeros((H, W, 3), np.uint8))
    with pytest.raises(UserError, match="differ in size"):
        ImageInputs([*image_specs("left"), *image_specs("right", height=60, width=80)])


def test_robot_model_refuses_a_mono_source_on_zoo_stereo_at_open() -> None:
    robot = RobotModel(stereo_model(), "zoo:stereo")
    with pytest.raises(UserError, match="source synthetic gives one image a frame"):
        robot.open_source("synthetic", seed=0)


def test_cut_0_crosses_as_one_image_per_view_which_the_cloud_decodes() -> None:
    """jpeg80 and png at cut 0 encode each uint8 view on its own; the cloud's decoder reads both
    back at the cut's specs; JPEG is a small share of raw and keeps d_coll close."""
    model = stereo_model()
    robot = RobotModel(model, "zoo:stereo")
    source = robot.open_source("stereo:world", seed=1)
    feeds = robot.feeds(source.read())
    specs = model.cut_tensor_specs(0)
    assert sorted(s.name for s in specs) == ["left", "right"]
    crossing = model.run_prefix(0, feeds)
    raw_bytes = sum(s.nbytes for s in specs)
    for codec in ("jpeg80", "png"):
        encoded = {name: encode_tensor_as(a, codec) for name, a in crossing.items()}
        assert all(e.codec == codec and e.shape == [1, H, W, 3] for e in encoded.values())
        request = InferRequest(
            robot="r",
            frame=0,
            model_digest=model.digest,
            cut=0,
            tensors=encoded,
            deadline_s=1.0,
            sent_at=0.0,
            epoch=0,
        )
        decoded = decode_tensors(InferRequest.from_wire(request.to_wire()), specs)
        assert set(decoded) == {"left", "right"}
        if codec == "png":
            assert all(np.array_equal(decoded[n], crossing[n]) for n in decoded)
        else:
            assert sum(e.nbytes for e in encoded.values()) < raw_bytes / 5
    table = profile_codecs(model, [feeds], Fidelity(), {0: ["jpeg80"]})
    by_name = {e["name"]: e for e in table[0]}
    assert {"raw", "png", "jpeg80"} <= set(by_name)
    assert by_name["jpeg80"]["action"] and by_name["jpeg80"]["bytes"] < raw_bytes / 5

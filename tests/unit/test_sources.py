"""Frame sources: synthetic frames whose entropy really differs between key and flat frames (and
repeats with the seed), a video file written here with cv2.VideoWriter and read back (looping at
its end), clear errors for sources that cannot be opened, and the frame → model input adapter."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from common.errors import UserError
from common.partition import TensorSpec
from robotd.entropy import frame_entropy
from robotd.sources import (
    CameraSource,
    InputAdapter,
    SyntheticSource,
    VideoSource,
    open_source,
    parse_synthetic_options,
)

H, W = 48, 64
KEY_ENTROPY_MIN = 0.9  # textured frames fill most of the 256 grey levels
FLAT_ENTROPY_MAX = 0.4  # a handful of grey levels
VIDEO_FRAMES = 5
VIDEO_FPS = 10.0
# A camera index no test machine has.
MISSING_CAMERA = 97


def test_synthetic_key_frames_have_far_more_entropy_than_flat_ones() -> None:
    source = SyntheticSource(H, W, seed=1, key_every=2)
    frames = [source.read() for _ in range(8)]
    assert all(f.shape == (H, W, 3) and f.dtype == np.uint8 for f in frames)
    key = [frame_entropy(f) for f in frames[0::2]]
    flat = [frame_entropy(f) for f in frames[1::2]]
    assert min(key) >= KEY_ENTROPY_MIN, key
    assert max(flat) <= FLAT_ENTROPY_MAX, flat


def test_synthetic_key_fraction_is_honoured_and_repeats_with_the_seed() -> None:
    def entropies(seed: int, key: float, n: int = 200) -> list[float]:
        source = SyntheticSource(16, 16, seed=seed, key_fraction=key)
        return [frame_entropy(source.read()) for _ in range(n)]

    first = entropies(seed=5, key=0.3)
    assert first == entropies(seed=5, key=0.3)
    assert first != entropies(seed=6, key=0.3)
    share = np.mean([e > 0.6 for e in first])
    assert 0.2 <= share <= 0.4, share
    assert max(entropies(seed=5, key=0.0, n=20)) <= FLAT_ENTROPY_MAX
    assert min(entropies(seed=5, key=1.0, n=20)) >= 0.6


def test_synthetic_options_are_parsed_and_bad_ones_named() -> None:
    assert parse_synthetic_options("synthetic") == {}
    assert parse_synthetic_options("synthetic:key=0.5,every=3") == {
        "key_fraction": 0.5,
        "key_every": 3,
    }
    with pytest.raises(UserError, match="unknown option 'colour'; known: key, every"):
        open_source("synthetic:colour=red", height=H, width=W)
    with pytest.raises(UserError, match=r"key must be in \[0, 1\]"):
        open_source("synthetic:key=2", height=H, width=W)
    with pytest.raises(UserError, match="expected name=value"):
        open_source("synthetic:key", height=H, width=W)


def write_video(path: Path, frames: int = VIDEO_FRAMES) -> list[np.ndarray]:
    """A small MJPG video of frames with distinct brightness, written with OpenCV."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), VIDEO_FPS, (W, H))
    assert writer.isOpened(), "OpenCV cannot write MJPG here"
    written = []
    for i in range(frames):
        frame = np.full((H, W, 3), 30 + 40 * i, dtype=np.uint8)
        writer.write(frame)
        written.append(frame)
    writer.release()
    return written


def test_video_file_is_read_frame_by_frame_and_looped(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    written = write_video(path)
    with open_source(f"video:{path}", height=1, width=1) as source:
        assert isinstance(source, VideoSource)
        got = [source.read() for _ in range(VIDEO_FRAMES + 2)]
    assert all(f.shape == (H, W, 3) and f.dtype == np.uint8 for f in got)
    means = [float(f.mean()) for f in got]
    for mean, frame in zip(means, written, strict=False):
        assert abs(mean - float(frame.mean())) < 5  # MJPG is lossy, brightness survives
    # At its end the file starts again, so --frames N is honoured whatever its length.
    assert abs(means[VIDEO_FRAMES] - means[0]) < 5
    assert abs(means[VIDEO_FRAMES + 1] - means[1]) < 5


def test_missing_or_unreadable_video_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"video file not found: .*nope\.avi"):
        open_source(f"video:{tmp_path / 'nope.avi'}", height=H, width=W)
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"this is not a video")
    with pytest.raises(UserError, match=r"junk.avi"):
        VideoSource(junk)


def test_camera_that_cannot_be_opened_is_a_clear_error() -> None:
    with pytest.raises(UserError, match=f"cannot open camera {MISSING_CAMERA}"):
        CameraSource(MISSING_CAMERA)
    with pytest.raises(UserError, match="camera needs an index"):
        open_source("camera:front", height=H, width=W)


def test_unknown_source_names_the_accepted_forms() -> None:
    with pytest.raises(UserError, match=r"expected synthetic.*video:PATH or camera:INDEX"):
        open_source("rtsp://robot/stream", height=H, width=W)


def test_input_adapter_resizes_and_scales_to_the_model_input() -> None:
    frame = SyntheticSource(H, W, seed=0, key_every=1).read()
    nchw = InputAdapter(TensorSpec("image", "float32", (1, 3, 24, 32)))
    x = nchw(frame)
    assert x.shape == (1, 3, 24, 32) and x.dtype == np.float32
    assert float(x.min()) >= 0.0 and float(x.max()) <= 1.0
    # Channels come out as RGB: the adapter's first plane is OpenCV's last (red).
    small = cv2.resize(frame, (32, 24), interpolation=cv2.INTER_AREA)
    np.testing.assert_allclose(x[0, 0], small[:, :, 2] / 255.0, atol=1e-6)

    grey = InputAdapter(TensorSpec("image", "uint8", (1, H, W, 1)))(frame)
    assert grey.shape == (1, H, W, 1) and grey.dtype == np.uint8
    assert InputAdapter(TensorSpec("x", "float16", (3, H, W)))(frame).shape == (3, H, W)


@pytest.mark.parametrize(
    "spec",
    [
        TensorSpec("x", "float32", (1, 4)),
        TensorSpec("x", "float32", (2, 3, 8, 8)),
        TensorSpec("x", "int64", (1, 3, 8, 8)),
        TensorSpec("x", "float32", (1, 5, 8, 8)),
    ],
)
def test_input_adapter_refuses_inputs_that_are_not_images(spec: TensorSpec) -> None:
    with pytest.raises(UserError, match=r"model input 'x' .* is not an image"):
        InputAdapter(spec)

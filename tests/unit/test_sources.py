"""Frame sources: synthetic frames whose entropy really differs between key and flat frames (and
repeats with the seed), photographs through a moving virtual camera (deterministic, camera-like
motion, scene changes, natural-image JPEG sizes), a video file written here with cv2.VideoWriter
and read back (looping at its end), clear errors for sources that cannot be opened, and the
frame → model input adapter."""

from __future__ import annotations

import itertools
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.errors import UserError
from common.image_input import InputAdapter
from common.partition import TensorSpec
from common.photos import PHOTOS
from common.source_spec import (
    DEFAULT_CAMERA_SOURCE,
    KINDS,
    CameraMotion,
    CameraSpec,
    PhotoSpec,
    SourceError,
    SyntheticSpec,
    VideoSpec,
    parse_source,
)
from robotd.frame_path.entropy import frame_entropy
from robotd.sources.frame_sources import (
    PHOTO_SCENE_FRAMES,
    CameraSource,
    EndOfStream,
    PhotoSource,
    SyntheticSource,
    VideoSource,
)
from robotd.sources.opening import open_source

H, W = 48, 64
KEY_ENTROPY_MIN = 0.9  # textured frames fill most of the 256 grey levels
FLAT_ENTROPY_MAX = 0.4  # a handful of grey levels
VIDEO_FRAMES = 5
VIDEO_FPS = 10.0
# A camera index no test machine has.
MISSING_CAMERA = 97
# The photo source at a camera's size: QVGA.
CAM_H, CAM_W = 240, 320
# JPEG (quality 80) of a 320×240 photograph: noise takes far more, a flat frame far less.
JPEG_QUALITY = 80
PHOTO_JPEG_MIN_BYTES, PHOTO_JPEG_MAX_BYTES = 2_000, 40_000


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
    assert parse_source("synthetic") == SyntheticSpec("synthetic")
    assert parse_source("synthetic:key=0.5,every=3") == SyntheticSpec(
        "synthetic:key=0.5,every=3", key_fraction=0.5, key_every=3
    )
    with pytest.raises(UserError, match="unknown option 'colour'; known: key, every"):
        open_source("synthetic:colour=red", height=H, width=W)
    with pytest.raises(UserError, match=r"key must be in \[0, 1\]"):
        open_source("synthetic:key=2", height=H, width=W)
    with pytest.raises(UserError, match="expected name=value"):
        open_source("synthetic:key", height=H, width=W)


def mean_abs_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())


def jpeg_bytes(frame: np.ndarray) -> int:
    ok, data = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    assert ok
    return len(data)


def test_photo_frames_have_the_requested_shape_and_repeat_with_the_seed() -> None:
    source = open_source("photo", height=CAM_H, width=CAM_W, seed=7)
    assert isinstance(source, PhotoSource)
    frames = [source.read() for _ in range(5)]
    assert all(f.shape == (CAM_H, CAM_W, 3) and f.dtype == np.uint8 for f in frames)
    again = open_source("photo", height=CAM_H, width=CAM_W, seed=7)
    assert all(np.array_equal(f, again.read()) for f in frames)
    # frame_at gives the same frames in any order (what read() returns at that index).
    assert np.array_equal(again.frame_at(2), frames[2])
    other = open_source("photo", height=CAM_H, width=CAM_W, seed=8)
    assert not np.array_equal(other.read(), frames[0])
    assert open_source("photo", height=48, width=100).read().shape == (48, 100, 3)


def test_photo_frames_are_bgr_like_opencv_frames() -> None:
    # The coffee photograph is mostly a red cup and saucer: red must come out last (BGR).
    frame = PhotoSource(CAM_H, CAM_W, name="coffee", motion="zoom").read()
    blue, _, red = (float(frame[:, :, c].mean()) for c in range(3))
    assert red > blue + 30, (red, blue)


@pytest.mark.parametrize("motion", [m.value for m in CameraMotion])
def test_consecutive_photo_frames_differ_a_little_like_a_moving_camera(motion: str) -> None:
    source = open_source(f"photo,motion={motion}", height=CAM_H, width=CAM_W, seed=3)
    frames = [source.read() for _ in range(PHOTO_SCENE_FRAMES)]  # one scene: one photograph
    steps = [mean_abs_diff(a, b) for a, b in itertools.pairwise(frames)]
    assert min(steps) > 0.0, "the camera must move every frame"
    # Different photographs differ by tens of grey levels per pixel; one frame of camera motion
    # far less.
    firsts = [PhotoSource(CAM_H, CAM_W, name=name).read() for name in PHOTOS]
    between = [mean_abs_diff(a, b) for i, a in enumerate(firsts) for b in firsts[i + 1 :]]
    assert float(np.median(steps)) < 0.5 * float(np.median(between)), (steps, between)
    assert max(steps) < min(between), (max(steps), min(between))


def test_photo_speed_zero_is_a_still_camera_and_speed_scales_the_motion() -> None:
    still = PhotoSource(CAM_H, CAM_W, name="chelsea", speed=0.0)
    first = still.read()
    assert all(np.array_equal(first, still.read()) for _ in range(3))

    def mean_step(speed: float) -> float:
        source = PhotoSource(CAM_H, CAM_W, name="chelsea", motion="pan", seed=2, speed=speed)
        frames = [source.read() for _ in range(20)]
        return float(np.mean([mean_abs_diff(a, b) for a, b in itertools.pairwise(frames)]))

    assert mean_step(4.0) > 2 * mean_step(1.0)


def test_photo_scene_changes_cycle_through_the_photographs() -> None:
    source = PhotoSource(CAM_H, CAM_W, seed=0)
    n = PHOTO_SCENE_FRAMES
    shown = [source.photo_name(i * n) for i in range(len(PHOTOS))]
    assert sorted(shown) == sorted(PHOTOS), "every photograph takes a turn"
    assert source.photo_name(len(PHOTOS) * n) == shown[0], "then the cycle starts again"
    assert source.photo_name(n - 1) == shown[0] and source.photo_name(n) == shown[1]
    before, cut, after = source.frame_at(n - 2), source.frame_at(n - 1), source.frame_at(n)
    assert mean_abs_diff(cut, after) > 3 * mean_abs_diff(before, cut)
    # The order of the photographs comes from the seed.
    orders = {tuple(PhotoSource(8, 8, seed=s).names) for s in range(4)}
    assert len(orders) > 1
    # With a NAME the camera stays on that photograph: no cut at the scene boundary.
    named = PhotoSource(CAM_H, CAM_W, name="astronaut")
    assert {named.photo_name(i) for i in range(0, 5 * n, 7)} == {"astronaut"}
    assert mean_abs_diff(named.frame_at(n - 1), named.frame_at(n)) < 0.5 * mean_abs_diff(cut, after)


def test_photo_frames_have_natural_image_statistics() -> None:
    # A JPEG of a photograph is neither the size of noise nor that of a flat wall, and the size
    # varies with the scene as a camera's does.
    source = PhotoSource(CAM_H, CAM_W, seed=1)
    sizes = [jpeg_bytes(source.frame_at(n)) for n in range(0, len(PHOTOS) * PHOTO_SCENE_FRAMES, 25)]
    assert min(sizes) >= PHOTO_JPEG_MIN_BYTES and max(sizes) <= PHOTO_JPEG_MAX_BYTES, sizes
    assert max(sizes) > 1.5 * min(sizes), sizes
    noise = SyntheticSource(CAM_H, CAM_W, key_every=1).read()
    assert jpeg_bytes(noise) > PHOTO_JPEG_MAX_BYTES, "the bound must tell noise apart"
    flat = SyntheticSource(CAM_H, CAM_W, key_fraction=0.0).read()
    assert frame_entropy(source.frame_at(0)) > frame_entropy(flat)


def test_photo_options_are_parsed_and_bad_ones_named() -> None:
    assert parse_source("photo") == PhotoSpec("photo")
    assert parse_source("photo:rocket") == PhotoSpec("photo:rocket", name="rocket")
    assert parse_source("photo:coffee,motion=pan,speed=2") == PhotoSpec(
        "photo:coffee,motion=pan,speed=2", name="coffee", motion=CameraMotion.PAN, speed=2.0
    )
    assert parse_source("photo,motion=shake").motion == CameraMotion.SHAKE  # type: ignore[attr-defined]
    assert parse_source("photo:speed=0.5") == PhotoSpec("photo:speed=0.5", speed=0.5)
    assert open_source("photo,motion=zoom", height=H, width=W).description.startswith("photo")
    errors = {
        "photo:kitten": r"unknown photo 'kitten'; known: astronaut, coffee",
        "photo:coffee,motion=dolly": r"motion='dolly' is not one of pan, zoom, shake, mixed",
        "photo:coffee,speed=fast": r"speed='fast' is not a number",
        "photo:coffee,speed=-1": r"speed must be in \[0, 20\], got -1",
        "photo,speed=nan": r"speed must be in \[0, 20\], got nan",
        "photo:coffee,zoom=2": r"unknown option 'zoom'; known: motion, speed",
        "photo:coffee,pan": r"expected name=value options, got 'pan'",
    }
    for spec, message in errors.items():
        with pytest.raises(SourceError, match=message):
            open_source(spec, height=H, width=W)
    with pytest.raises(SourceError, match="photo source: height must be"):
        PhotoSource(0, W)


def test_camera_like_default_is_the_photo_source_and_synthetic_keeps_its_defaults() -> None:
    assert DEFAULT_CAMERA_SOURCE == "photo"
    assert isinstance(open_source(DEFAULT_CAMERA_SOURCE, height=H, width=W), PhotoSource)
    assert open_source("synthetic", height=H, width=W).description == (
        f"synthetic {W}x{H} (seed 0, key=0.25)"
    )


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


def test_a_video_plays_on_its_own_timeline_and_without_loop_ends_at_its_end(
    tmp_path: Path,
) -> None:
    """Regression: a 60-frame 15 fps file ran 1,184 frames at the config's 10 fps until killed.
    The file's frame rate is its timeline (continuing across loops), and `loop=false` ends it."""
    path = tmp_path / "clip.avi"
    write_video(path)
    with open_source(f"video:{path},loop=false", height=1, width=1) as source:
        assert isinstance(source, VideoSource) and not source.loop
        assert source.file_fps == pytest.approx(VIDEO_FPS)
        offsets = []
        for _ in range(VIDEO_FRAMES):
            offsets.append(source.next_offset_s())
            source.read()
        with pytest.raises(EndOfStream):
            source.read()
        assert source.next_offset_s() is None
    assert offsets == pytest.approx([i / VIDEO_FPS for i in range(VIDEO_FRAMES)])
    with open_source(f"video:{path}", height=1, width=1) as looped:
        for _ in range(VIDEO_FRAMES + 2):
            looped.read()
        assert looped.next_offset_s() == pytest.approx((VIDEO_FRAMES + 2) / VIDEO_FPS)


def test_video_specs_take_a_loop_option_after_the_path() -> None:
    assert parse_source("video:a.mp4,loop=false") == VideoSpec(
        "video:a.mp4,loop=false", path=Path("a.mp4"), loop=False
    )
    assert parse_source("video:a.mp4, loop=true").loop  # type: ignore[attr-defined]
    # A comma that no option follows belongs to the path.
    assert parse_source("video:take 1,2.mp4").path == Path("take 1,2.mp4")  # type: ignore[attr-defined]
    moved = parse_source("video:a.mp4,loop=false").resolved(lambda p: f"/fleet/{p}")
    assert str(moved) == "video:/fleet/a.mp4,loop=false"
    with pytest.raises(SourceError, match="loop='no'; expected true or false"):
        parse_source("video:a.mp4,loop=no")
    with pytest.raises(SourceError, match="video needs a file"):
        parse_source("video:,loop=false")


def test_missing_or_unreadable_video_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"video file not found: .*nope\.avi"):
        open_source(f"video:{tmp_path / 'nope.avi'}", height=H, width=W)
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"this is not a video")
    with pytest.raises(UserError, match=r"junk.avi"):
        VideoSource(junk)


def test_a_camera_is_named_by_index_or_by_its_linux_device() -> None:
    """Guards against `camera:/dev/video0`, what every Linux user types first, being refused."""
    assert parse_source("camera:/dev/video0") == CameraSpec(
        "camera:/dev/video0", index=0, device="/dev/video0"
    )
    assert parse_source("camera:/dev/video12").index == 12
    assert parse_source("camera:2") == CameraSpec("camera:2", index=2)
    for bad in ("camera:/dev/video", "camera:/dev/sda", "camera:video0", "camera:"):
        with pytest.raises(SourceError, match=r"e\.g\. camera:0 or camera:/dev/video0"):
            parse_source(bad)


def test_camera_that_cannot_be_opened_is_a_clear_error() -> None:
    with pytest.raises(UserError, match=f"cannot open camera {MISSING_CAMERA}"):
        CameraSource(MISSING_CAMERA)
    device = f"/dev/video{MISSING_CAMERA}"
    with pytest.raises(UserError, match=f"cannot open camera {device}"):
        open_source(f"camera:{device}", height=H, width=W)
    with pytest.raises(UserError, match="camera needs an index or a video device"):
        open_source("camera:front", height=H, width=W)


def test_unknown_source_names_the_accepted_forms() -> None:
    with pytest.raises(
        UserError,
        match=r"expected synthetic.*photo\[:NAME\].*video:PATH\[,loop=false\], bag:PATH\[:TOPIC\], "
        r"camera:INDEX\|/dev/videoINDEX, stereo:world.*"
        r"stereo:LEFT,RIGHT",
    ):
        open_source("rtsp://robot/stream", height=H, width=W)
    with pytest.raises(UserError, match="unknown frame source 'photos'"):
        open_source("photos", height=H, width=W)
    with pytest.raises(SourceError, match=f"known kinds: {', '.join(KINDS)}"):
        parse_source("webcam")


def test_a_spec_is_parsed_once_into_a_typed_value_and_paths_resolve_against_a_base() -> None:
    spec = parse_source("video:clips/run.mp4")
    assert spec == VideoSpec("video:clips/run.mp4", path=Path("clips/run.mp4"))
    assert parse_source(spec) is spec
    moved = spec.resolved(lambda p: f"/fleet/{p}")
    assert moved == VideoSpec("video:/fleet/clips/run.mp4", path=Path("/fleet/clips/run.mp4"))
    assert str(moved) == "video:/fleet/clips/run.mp4"
    # A kind takes only its own separator: `video,x` and `synthetic,key=1` are not sources.
    for text in ("video,x", "synthetic,key=1", "video:", "camera:"):
        with pytest.raises(SourceError):
            parse_source(text)


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


@pytest.mark.parametrize(
    ("dtype", "shape"),
    [
        ("float32", (1, 3, 24, 32)),
        ("float32", (1, 24, 32, 3)),
        ("uint8", (3, 24, 32)),
        ("float32", (1, 1, 24, 32)),
    ],
)
def test_input_adapter_image_gives_back_the_frame_the_model_saw(
    dtype: str, shape: tuple[int, ...]
) -> None:
    """What a recording of a run's input shows (`--record`): the adapter's inverse."""
    frame = PhotoSource(24, 32, seed=0).read()
    adapter = InputAdapter(TensorSpec("image", dtype, shape))
    image = adapter.image(adapter(frame))
    assert image.shape == (24, 32, 3) and image.dtype == np.uint8
    expected = (
        frame
        if adapter.channels == 3
        else cv2.cvtColor(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    )
    np.testing.assert_array_equal(image, expected)  # float32 holds every level exactly

"""The stereo ONNX graph: each stage against its reference (a known shift, the numpy camera
model, the numpy d_coll), the whole zoo model on a rendered wall, its split at the stage
boundaries, and accuracy on a real pair with ground truth against OpenCV's StereoBM."""

from __future__ import annotations

from collections.abc import Mapping

import cv2
import numpy as np
import onnx
import onnxruntime as ort
import pytest

from common import zoo
from common.errors import UserError
from common.models import resolve_model
from common.partition import load_partition
from nav.camera import CameraModel, points_from_disparity
from nav.curvature import CurvatureBins, ObstacleBand, arc_to_point, dcoll_from_points
from nav.disparity import DisparityRunner
from nav.stereo_eval import bad_pixels, opencv_disparity, stereo_motorcycle
from nav.stereo_graph import Stage, StereoPipeline, build_model
from nav.stereo_params import StereoParams, zoo_disparities
from nav.zoo_entry import STEREO_FORMAT

SMALL = (3, 48, 64)  # zoo shape C×H×W: D = 16


def run(model: onnx.ModelProto, feeds: Mapping[str, np.ndarray]) -> np.ndarray:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(
        model.SerializeToString(), options, providers=["CPUExecutionProvider"]
    )
    return session.run(None, dict(feeds))[0]


def texture(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A textured RGB image (blurred noise: matchable, like a real surface)."""
    rng = np.random.default_rng(seed)
    noise = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    return cv2.GaussianBlur(noise, (3, 3), 0)


def shifted(left: np.ndarray, disparity: float) -> np.ndarray:
    """The right view of a fronto-parallel plane: right(u) = left(u + disparity)."""
    h, w = left.shape[:2]
    map_x = np.tile(np.arange(w, dtype=np.float32) + np.float32(disparity), (h, 1))
    map_y = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    return cv2.remap(left, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def test_a_known_shift_is_found_and_no_match_points_outside_the_right_view() -> None:
    left = texture(48, 96)
    right = shifted(left, 5.0)
    disparity = DisparityRunner(StereoParams(16))(left, right).disparity
    assert disparity.shape == (48, 96) and disparity.dtype == np.float32
    interior = disparity[8:-8, 24:-8]
    assert np.isfinite(interior).mean() > 0.95
    assert np.nanmax(np.abs(interior - 5.0)) <= 0.5
    # column u can only match right columns u − d ≥ 0 (sub-pixel: within half a pixel)
    columns = np.arange(96)[None, :].repeat(48, axis=0)
    assert not (disparity > columns + 0.5).any()


def test_a_textureless_region_has_no_disparity_and_a_textured_one_has() -> None:
    """Regression: chance matches in a flat region (the sky above a wall at 640×480) became
    phantom obstacles in front of the robot. A band of flat grey with independent sensor noise
    in each view must be NaN; the textured rows around it must match."""
    rng = np.random.default_rng(4)
    left = texture(64, 96, seed=5)
    right = shifted(left, 5.0)
    for view in (left, right):
        noise = rng.normal(0.0, 2.0, (24, 96, 3))
        view[20:44] = np.clip(np.rint(200.0 + noise), 0, 255).astype(np.uint8)
    disparity = DisparityRunner(StereoParams(16))(left, right).disparity
    assert np.isnan(disparity[26:38]).all()
    textured = disparity[4:14, 24:-8]
    assert np.isfinite(textured).mean() > 0.9
    assert np.nanmax(np.abs(textured - 5.0)) <= 0.5


def test_the_small_region_filter_samples_a_grid_around_the_pixel() -> None:
    offsets = StereoParams(64).support_offsets
    assert len(offsets) == 48 and (0, 0) not in offsets
    assert {dy for dy, _ in offsets} == {-6, -4, -2, 0, 2, 4, 6}
    assert StereoParams(64, support_radius_px=2, support_step_px=2).support_offsets == (
        (-2, -2), (-2, 0), (-2, 2), (0, -2), (0, 2), (2, -2), (2, 0), (2, 2),
    )  # fmt: skip


def test_points_stage_matches_the_camera_model() -> None:
    camera = CameraModel.for_image(32, 24)
    pipeline = StereoPipeline(StereoParams(16), camera)
    rng = np.random.default_rng(1)
    disparity = rng.uniform(0.5, 15.0, (24, 32)).astype(np.float32)
    disparity[rng.random((24, 32)) < 0.2] = np.nan
    disparity[0, :4] = 0.0  # at infinity: no point
    model = build_model(pipeline, Stage.DISPARITY, Stage.POINTS, 24, 32)
    got = run(model, {"disparity": disparity[None, None]})[0]
    want = points_from_disparity(disparity, camera)
    assert got.shape == (24, 32, 3)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5, equal_nan=True)


def test_dcoll_stage_matches_the_numpy_reference() -> None:
    bins, band = CurvatureBins(2.0, 41), ObstacleBand(0.05, 0.6, 5.0)
    pipeline = StereoPipeline(StereoParams(16), CameraModel.for_image(64, 48), bins, band)
    rng = np.random.default_rng(2)
    n = 48 * 64
    points = np.stack(
        [rng.uniform(-2, 2, n), rng.uniform(-0.5, 4, n), rng.uniform(-0.2, 1.0, n)], axis=-1
    )
    # float32 against float64 must not round differently: keep clear of bin and band edges
    k, _ = arc_to_point(points[:, 0], points[:, 1])
    position = (k + bins.k_max_per_m) / bins.step_per_m
    edge = np.abs(position - np.floor(position) - 0.5) < 1e-3
    edge |= np.minimum(np.abs(points[:, 2] - 0.05), np.abs(points[:, 2] - 0.6)) < 1e-4
    points[edge] = np.nan
    points[rng.random(n) < 0.1] = np.nan
    points = points.astype(np.float32)
    model = build_model(pipeline, Stage.POINTS, Stage.DCOLL, 48, 64)
    got = run(model, {"points": points.reshape(1, 48, 64, 3)})
    want = dcoll_from_points(points.astype(np.float64), bins, band)
    assert got.shape == (1, bins.count)
    assert (want < band.max_range_m).sum() > 20  # most bins see an obstacle
    np.testing.assert_allclose(got[0], want, rtol=1e-5)


def test_the_zoo_model_sees_a_wall_at_its_distance() -> None:
    """Whole pipeline, images → d_coll, at 320×240: a textured wall 1 m in front of the camera."""
    ref = resolve_model("zoo:stereo", (3, 240, 320))
    assert ref.path.name == f"stereo-3x240x320-v{STEREO_FORMAT}.onnx"
    camera = CameraModel.for_image(320, 240)
    left = texture(240, 320, seed=3)
    right = shifted(left, camera.fx_px * camera.baseline_m / 1.0)  # 16.6 px
    d_coll = run(onnx.load(str(ref.path)), {"left": left[None], "right": right[None]})[0]
    bins, band = CurvatureBins(), ObstacleBand()
    centres = bins.centres()
    straight = d_coll[np.argmin(np.abs(centres))]
    assert straight == pytest.approx(1.0 + camera.forward_m, abs=0.03)
    # the wall spans the 60° field of view, x within ±0.58 m at y = 1.1 m: |K| ≤ 0.74
    seen = d_coll < band.max_range_m
    assert seen[np.abs(centres) <= 0.6].all() and not seen[np.abs(centres) >= 1.0].any()


def test_the_zoo_model_splits_at_the_stage_boundaries() -> None:
    c, h, w = SMALL
    d = zoo_disparities(w)
    part = load_partition("zoo:stereo", input_shape=SMALL)
    assert [cut.tensors for cut in part.cuts] == [
        ["left", "right"],
        ["grey"],
        ["census"],
        ["disparity"],
        ["points"],
    ]
    assert all(cut.verified and cut.max_abs_err == 0.0 for cut in part.cuts)
    sizes = {cut.tensors[-1]: cut.bytes for cut in part.cuts}
    assert sizes == {
        "right": 2 * h * w * c,
        "grey": 2 * h * w,
        "census": 2 * 8 * h * w,
        "disparity": 4 * h * w,
        "points": 12 * h * w,
    }
    # The cost volume is a cut too, pruned as it sends D times the disparity's bytes for the
    # same robot FLOPs; every cut kept: D·H·W floats.
    every = load_partition("zoo:stereo", input_shape=SMALL, prune=False)
    volume = {cut.tensors[0]: cut.bytes for cut in every.cuts if len(cut.tensors) == 1}
    assert volume["cost"] == volume["cost_agg"] == 4 * d * h * w
    assert zoo.get("stereo").name == "stereo"


def test_disparity_beats_opencv_stereobm_on_motorcycle() -> None:
    """bad-2 (invalid counted as wrong) over 0..63 px: ours at most StereoBM's best block size."""
    left, right, truth = stereo_motorcycle()
    ours = bad_pixels(DisparityRunner(StereoParams(64))(left, right).disparity, truth)
    bm = min(
        (
            bad_pixels(opencv_disparity(left, right, 64, "bm", block), truth)
            for block in (5, 9, 15, 21)
        ),
        key=lambda a: a.bad,
    )
    assert ours.bad <= bm.bad, (ours, bm)
    assert ours.bad < 0.2 and ours.density > 0.8  # docs/navigation.md: 18.2% at 84% density


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: StereoParams(1), "max disparity must be an integer in 2..512"),
        (lambda: StereoParams(64, window_px=8), "odd number"),
        (lambda: StereoParams(64, uniqueness=1.0), "uniqueness"),
        (lambda: StereoParams(64).check_image(100, 50), "more than the image width"),
        (lambda: StereoParams(64, min_support=49), "min support must be in 0..48"),
        (lambda: StereoParams(64, support_step_px=0), "support radius and step"),
    ],
)
def test_bad_parameters_are_named(make: object, message: str) -> None:
    with pytest.raises(UserError, match=message):
        make()  # type: ignore[operator]


def test_zoo_stereo_needs_colour_images() -> None:
    with pytest.raises(UserError, match="3xHxW; got 1x48x64"):
        resolve_model("zoo:stereo", (1, 48, 64))

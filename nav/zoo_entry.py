"""``zoo:stereo``: the stereo pipeline in the model zoo (entry point group ``elasticfog.zoo``).

The zoo's shape option is the size of one camera image, C×H×W with C = 3 (default 3x240x320);
the model's inputs are the left and right images, uint8 1×H×W×3 each, and its output ``d_coll``
(1×B). The disparity range is a fifth of the width (64 at 320×240, 128 at 640×480) and the
camera is :meth:`nav.camera.CameraModel.for_image` at that size, for the geometry given as the
zoo's build options ``baseline_m``, ``hfov_deg`` and ``height_m`` (fleet.yaml ``nav: camera:``;
defaults 0.06 m, 60°, 0.30 m). The built model's metadata ``nav.camera`` states the camera it
was built for. Kept free of heavy imports: the zoo loads this module to list its models.
"""

from __future__ import annotations

from typing import Any

from common.defaults import (
    DEFAULT_STEREO_BASELINE_M,
    DEFAULT_STEREO_HEIGHT_M,
    DEFAULT_STEREO_HFOV_DEG,
)
from common.errors import UserError
from common.zoo import ZooGraph

# Bump when the graph changes for the same shape (cached exports are named by it).
# 2: the metadata names the `points` cut (elasticfog.cut.points) for the offloading options.
# 3: the disparity stage's small-region filter (phantom obstacles at 640×480).
# 4: the metadata declares d_coll a distance output (elasticfog.output.d_coll), for the fidelity
# gate.
STEREO_FORMAT = 4


def build_stereo(
    shape: tuple[int, int, int],
    *,
    baseline_m: float = DEFAULT_STEREO_BASELINE_M,
    hfov_deg: float = DEFAULT_STEREO_HFOV_DEG,
    height_m: float = DEFAULT_STEREO_HEIGHT_M,
) -> Any:
    """The whole pipeline, images to d_coll, for camera images of shape (3, H, W) from a stereo
    camera of that baseline (m), horizontal field of view (degrees) and height (m)."""
    from nav.camera import CameraModel
    from nav.stereo_graph import StereoPipeline, build_model
    from nav.stereo_params import StereoParams, zoo_disparities

    channels, height, width = shape
    if channels != 3:
        raise UserError(
            f"zoo:stereo takes colour camera images, 3xHxW; got {channels}x{height}x{width}"
        )
    pipeline = StereoPipeline(
        StereoParams(zoo_disparities(width)),
        CameraModel.for_image(width, height, hfov_deg, baseline_m, height_m),
    )
    return build_model(pipeline, height=height, width=width)


STEREO = ZooGraph(
    "stereo",
    "Stereo navigation pipeline (two uint8 images → d_coll per curvature); no weights",
    build_stereo,
    STEREO_FORMAT,
    {
        "baseline_m": DEFAULT_STEREO_BASELINE_M,
        "hfov_deg": DEFAULT_STEREO_HFOV_DEG,
        "height_m": DEFAULT_STEREO_HEIGHT_M,
    },
)

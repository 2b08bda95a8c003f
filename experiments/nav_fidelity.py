"""`bench nav`'s fidelity rows: what each image codec does to zoo:stereo's answers, d_coll and the
disparity map, against the same pair sent raw (the fidelity gate's measures,
`common.codec_profile`), and whether the fleet's default bound admits it.

Both images of a pair cross in the codec (cut 0, as the robot sends them), the whole pipeline runs
on what the cloud decodes, and the answers are compared with the pipeline run on the raw images:

- d_coll (1×B, metres per curvature bin): the relative L2 error over the bins (what
  `fidelity.max_output_rel_err` bounds) and the largest error of one bin relative to its raw
  value (what the shared control feels: an over-estimate of d_coll(K) lets the robot drive that
  much closer before it brakes);
- the disparity map (an intermediate tensor here, an output for a model that ends at it): the
  share of pixels off by more than 1 px, a disparity present on one side only counting as off
  (what `fidelity.max_bad_pixel_share` bounds).

Frames: rendered pairs of the navigation world (`stereo:world`, the robot's source in
`bench nav`) and Middlebury's Motorcycle resized to the same size (`stereo:motorcycle`).

The gate judges d_coll, the model's output, a distance output (`OutputKind.DISTANCE`): a codec
passes when on every frame every bin's relative error stays within `fidelity.max_output_rel_err`
(`passes`; the default 0.05 is within the 0.2 below). The bound the shared control tolerates
(docs/navigation.md): the commanded speed v = sqrt(2·a_max·s) lets the robot stop within
s·a_max/a_brake, so d_coll(K) may be over-estimated by up to 1 − a_max/a_brake = 20% (the
paper's 8 and 10 m/s²) and the robot still stops before the obstacle (`TOLERATED_BIN_REL_ERR`).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import onnx
import onnxruntime as ort

from common.codec_profile import (
    Fidelity,
    bad_pixel_share,
    relative_error,
    worst_relative_error,
)
from common.wire.tensor_codecs import decode_encoded, encode_tensor_as
from nav.shared_control import PAPER_A_BRAKE_MPS2, PAPER_A_MAX_MPS2
from nav.stereo_eval import stereo_motorcycle
from nav.stereo_graph import LEFT_INPUT, RIGHT_INPUT, Stage
from nav.stereo_sources import StereoWorldSource
from nav.zoo_entry import build_stereo
from robotd.sources.stereo_frame import LEFT_VIEW, RIGHT_VIEW

CODECS = ("png", "jpeg95", "jpeg90", "jpeg80", "jpeg70", "jpeg50")
TOLERATED_BIN_REL_ERR = 1.0 - PAPER_A_MAX_MPS2 / PAPER_A_BRAKE_MPS2
"""Over-estimate of one bin of d_coll the shared control still stops in time for (module doc)."""
# The world source's first frames are near each other: take every few-th.
WORLD_STRIDE = 10


def _session(width: int, height: int) -> ort.InferenceSession:
    """zoo:stereo with the disparity map as a second output."""
    model = build_stereo((3, height, width))
    model.graph.output.append(
        onnx.helper.make_tensor_value_info(
            Stage.DISPARITY.value, onnx.TensorProto.FLOAT, [1, 1, height, width]
        )
    )
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    return ort.InferenceSession(model.SerializeToString(), options)


def _pairs(width: int, height: int, frames: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(source, left RGB, right RGB): rendered frames, then the Motorcycle pair."""
    source = StereoWorldSource(height, width)
    out = []
    for n in range(frames * WORLD_STRIDE):
        frame = source.read()
        if n % WORLD_STRIDE == 0:
            left = cv2.cvtColor(frame.views[LEFT_VIEW], cv2.COLOR_BGR2RGB)
            right = cv2.cvtColor(frame.views[RIGHT_VIEW], cv2.COLOR_BGR2RGB)
            out.append(("world", left, right))
    left, right, _truth = stereo_motorcycle()
    size = (width, height)
    resize = cv2.INTER_AREA
    out.append(
        ("motorcycle", cv2.resize(left, size, interpolation=resize), cv2.resize(right, size))
    )
    return out


def measure(width: int, height: int, frames: int) -> list[dict[str, Any]]:
    session = _session(width, height)
    names = [Stage.DCOLL.value, Stage.DISPARITY.value]

    def run(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        feeds = {LEFT_INPUT: left[None], RIGHT_INPUT: right[None]}
        d_coll, disparity = session.run(names, feeds)
        return np.asarray(d_coll), np.asarray(disparity)

    rows = []
    for source, left, right in _pairs(width, height, frames):
        want_d, want_disp = run(left, right)
        for codec in CODECS:
            views = []
            nbytes = 0
            for image in (left, right):
                encoded = encode_tensor_as(image[None], codec)
                nbytes += encoded.nbytes
                views.append(decode_encoded(encoded, max_bytes=image.nbytes)[0])
            got_d, got_disp = run(views[0], views[1])
            rows.append(
                {
                    "size": f"{width}x{height}",
                    "source": source,
                    "codec": codec,
                    "bytes": nbytes,
                    "d_coll_rel_err": relative_error(got_d, want_d),
                    "d_coll_max_bin_rel_err": worst_relative_error(got_d, want_d),
                    "disparity_bad1_share": bad_pixel_share(got_disp, want_disp),
                }
            )
    return rows


def summary(rows: list[dict[str, Any]], fidelity: Fidelity | None = None) -> list[dict[str, Any]]:
    """Per (size, source kind, codec): the worst frame of each measure, the median bytes, and
    whether the bound (default: the fleet's default) admits the codec (`passes`: every bin of
    d_coll, a distance output, within max_output_rel_err on every frame; `within_tolerance`:
    every bin within what the shared control tolerates)."""
    bound = fidelity or Fidelity()
    out = []
    keys = sorted({(r["size"], r["source"], r["codec"]) for r in rows}, key=str)
    for size, source, codec in keys:
        sel = [r for r in rows if (r["size"], r["source"], r["codec"]) == (size, source, codec)]
        out.append(
            {
                "size": size,
                "source": source,
                "codec": codec,
                "frames": len(sel),
                "bytes": float(np.median([r["bytes"] for r in sel])),
                "d_coll_rel_err": max(r["d_coll_rel_err"] for r in sel),
                "d_coll_max_bin_rel_err": max(r["d_coll_max_bin_rel_err"] for r in sel),
                "disparity_bad1_share": max(r["disparity_bad1_share"] for r in sel),
                "passes": all(bound.admits(None, r["d_coll_max_bin_rel_err"]) for r in sel),
                "within_tolerance": all(
                    r["d_coll_max_bin_rel_err"] <= TOLERATED_BIN_REL_ERR for r in sel
                ),
            }
        )
    return out


def markdown(rows: list[dict[str, Any]]) -> str:
    head = (
        "| size | frames | codec | bytes (pair) | d_coll rel. L2 err | d_coll worst bin "
        "| disparity bad-1 | admitted |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['size']} | {r['source']} ({r['frames']}) | {r['codec']} | {r['bytes']:,.0f} | "
            f"{r['d_coll_rel_err']:.4f} | {r['d_coll_max_bin_rel_err']:.3f} | "
            f"{r['disparity_bad1_share']:.3f} | {'yes' if r['passes'] else 'no'} |"
        )
    return "\n".join(lines)

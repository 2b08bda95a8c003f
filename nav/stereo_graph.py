"""The stereo pipeline as one ONNX graph, built with onnx.helper: no learned weights.

Stages, in graph order; the tensor between two stages is a natural cut (sizes per pixel of one
H×W view, D disparities, B curvature bins):

==========  =====================  ==========  ==============================================
tensor      dtype, shape           per pixel   made by
==========  =====================  ==========  ==============================================
left/right  uint8 1×H×W×3 each     6 B         the camera (RGB, ``common.zoo.CAMERA_ORDER``)
grey        uint8 2×1×H×W          2 B         integer luma (77R + 150G + 29B) >> 8, as a MatMul;
                                               the two views as a batch of two from here on
census      bool 2×P×H×W           2P B        sparse census: neighbour < centre at P points,
                                               one Conv (neighbour − centre) and a sign
cost        float 1×D×H×W          4D B        Hamming distance of the census codes at each
                                               disparity 0..D−1 (Xor, sum)
cost_agg    float 1×D×H×W          4D B        box filter (window × window) as a depthwise
                                               convolution
disparity   float 1×1×H×W          4 B         winner-take-all; uniqueness, left-right and
                                               cost-share checks; parabola sub-pixel refinement;
                                               small-region filter; NaN where invalid
points      float 1×H×W×3          12 B        camera model (one 3×3 MatMul) into the ground frame
                                               of :mod:`nav.camera`; NaN where no point
d_coll      float 1×B              —           distance to collision per curvature bin
                                               (:mod:`nav.curvature`)
==========  =====================  ==========  ==============================================

Everything up to the sub-pixel step is integer-valued in float32 (exact sums), so a split model
computes the same costs and the same winners as the whole one, bit for bit: a near-tie between
two disparities cannot flip between prefix and suffix.

The op order inside each stage is chosen for the partitioner, which cuts wherever at most two
tensors cross and prunes cuts that send more bytes for the same robot FLOPs: every stage boundary
is a one-tensor cut, and inside a stage the crossing tensors are either three or more, or more
bytes than the stage's output. The partitioner counts only Conv/Gemm/MatMul FLOPs, so ``cost`` and
``cost_agg`` (4D bytes per pixel) are pruned as costing the robot no more than ``census`` and
``disparity``; ``--all-cuts`` keeps them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from common.codec_profile import OUTPUT_KIND_PREFIX, OutputKind
from common.partition.named_cuts import NAMED_CUT_PREFIX
from nav.camera import CameraModel
from nav.curvature import CurvatureBins, ObstacleBand
from nav.stereo_params import StereoParams

OPSET = 17
IR_VERSION = 8
LEFT_INPUT = "left"
RIGHT_INPUT = "right"
# Symbolic dimensions of a graph built for any image size.
HEIGHT_DIM = "height"
WIDTH_DIM = "width"
# ITU-R BT.601 luma in 8-bit fixed point (sums to 256), per channel in R, G, B order.
LUMA_RGB = (77, 150, 29)
LUMA_SHIFT = 256.0
# Larger than any aggregated cost: fills the disparities a pixel cannot have.
BIG_COST = 1.0e9
INT64_MAX = np.iinfo(np.int64).max


class Stage(str, Enum):
    """The stages' output tensors, in graph order (IMAGES: the two input images)."""

    IMAGES = "images"
    GREY = "grey"
    CENSUS = "census"
    COST = "cost"
    COST_AGG = "cost_agg"
    DISPARITY = "disparity"
    POINTS = "points"
    DCOLL = "d_coll"


STAGE_ORDER: tuple[Stage, ...] = tuple(Stage)


@dataclass(frozen=True)
class StereoPipeline:
    """Everything the graph bakes in: the matcher, the camera and the obstacle geometry."""

    params: StereoParams
    camera: CameraModel
    bins: CurvatureBins = field(default_factory=CurvatureBins)
    band: ObstacleBand = field(default_factory=ObstacleBand)

    def stage_spec(
        self, stage: Stage, height: int | str, width: int | str
    ) -> list[tuple[str, int, list[Any]]]:
        """(name, ONNX element type, shape) of the tensors a stage hands on."""
        d, p, b = self.params.max_disparity, len(self.params.census), self.bins.count
        h, w = height, width
        specs: dict[Stage, list[tuple[str, int, list[Any]]]] = {
            Stage.IMAGES: [
                (LEFT_INPUT, TensorProto.UINT8, [1, h, w, 3]),
                (RIGHT_INPUT, TensorProto.UINT8, [1, h, w, 3]),
            ],
            Stage.GREY: [(Stage.GREY.value, TensorProto.UINT8, [2, 1, h, w])],
            Stage.CENSUS: [(Stage.CENSUS.value, TensorProto.BOOL, [2, p, h, w])],
            Stage.COST: [(Stage.COST.value, TensorProto.FLOAT, [1, d, h, w])],
            Stage.COST_AGG: [(Stage.COST_AGG.value, TensorProto.FLOAT, [1, d, h, w])],
            Stage.DISPARITY: [(Stage.DISPARITY.value, TensorProto.FLOAT, [1, 1, h, w])],
            Stage.POINTS: [(Stage.POINTS.value, TensorProto.FLOAT, [1, h, w, 3])],
            Stage.DCOLL: [(Stage.DCOLL.value, TensorProto.FLOAT, [1, b])],
        }
        return specs[stage]


def build_model(
    pipeline: StereoPipeline,
    first: Stage = Stage.IMAGES,
    last: Stage = Stage.DCOLL,
    height: int | None = None,
    width: int | None = None,
) -> onnx.ModelProto:
    """The graph from stage ``first``'s tensors to stage ``last``'s. Without ``height`` and
    ``width`` the image size is symbolic: the model runs on any pair (the CLI's disparity)."""
    start, stop = STAGE_ORDER.index(first), STAGE_ORDER.index(last)
    if stop <= start:
        raise ValueError(f"stage {last.value} does not come after {first.value}")
    h: int | str = HEIGHT_DIM if height is None else height
    w: int | str = WIDTH_DIM if width is None else width
    graph = _StereoGraph(pipeline)
    inputs = pipeline.stage_spec(first, h, w)
    current = [name for name, _, _ in inputs]
    for stage in STAGE_ORDER[start + 1 : stop + 1]:
        current = [graph.step(stage, current)]
    outputs = pipeline.stage_spec(last, h, w)
    model = helper.make_model(
        helper.make_graph(
            graph.nodes,
            f"stereo_{first.value}_to_{last.value}",
            [helper.make_tensor_value_info(*spec) for spec in inputs],
            [helper.make_tensor_value_info(*spec) for spec in outputs],
            graph.initializers,
        ),
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="elasticfog.nav",
    )
    # helper stamps the newest IR version this onnx knows; the one released with the opset
    # (onnx 1.12, IR 8) lets older runtimes load the file too.
    model.ir_version = IR_VERSION
    helper.set_model_props(model, _metadata(pipeline))
    onnx.checker.check_model(model, full_check=True)
    return model


def _metadata(pipeline: StereoPipeline) -> dict[str, str]:
    """What a consumer of the outputs needs to read them (bin centres, camera), and the cut the
    offloading options name (`common.partition.named_cuts`: option 2 runs up to the points on
    the robot, option 3 runs the segment up to them in the cloud)."""
    cam, bins = pipeline.camera, pipeline.bins
    return {
        f"{NAMED_CUT_PREFIX}points": Stage.POINTS.value,
        # d_coll is 1×B like a classifier's scores, but metres: the fidelity gate bounds each
        # bin's relative error instead of the argmax (`common.codec_profile.OutputKind`).
        f"{OUTPUT_KIND_PREFIX}{Stage.DCOLL.value}": OutputKind.DISTANCE.value,
        "nav.max_disparity": str(pipeline.params.max_disparity),
        "nav.bins.k_max_per_m": repr(bins.k_max_per_m),
        "nav.bins.count": str(bins.count),
        "nav.max_range_m": repr(pipeline.band.max_range_m),
        "nav.camera": ",".join(
            repr(v)
            for v in (cam.fx_px, cam.baseline_m, cam.cx_px, cam.cy_px, cam.height_m, cam.forward_m)
        ),
    }


class _StereoGraph:
    """Nodes and initializers of the graph, one private step per stage."""

    def __init__(self, pipeline: StereoPipeline) -> None:
        self.p = pipeline.params
        self.camera = pipeline.camera
        self.bins = pipeline.bins
        self.band = pipeline.band
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self._consts: dict[tuple[str, tuple[int, ...], bytes], str] = {}
        self._count = 0

    def step(self, stage: Stage, inputs: list[str]) -> str:
        steps: dict[Stage, Callable[..., str]] = {
            Stage.GREY: self._grey,
            Stage.CENSUS: self._census,
            Stage.COST: self._cost,
            Stage.COST_AGG: self._aggregate,
            Stage.DISPARITY: self._disparity,
            Stage.POINTS: self._points,
            Stage.DCOLL: self._dcoll,
        }
        return steps[stage](*inputs)

    # -- writing --

    def const(self, value: Any, dtype: Any = np.float32) -> str:
        """An initializer holding ``value`` (one per distinct value)."""
        array = np.asarray(value, dtype=dtype)
        key = (array.dtype.str, array.shape, array.tobytes())
        name = self._consts.get(key)
        if name is None:
            name = f"c{len(self._consts)}"
            self._consts[key] = name
            self.initializers.append(numpy_helper.from_array(array, name))
        return name

    def op(self, op_type: str, inputs: Sequence[str], out: str | None = None, **attrs: Any) -> str:
        (name,) = self.ops(op_type, inputs, 1, out=out, **attrs)
        return name

    def ops(
        self, op_type: str, inputs: Sequence[str], n_out: int, out: str | None = None, **attrs: Any
    ) -> list[str]:
        if out is not None:
            names = [out]
        else:
            names = [f"{op_type.lower()}{self._count}_{i}" for i in range(n_out)]
            self._count += 1
        self.nodes.append(helper.make_node(op_type, list(inputs), names, **attrs))
        return names

    def ints(self, *values: int) -> str:
        return self.const(list(values), np.int64)

    def dim(self, tensor: str, axis: int) -> str:
        """Scalar int64 size of ``tensor`` along ``axis`` (works for any image size)."""
        return self.op("Gather", [self.op("Shape", [tensor]), self.const(axis, np.int64)])

    def arange(self, size: str, shape: Sequence[int]) -> str:
        """0..size−1 as float32, reshaped to ``shape`` (one −1 in it takes the size)."""
        index = self.op("Range", [self.const(0, np.int64), size, self.const(1, np.int64)])
        return self.op(
            "Reshape", [self.op("Cast", [index], to=TensorProto.FLOAT), self.ints(*shape)]
        )

    # -- stages --

    def _grey(self, left: str, right: str) -> str:
        from common.zoo import CAMERA_ORDER

        # Cast before joining the views: the joined uint8 pair would be a cut that only
        # renames the inputs.
        rgb = self.op(
            "Concat",
            [self.op("Cast", [view], to=TensorProto.FLOAT) for view in (left, right)],
            axis=0,
        )
        weights = LUMA_RGB if CAMERA_ORDER == "rgb" else LUMA_RGB[::-1]
        luma = self.op("MatMul", [rgb, self.const(np.array(weights).reshape(3, 1))])
        nchw = self.op("Transpose", [luma], perm=[0, 3, 1, 2])
        shifted = self.op("Floor", [self.op("Mul", [nchw, self.const(1.0 / LUMA_SHIFT)])])
        return self.op("Cast", [shifted], out=Stage.GREY.value, to=TensorProto.UINT8)

    def _census(self, grey: str) -> str:
        r = self.p.census_radius
        size = 2 * r + 1
        weights = np.zeros((len(self.p.census), 1, size, size), np.float32)
        for i, (dy, dx) in enumerate(self.p.census):
            weights[i, 0, r + dy, r + dx] += 1.0
            weights[i, 0, r, r] -= 1.0
        level = self.op("Cast", [grey], to=TensorProto.FLOAT)
        # Edge padding: zeros beyond the border would read as dark neighbours, the same code in
        # every border pixel of both views, which matches at any disparity.
        padded = self.op("Pad", [level, self.ints(0, 0, r, r, 0, 0, r, r)], mode="edge")
        diff = self.op("Conv", [padded, self.const(weights)])
        return self.op("Less", [diff, self.const(0.0)], out=Stage.CENSUS.value)

    def _cost(self, census: str) -> str:
        # One plane per census bit: onnxruntime sums a few planes much faster than it reduces
        # over the channel axis, and slicing a plane costs no more than slicing all of them.
        # Bits first, views second: splitting the views first would make a cut that only
        # renames the census.
        left_bits, right_bits = [], []
        for pair in self.ops("Split", [census], len(self.p.census), axis=1):
            left_bit, right_bit = self.ops("Split", [pair], 2, axis=0)
            left_bits.append(left_bit)
            right_bits.append(right_bit)
        n_bits = len(self.p.census)
        axis3 = self.ints(3)
        worst = self.const(float(n_bits))  # pixels with no match at d: x < d
        parts = []
        for d in range(self.p.max_disparity):
            differ = []
            for a, b in zip(left_bits, right_bits, strict=True):
                if d:
                    a = self.op("Slice", [a, self.ints(d), self.ints(INT64_MAX), axis3])
                    b = self.op("Slice", [b, self.ints(0), self.ints(-d), axis3])
                differ.append(self.op("Cast", [self.op("Xor", [a, b])], to=TensorProto.FLOAT))
            cost = self.op("Sum", differ)
            if d:
                cost = self.op("Pad", [cost, self.ints(0, 0, 0, d, 0, 0, 0, 0), worst])
            parts.append(cost)
        return self.op("Concat", parts, out=Stage.COST.value, axis=1)

    def _aggregate(self, cost: str) -> str:
        # One depthwise k×k convolution of ones (sums, not means: integers stay exact). Two
        # separable passes would be faster, but the tensor between them would be a cut of the
        # cost volume's size with FLOPs of its own, which the partitioner could not prune.
        d, k = self.p.max_disparity, self.p.window_px
        pad = k // 2
        return self.op(
            "Conv",
            [cost, self.const(np.ones((d, 1, k, k)))],
            out=Stage.COST_AGG.value,
            group=d,
            pads=[pad, pad, pad, pad],
        )

    def _disparity(self, agg: str) -> str:
        # Plane by plane (running minima with Less/Where) rather than ArgMin/ReduceMin over the
        # channel axis: several times faster in onnxruntime, and exact.
        n = self.p.max_disparity
        planes = self.ops("Split", [agg], n, axis=1)
        best, best_cost = self._winner(planes)
        best_index = self.op("Cast", [best], to=TensorProto.INT64)
        valid = self.op(
            "And",
            [self._unique(planes, best, best_cost), self._left_right_agree(planes, best_index)],
        )
        if self.p.max_cost_share < 1:
            valid = self.op("And", [valid, self._close_enough(best_cost)])
        valid = self.op("And", [valid, self._full_census(best)])
        value = self.op("Add", [best, self._subpixel(agg, best_index, best_cost)])
        if self.p.min_support:
            # valid and value stay live beside the filter's input: three tensors cross until
            # the end of the stage, so the filter makes no cut of its own (module docstring).
            checked = self.op("Where", [valid, value, self.const(np.nan)])
            valid = self.op("And", [valid, self._supported(checked)])
        return self.op("Where", [valid, value, self.const(np.nan)], out=Stage.DISPARITY.value)

    def _supported(self, disparity: str) -> str:
        """Small-region (speckle) filter: at least ``min_support`` of the sampled neighbours
        have a disparity within ``support_tolerance_px`` (NaN and the padding beyond the border
        never do). Chance matches that pass the per-pixel checks (a window half on an untextured
        sky, half on a wall's top edge) come in small patches whose sub-pixel values disagree;
        a surface's pixels have neighbours at their depth."""
        r = self.p.support_radius_px
        axes = self.ints(2, 3)
        padded = self.op("Pad", [disparity, self.ints(0, 0, r, r, 0, 0, r, r), self.const(np.nan)])
        agree = []
        for dy, dx in self.p.support_offsets:
            # Rows r + dy .. H + r + dy of the padded map (the end as an offset from its end).
            starts = self.ints(r + dy, r + dx)
            ends = self.ints(*(o - r if o < r else INT64_MAX for o in (dy, dx)))
            neighbour = self.op("Slice", [padded, starts, ends, axes])
            gap = self.op("Abs", [self.op("Sub", [neighbour, disparity])])
            close = self.op("LessOrEqual", [gap, self.const(self.p.support_tolerance_px)])
            agree.append(self.op("Cast", [close], to=TensorProto.FLOAT))
        support = self.op("Sum", agree)
        return self.op("GreaterOrEqual", [support, self.const(float(self.p.min_support))])

    def _winner(self, planes: Sequence[str]) -> tuple[str, str]:
        """(index, cost) of each pixel's cheapest plane, as float; ties go to the first."""
        best_cost = self.op("Min", [planes[0], planes[1]])
        best = self.op(
            "Where", [self.op("Less", [planes[1], planes[0]]), self.const(1.0), self.const(0.0)]
        )
        for d, plane in enumerate(planes[2:], start=2):
            cheaper = self.op("Less", [plane, best_cost])
            best = self.op("Where", [cheaper, self.const(float(d)), best])
            best_cost = self.op("Min", [best_cost, plane])
        return best, best_cost

    def _unique(self, planes: Sequence[str], best: str, best_cost: str) -> str:
        """The best cost is below (1 − uniqueness) × the best one at any other disparity than
        the winner's neighbours (a smooth minimum always has close costs beside it)."""
        others = []
        for d, plane in enumerate(planes):
            gap = self.op("Abs", [self.op("Sub", [best, self.const(float(d))])])
            near = self.op("Less", [gap, self.const(1.5)])
            others.append(self.op("Where", [near, self.const(BIG_COST), plane]))
        runner_up = self.op("Min", others)
        scaled = self.op("Mul", [runner_up, self.const(1.0 - self.p.uniqueness)])
        return self.op("Less", [best_cost, scaled])

    def _left_right_agree(self, planes: Sequence[str], best: str) -> str:
        """The right view's own winner at the matched pixel x − d is d again (± tolerance).

        The right view's cost at (x_r, d) is the left's at (x_r + d, d): each plane shifted left
        by d, the columns it lacks filled with a cost no disparity wins with.
        """
        axis3 = self.ints(3)
        shifted = []
        for d, plane in enumerate(planes):
            if d:
                plane = self.op("Slice", [plane, self.ints(d), self.ints(INT64_MAX), axis3])
                plane = self.op(
                    "Pad", [plane, self.ints(0, 0, 0, 0, 0, 0, 0, d), self.const(BIG_COST)]
                )
            shifted.append(plane)
        right_best, _ = self._winner(shifted)
        right_index = self.op("Cast", [right_best], to=TensorProto.INT64)
        width = self.dim(best, 3)
        columns = self.op("Range", [self.const(0, np.int64), width, self.const(1, np.int64)])
        matched = self.op("Sub", [columns, best])
        inside = self.op("GreaterOrEqual", [matched, self.const(0, np.int64)])
        clamped = self.op("Max", [matched, self.const(0, np.int64)])
        back = self.op("GatherElements", [right_index, clamped], axis=3)
        drift = self.op("Abs", [self.op("Sub", [back, best])])
        agree = self.op("LessOrEqual", [drift, self.const(self.p.lr_tolerance_px, np.int64)])
        return self.op("And", [inside, agree])

    def _full_census(self, best: str) -> str:
        """Pixels at least the census radius from the border: nearer, part of each code
        compares the edge padding with itself, the same bits in both views, and chance matches
        in a textureless border (a ceiling, the sky) pass the checks."""
        r = self.p.census_radius
        inside = []
        for axis, shape in ((2, (-1, 1)), (3, (1, -1))):
            size = self.dim(best, axis)
            index = self.arange(size, shape)
            low = self.op("GreaterOrEqual", [index, self.const(float(r))])
            high = self.op(
                "Less",
                [index, self.op("Sub", [self.op("Cast", [size], to=TensorProto.FLOAT),
                                        self.const(float(r))])],
            )  # fmt: skip
            inside.append(self.op("And", [low, high]))
        return self.op("And", inside)

    def _close_enough(self, best_cost: str) -> str:
        """The winner's codes differ in less than ``max_cost_share`` of their bits: two random
        codes (a textureless region, where the census is sensor noise) differ in half.

        The bits compared per pixel: the window's pixels inside the image (fewer at the border,
        where the box filter's zero padding leaves them out) times the census points. Counted
        with index arithmetic, not a convolution of ones: that would add FLOPs between
        ``cost_agg`` and ``disparity`` and make the cost volume a cut of its own.
        """
        inside = self.op(
            "Mul",
            [self._window_rows(best_cost, 2, (-1, 1)), self._window_rows(best_cost, 3, (1, -1))],
        )
        share = self.p.max_cost_share * len(self.p.census)
        return self.op("Less", [best_cost, self.op("Mul", [inside, self.const(share)])])

    def _window_rows(self, tensor: str, axis: int, shape: tuple[int, int]) -> str:
        """How many of a window's rows (or columns) lie inside the image along ``axis``:
        1 + min(i, k//2) + min(n − 1 − i, k//2), as float, shaped to broadcast."""
        half = self.const(float(self.p.window_px // 2))
        size = self.dim(tensor, axis)
        index = self.arange(size, shape)
        last = self.op("Sub", [self.op("Cast", [size], to=TensorProto.FLOAT), self.const(1.0)])
        before = self.op("Min", [index, half])
        after = self.op("Min", [self.op("Sub", [last, index]), half])
        return self.op("Add", [self.op("Add", [before, after]), self.const(1.0)])

    def _subpixel(self, agg: str, best: str, best_cost: str) -> str:
        """Offset in (−½, ½) to the vertex of the parabola through the costs at d − 1, d, d + 1
        (0 at the ends of the range and where the costs are flat)."""
        d_max = self.p.max_disparity - 1
        below = self.op("Max", [self.op("Sub", [best, self.ints(1)]), self.ints(0)])
        above = self.op("Min", [self.op("Add", [best, self.ints(1)]), self.ints(d_max)])
        c_below = self.op("GatherElements", [agg, below], axis=1)
        c_above = self.op("GatherElements", [agg, above], axis=1)
        curve = self.op(
            "Sub",
            [self.op("Add", [c_below, c_above]), self.op("Mul", [best_cost, self.const(2.0)])],
        )
        interior = self.op(
            "And",
            [
                self.op(
                    "And",
                    [
                        self.op("Greater", [best, self.const(0, np.int64)]),
                        self.op("Less", [best, self.const(d_max, np.int64)]),
                    ],
                ),
                self.op("Greater", [curve, self.const(0.0)]),
            ],
        )
        step = self.op(
            "Div",
            [
                self.op("Sub", [c_below, c_above]),
                self.op("Mul", [self.op("Max", [curve, self.const(1.0)]), self.const(2.0)]),
            ],
        )
        return self.op("Where", [interior, step, self.const(0.0)])

    def _points(self, disparity: str) -> str:
        # The grid comes from the disparity's own shape first, so that until the MatMul every
        # crossing set holds more than the disparity alone (see the module docstring).
        shape = self.op("Shape", [disparity])
        d = self.op("Transpose", [disparity], perm=[0, 2, 3, 1])  # 1×H×W×1
        valid = self.op("Greater", [d, self.const(0.0)])  # NaN compares false
        scale = self.op(
            "Where",
            [valid, self.op("Div", [self.const(self.camera.baseline_m), d]), self.const(np.nan)],
        )
        height = self.op("Gather", [shape, self.const(2, np.int64)])
        width = self.op("Gather", [shape, self.const(3, np.int64)])
        u = self.arange(width, (1, 1, -1, 1))
        v = self.arange(height, (1, -1, 1, 1))
        homogeneous = self.op(
            "Concat",
            [self.op("Mul", [u, scale]), self.op("Mul", [v, scale]), scale],
            axis=3,
        )
        camera = self.op("MatMul", [homogeneous, self.const(self.camera.projection().T)])
        return self.op("Add", [camera, self.const(self.camera.offset())], out=Stage.POINTS.value)

    def _dcoll(self, points: str) -> str:
        bins, band = self.bins, self.band
        flat = self.ints(1, 1, -1)
        x, y, z = self.ops("Split", [points], 3, axis=3)
        # Op order keeps three or more tensors crossing until the bin selection (module doc).
        z = self.op("Reshape", [z, flat])
        obstacle = self.op(
            "And",
            [
                self.op("GreaterOrEqual", [z, self.const(band.min_height_m)]),
                self.op("LessOrEqual", [z, self.const(band.max_height_m)]),
            ],
        )
        x = self.op("Reshape", [x, flat])
        y = self.op("Reshape", [y, flat])
        r2 = self.op("Add", [self.op("Mul", [x, x]), self.op("Mul", [y, y])])
        ax = self.op("Abs", [x])
        # β = atan2(|x|, y) from Atan (ONNX has no atan2): π − atan(|x|/|y|) behind the axle.
        half = self.op("Atan", [self.op("Div", [ax, self.op("Abs", [y])])])
        ahead = self.op("GreaterOrEqual", [y, self.const(0.0)])
        beta = self.op("Where", [ahead, half, self.op("Sub", [self.const(math.pi), half])])
        arc = self.op("Div", [self.op("Mul", [r2, beta]), ax])
        straight = self.op(
            "Where",
            [self.op("Greater", [y, self.const(0.0)]), y, self.const(np.inf)],
        )
        arc = self.op("Where", [self.op("Greater", [ax, self.const(0.0)]), arc, straight])
        arc = self.op("Min", [arc, self.const(band.max_range_m)])
        curvature = self.op("Div", [self.op("Mul", [x, self.const(-2.0)]), r2])
        index = self.op(
            "Round",
            [
                self.op(
                    "Div",
                    [
                        self.op("Add", [curvature, self.const(bins.k_max_per_m)]),
                        self.const(bins.step_per_m),
                    ],
                )
            ],
        )
        in_bins = self.op(
            "And",
            [
                self.op("GreaterOrEqual", [index, self.const(0.0)]),
                self.op("LessOrEqual", [index, self.const(float(bins.count - 1))]),
            ],
        )
        keep = self.op("And", [obstacle, in_bins])
        slots = self.const(np.arange(bins.count, dtype=np.float32).reshape(1, -1, 1))
        hit = self.op("And", [self.op("Equal", [index, slots]), keep])  # 1×B×N
        arcs = self.op("Where", [hit, arc, self.const(band.max_range_m)])
        return self.op("ReduceMin", [arcs], out=Stage.DCOLL.value, axes=[2], keepdims=0)

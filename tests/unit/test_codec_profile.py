"""Which measured (cut, codec) entries become actions under a fidelity bound."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from common.codec_profile import (
    OUTPUT_KIND_PREFIX,
    Fidelity,
    OutputKind,
    compare_outputs,
    declared_output_kinds,
    select_codecs,
)
from common.errors import UserError


def entry(
    name: str, size: float, *, top1: float | None = None, err: float | None = None
) -> dict[str, Any]:
    lossy = name.startswith(("jpeg", "int8", "fp16"))
    return {"name": name, "bytes": size, "top1_agreement": top1, "rel_err": err, "lossy": lossy}


ENTRIES = [
    entry("raw", 230_400),
    entry("raw+zstd", 220_000),  # saves under 10%: not worth its CPU
    entry("png", 90_000),
    entry("jpeg95", 16_000, top1=1.0),
    entry("jpeg80", 7_000, top1=1.0),
    entry("jpeg50", 4_500, top1=0.9),  # changes the answer on one frame in ten
]


def names(chosen: list[dict[str, Any]]) -> list[str]:
    return [e["name"] for e in chosen]


def test_raw_lossless_savings_and_the_lowest_jpeg_that_keeps_the_answers() -> None:
    assert names(select_codecs(ENTRIES, Fidelity())) == ["raw", "jpeg80", "png"]


def test_a_codec_a_baseline_names_is_kept_whatever_the_bound() -> None:
    chosen = names(select_codecs(ENTRIES, Fidelity(), required=["jpeg50"]))
    assert chosen[:2] == ["raw", "jpeg50"]


def test_a_bound_that_cannot_be_checked_admits_no_lossy_codec() -> None:
    assert not Fidelity().admits(None, None), "nothing compared"
    assert not Fidelity(max_output_rel_err=None).admits(None, 0.001)
    assert not Fidelity(max_bad_pixel_share=None).admits(None, 0.001, 0.0)
    assert Fidelity(max_output_rel_err=0.01).admits(None, 0.001)
    assert not Fidelity(max_output_rel_err=0.01).admits(1.0, 0.02)


def test_every_output_is_judged_by_its_kind() -> None:
    scores = np.array([[0.1, 0.7, 0.2]])
    d_coll = np.array([[2.0, 1.5, 3.0, 0.8]])
    disparity = np.full((1, 1, 4, 8), 10.0)
    outputs = {"scores": scores, "d_coll": d_coll, "disparity": disparity}
    # d_coll is 1xB like scores: only the model's declaration makes it a distance.
    declared = {"d_coll": OutputKind.DISTANCE}
    assert compare_outputs(outputs, outputs, declared) == (True, 0.0, 0.0)
    moved = dict(outputs, d_coll=d_coll * 1.1)
    agree, err, bad = compare_outputs(moved, outputs, declared)
    assert agree is True and err == pytest.approx(0.1) and bad == 0.0
    assert compare_outputs(moved, outputs)[1] == 0.0, "undeclared: a classifier, argmax kept"
    # One bin of four far off: the L2 error of a value is diluted, a distance's is not.
    one_bin = d_coll.copy()
    one_bin[0, 3] = 8.0  # an obstacle at 0.8 m no longer seen
    as_value = compare_outputs(dict(outputs, d_coll=one_bin), outputs, {"d_coll": OutputKind.VALUE})
    as_distance = compare_outputs(dict(outputs, d_coll=one_bin), outputs, declared)
    assert as_value[1] == pytest.approx(7.2 / np.linalg.norm(d_coll))
    assert as_distance[1] == pytest.approx(9.0)
    shifted = disparity.copy()
    shifted[0, 0, 0, :4] += 1.5  # 4 of 32 pixels off by more than 1 px
    shifted[0, 0, 1, 0] = np.nan  # a match lost: off too
    shifted[0, 0, 2, 0] += 0.9  # within 1 px
    _, _, bad = compare_outputs(dict(outputs, disparity=shifted), outputs, declared)
    assert bad == pytest.approx(5 / 32)
    assert not Fidelity().admits(True, 0.01, bad), "5/32 of the pixels over the 5% default"
    assert Fidelity(max_bad_pixel_share=0.2).admits(True, 0.01, bad)


def test_a_model_declares_its_output_kinds_in_its_metadata(tmp_path: Path) -> None:
    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["d_coll"])],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])],
        [helper.make_tensor_value_info("d_coll", TensorProto.FLOAT, [1, 4])],
    )
    model = helper.make_model(graph)
    helper.set_model_props(model, {f"{OUTPUT_KIND_PREFIX}d_coll": "value"})
    path = tmp_path / "m.onnx"
    onnx.save(model, str(path))
    assert declared_output_kinds(path) == {"d_coll": OutputKind.VALUE}
    helper.set_model_props(model, {f"{OUTPUT_KIND_PREFIX}d_coll": "metres"})
    onnx.save(model, str(path))
    with pytest.raises(UserError, match="unknown output kind 'metres'"):
        declared_output_kinds(path)


def test_the_stereo_model_declares_d_coll_a_value() -> None:
    from nav.zoo_entry import build_stereo

    props = {p.key: p.value for p in build_stereo((3, 24, 32)).metadata_props}
    assert props[f"{OUTPUT_KIND_PREFIX}d_coll"] == OutputKind.DISTANCE.value

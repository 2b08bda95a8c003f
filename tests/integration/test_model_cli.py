"""`elasticfog model ...` through typer's runner: the JSON contracts, tables, and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import onnx
import pytest
from typer.testing import CliRunner, Result

from common.cli import app
from common.models import file_digest
from tests.helpers.onnx_graphs import diamond, late_input, make_model, node, save, vi
from tests.unit.test_prep import conv_net

runner = CliRunner()


def invoke(*args: str) -> Result:
    return runner.invoke(app, ["model", *args])


def assert_one_line_error(result: Result, *fragments: str) -> None:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ")
    for fragment in fragments:
        assert fragment in lines[0]
    assert "Traceback" not in result.output
    assert result.stdout == ""


def test_zoo_list_json() -> None:
    result = invoke("zoo", "list", "--json")
    assert result.exit_code == 0, result.output
    rows = json.loads(result.stdout)
    names = [r["name"] for r in rows]
    assert names[:5] == ["vgg", "resnet", "mobilenet", "resnet18", "mobilenet_v2"]
    assert "stereo" in names[5:]  # graph models from entry points follow the zoo's own networks
    assert sum(r["default"] for r in rows) == 1


def test_zoo_list_table() -> None:
    result = invoke("zoo", "list")
    assert result.exit_code == 0, result.output
    assert "zoo:resnet" in result.stdout and "(default)" in result.stdout
    # Guards against a user reading the ROS 2 walkthrough's top-5 of a zoo model as classes.
    assert "seeded, not trained" in " ".join(result.stdout.split())


def test_zoo_export(tmp_path: Path) -> None:
    out = tmp_path / "models" / "vgg.onnx"
    result = invoke("zoo", "export", "vgg", "--out", str(out), "--input-shape", "3x64x64", "--json")
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert info == {
        "name": "vgg",
        "path": str(out),
        "digest": file_digest(out),
        "input_shape": [1, 64, 64, 3],
        "input_dtype": "uint8",
        "camera_order": "rgb",
    }


def test_split_json_is_the_manifest(tmp_path: Path) -> None:
    src = save(diamond(), tmp_path / "m.onnx")
    out = tmp_path / "split"
    result = invoke("split", str(src), "--out", str(out), "--json")
    assert result.exit_code == 0, result.output
    printed = json.loads(result.stdout)
    assert printed == json.loads((out / "manifest.json").read_text())
    assert [c["tensors"] for c in printed["cuts"]] == [["x"], ["a"], ["a", "b"], ["b", "c"]]
    assert printed["cuts"][1]["prefix"] == "cut001.prefix.onnx"


def test_split_options(tmp_path: Path) -> None:
    src = save(late_input(), tmp_path / "m.onnx")
    out = tmp_path / "split"
    result = invoke("split", str(src), "--out", str(out), "--cuts", "b", "--json")
    assert result.exit_code == 0, result.output
    assert [c["tensors"] for c in json.loads(result.stdout)["cuts"]] == [["x", "z"], ["z", "b"]]
    result = invoke("split", str(src), "--out", str(out), "--max-cut-tensors", "1", "--json")
    assert [c["tensors"] for c in json.loads(result.stdout)["cuts"]] == [["x", "z"]]


def test_split_table(tmp_path: Path) -> None:
    src = save(diamond(), tmp_path / "m.onnx")
    result = invoke("split", str(src), "--out", str(tmp_path / "split"))
    assert result.exit_code == 0, result.output
    assert "max abs err" in result.stdout
    assert "a + b" in result.stdout


def test_check_zoo_model_table() -> None:
    result = invoke("check", "zoo:resnet", "--input-shape", "3x64x64")
    assert result.exit_code == 0, result.output
    assert "verified" in result.stdout
    assert "left out" in result.stdout  # dominated cuts are summarised, not listed


def test_profile_json(tmp_path: Path) -> None:
    src = save(diamond(), tmp_path / "m.onnx")
    result = invoke("profile", str(src), "--runs", "2", "--threads", "1", "--json")
    assert result.exit_code == 0, result.output
    prof = json.loads(result.stdout)
    assert set(prof) == {"digest", "full_ms", "cuts"}
    assert prof["digest"] == file_digest(src)
    assert len(prof["cuts"]) == 4


def test_profile_table(tmp_path: Path) -> None:
    src = save(diamond(), tmp_path / "m.onnx")
    result = invoke("profile", str(src), "--runs", "2")
    assert result.exit_code == 0, result.output
    assert "full model" in result.stdout and "robot ms" in result.stdout


def test_profile_codecs_measures_every_cut_on_photographs() -> None:
    shape = ["--input-shape", "3x48x64", "--runs", "2", "--threads", "1"]
    bound = ["--fidelity", "lossy_features=true,codecs=jpeg80,codecs=int8+zstd"]
    result = invoke("profile", "zoo:resnet", *shape, "--codecs", *bound, "--json")
    assert result.exit_code == 0, result.output
    cuts = json.loads(result.stdout)["cuts"]
    first = {e["name"]: e for e in cuts[0]["codecs"]}
    assert set(first) == {"raw", "jpeg80"}  # the image: the codec list leaves png and zstd out
    assert first["jpeg80"]["bytes"] < first["raw"]["bytes"] == 48 * 64 * 3
    assert first["jpeg80"]["bytes_p10"] <= first["jpeg80"]["bytes"] <= first["jpeg80"]["bytes_p90"]
    middle = {e["name"]: e for e in cuts[1]["codecs"]}
    assert set(middle) == {"raw", "int8+zstd"}  # a feature map: no JPEG
    assert middle["int8+zstd"]["lossy"] and middle["int8+zstd"]["top1_agreement"] is not None
    assert middle["raw"]["action"]  # raw is always an action
    table = invoke("profile", "zoo:resnet", *shape, "--codecs")
    assert table.exit_code == 0, table.output
    assert "jpeg80" in table.stdout and "top-1" in table.stdout


def test_prep_json_then_split_sends_the_uint8_image(tmp_path: Path) -> None:
    src = save(conv_net(["N", 3, "H", "W"]), tmp_path / "m.onnx")
    out = tmp_path / "m.prep.onnx"
    imagenet = ["--mean", "0.485,0.456,0.406", "--std", "0.229,0.224,0.225"]
    result = invoke("prep", str(src), "--out", str(out), "--bgr", *imagenet, "--input-shape",
                    "48x64", "--json")  # fmt: skip
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert info["input"] == {"name": "x", "shape": ["N", 48, 64, 3], "dtype": "uint8"}
    assert (info["camera_order"], info["model_order"], info["layout"]) == ("bgr", "rgb", "nchw")
    assert info["outputs"] == ["y"] and info["max_abs_err"] <= info["tolerance"]
    result = invoke("split", str(out), "--out", str(tmp_path / "split"), "--json")
    assert result.exit_code == 0, result.output
    manifest = json.loads(result.stdout)
    assert manifest["specs"]["x"] == {"dtype": "uint8", "shape": [1, 48, 64, 3]}
    assert manifest["cuts"][0]["tensors"] == ["x"] and manifest["cuts"][0]["bytes"] == 48 * 64 * 3
    assert all(c["verified"] for c in manifest["cuts"])
    # Regression: the front end's float tensors (0 FLOPs, 4× the bytes) lose to cut 0, and the
    # BGR reorder is not a second uint8 cut: every later cut computes something on the robot.
    assert all(c["prefix_flops"] > 0 for c in manifest["cuts"][1:])


def test_prep_table(tmp_path: Path) -> None:
    src = save(conv_net([1, 32, 40, 3], nhwc=True), tmp_path / "m.onnx")
    result = invoke("prep", str(src), "--out", str(tmp_path / "p.onnx"), "--layout", "nhwc")
    assert result.exit_code == 0, result.output
    assert "uint8 1×32×40×3" in result.stdout and "RGB order" in result.stdout
    assert "checked on a 32×40 photograph" in result.stdout


# ---------------------------------------------------------------------------------------------
# Bad input: one line on stderr, exit code 2


@pytest.mark.parametrize(
    ("model", "args", "fragments"),
    [
        (conv_net([1, 1, 8, 8]), [], ["has 1 channel", "3-channel"]),
        (
            make_model([node("Relu", ["x"], ["y"])], [vi("x", [1, 4])], [vi("y", [1, 4])]),
            [],
            ["not an image model"],
        ),
        (
            make_model(
                [node("Add", ["a", "b"], ["y"])],
                [vi("a", [1, 4]), vi("b", [1, 4])],
                [vi("y", [1, 4])],
            ),
            [],
            ["has 2 inputs (a, b)"],
        ),
        (conv_net([1, 3, 8, 8]), ["--mean", "0.5,0.5"], ["--mean needs 3 values"]),
        (conv_net([1, 3, 8, 8]), ["--std", "1,x,1"], ["--std"]),
        (conv_net([1, 3, 8, 8]), ["--input-shape", "16x16"], ["its height is fixed at 8"]),
        (conv_net([1, 3, 8, 8]), ["--input-shape", "3x16x16"], ["HxW"]),
        (conv_net([1, 3, 8, 8]), ["--layout", "chw"], ["--layout must be nchw or nhwc"]),
    ],
)
def test_prep_bad_input(
    tmp_path: Path, model: onnx.ModelProto, args: list[str], fragments: list[str]
) -> None:
    src = save(model, tmp_path / "m.onnx")
    result = invoke("prep", str(src), "--out", str(tmp_path / "p.onnx"), *args)
    assert_one_line_error(result, *fragments)
    assert not (tmp_path / "p.onnx").exists()


def test_not_an_onnx_file(tmp_path: Path) -> None:
    src = tmp_path / "notes.onnx"
    src.write_text("hello\n")
    assert_one_line_error(invoke("split", str(src), "--out", str(tmp_path / "o")), "not an ONNX")


def test_truncated_file(tmp_path: Path) -> None:
    data = diamond().SerializeToString()
    src = tmp_path / "half.onnx"
    src.write_bytes(data[: len(data) // 2])
    assert_one_line_error(invoke("check", str(src)), "half.onnx", "ONNX model")


def test_unknown_tensor_names_are_listed(tmp_path: Path) -> None:
    src = save(diamond(), tmp_path / "m.onnx")
    result = invoke("split", str(src), "--out", str(tmp_path / "o"), "--cuts", "a,foo,bar+b")
    assert_one_line_error(result, "unknown tensor name(s)", "foo, bar")


def test_cut_that_does_not_separate(tmp_path: Path) -> None:
    src = save(diamond(), tmp_path / "m.onnx")
    result = invoke("split", str(src), "--out", str(tmp_path / "o"), "--cuts", "b")
    assert_one_line_error(result, "does not separate the inputs from the outputs")


def test_unsupported_opset(tmp_path: Path) -> None:
    model = make_model([node("Relu", ["x"], ["y"])], [vi("x", [1, 4])], [vi("y", [1, 4])], opset=30)
    src = save(model, tmp_path / "m.onnx")
    assert_one_line_error(invoke("profile", str(src)), "opset 30")


@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        (["check", "missing.onnx"], ["model file not found"]),
        (["check", "zoo:nope"], ["unknown zoo model 'nope'"]),
        (["check", "zoo:vgg", "--input-shape", "3xfoo"], ["bad shape"]),
        (["check", "zoo:vgg", "--max-cut-tensors", "0"], ["--max-cut-tensors"]),
        (["profile", "zoo:vgg", "--runs", "0"], ["--runs"]),
        (
            ["profile", "zoo:vgg", "--fidelity", "lossy_features=true"],
            ["--fidelity needs --codecs"],
        ),
        (["profile", "zoo:vgg", "--codecs", "--fidelity", "min_top1=0.9"], ["min_top1"]),
        (["profile", "zoo:vgg", "--codecs", "--fidelity", "codecs=jpeg"], ["unknown tensor codec"]),
        (["profile", "zoo:vgg", "--codecs", "--fidelity", "min_top1_agreement=2"], ["less than"]),
        (["zoo", "export", "nope", "--out", "x.onnx"], ["unknown zoo model"]),
    ],
)
def test_bad_arguments(tmp_path: Path, args: list[str], fragments: list[str]) -> None:
    assert_one_line_error(invoke(*args), *fragments)

"""The bench's options are checked before anything starts: a path option is the working
directory's (the fleet files are written in a temporary folder, where `rel.onnx` is not), a
missing file is one line naming the option, and a model file whose input shape is fixed has its
own shape (the default 3x240x320 made every bench fail on a `model prep` output). Guards
against the model path being taken relative to the fleet file again."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import onnx
import pytest
from onnx import TensorProto, helper

from common.errors import UserError
from experiments.defaults import DEFAULT_INPUT_SHAPE
from experiments.options import BenchOptions, default_input_shape

ROOT = Path(__file__).resolve().parents[2]


def write_identity(path: Path, dims: list[int | str]) -> Path:
    """A one-node ONNX model whose input has `dims` (a string: a dynamic dimension)."""
    x = helper.make_tensor_value_info("in0", TensorProto.UINT8, dims)
    y = helper.make_tensor_value_info("out0", TensorProto.UINT8, dims)
    graph = helper.make_graph([helper.make_node("Identity", ["in0"], ["out0"])], "g", [x], [y])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9)
    onnx.save(model, str(path))
    return path


def test_a_relative_model_and_workdir_are_the_working_directorys(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    write_identity(tmp_path / "rel.onnx", [1, 224, 224, 3])
    monkeypatch.chdir(tmp_path)
    options = BenchOptions(model="rel.onnx", workdir=Path("runs"), plots_dir=Path("plots"))
    options.check()
    assert options.model == str(tmp_path / "rel.onnx")
    assert options.workdir == tmp_path / "runs"
    assert options.plots_dir == tmp_path / "plots"


def test_a_fixed_input_is_the_files_shape_and_dynamic_dims_take_the_default(
    tmp_path: Path,
) -> None:
    fixed = write_identity(tmp_path / "fixed.onnx", [1, 224, 224, 3])
    dynamic = write_identity(tmp_path / "dynamic.onnx", ["N", 3, "H", "W"])
    assert default_input_shape(str(fixed)) == (1, 224, 224, 3)
    assert default_input_shape(str(dynamic)) == DEFAULT_INPUT_SHAPE
    assert default_input_shape("zoo:mobilenet_v2") == DEFAULT_INPUT_SHAPE
    given = BenchOptions(model=str(fixed), input_shape=(3, 224, 224))
    given.check()
    assert given.input_shape == (3, 224, 224)  # a shape given is kept


def test_a_missing_model_or_a_file_as_workdir_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError, match=r"--model mine\.onnx: no such file"):
        BenchOptions(model="mine.onnx").check()
    (tmp_path / "f").write_text("x")
    with pytest.raises(UserError, match="--workdir f: is a file"):
        BenchOptions(model="zoo:vgg", workdir=Path("f")).check()


@pytest.mark.parametrize(
    "command",
    [
        ["table1"],
        ["glitch", "--from-mbit", "5", "--to-mbit", "1"],
        ["table2"],
        ["table3"],
        ["anycast"],
        ["scale"],
    ],
)
def test_each_bench_command_refuses_a_missing_model_before_it_starts(
    command: list[str], tmp_path: Path
) -> None:
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            "from common.cli import main; main()",
            "bench",
            *command,
            "--model",
            "mine.onnx",
            "--quick",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"},
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert "--model mine.onnx: no such file" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_the_demo_refuses_a_missing_model_before_it_starts(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-c", "from common.cli import main; main()", "demo", "--model", "x.onnx"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"},
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip() == (
        f"error: --model x.onnx: no such file ({tmp_path / 'x.onnx'}); expected an ONNX file "
        "or zoo:NAME"
    )

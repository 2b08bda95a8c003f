"""`elasticfog model ...` names a bad partitioner option by its flag, though the partitioner
names it by its parameter (regression guard: the library must not know the CLI's flags, and the
CLI's message must not lose them)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers.onnx_graphs import chain, dynamic, save
from tests.integration.test_model_cli import assert_one_line_error, invoke


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--cuts", "a,,b"], "bad --cuts 'a,,b': expected 'auto' or tensor names like a,b+c"),
        (["--cuts", "a,nope"], "unknown tensor name(s) in --cuts: nope"),
        (["--max-cut-tensors", "0"], "--max-cut-tensors must be a positive integer, got 0"),
        (
            ["--input-shape", "q=1x4"],
            "--input-shape names unknown input(s) q; the model's inputs are x",
        ),
        (["--input-shape", "2x4"], "--input-shape 2x4 does not match input 'x': axis 0 is fixed"),
    ],
)
def test_split_names_the_flag(tmp_path: Path, args: list[str], message: str) -> None:
    src = save(chain(), tmp_path / "m.onnx")
    result = invoke("split", str(src), "--out", str(tmp_path / "split"), *args)
    assert_one_line_error(result, message)


def test_dynamic_dimension_asks_for_the_flag(tmp_path: Path) -> None:
    src = save(dynamic([1, "L"]), tmp_path / "m.onnx")
    result = invoke("check", str(src))
    assert_one_line_error(result, "axis 1; give its shape with --input-shape")


def test_out_that_is_a_file_names_the_flag(tmp_path: Path) -> None:
    src = save(chain(), tmp_path / "m.onnx")
    (tmp_path / "file").write_text("x")
    result = invoke("split", str(src), "--out", str(tmp_path / "file"))
    assert_one_line_error(result, f"--out {tmp_path / 'file'} exists and is not a directory")

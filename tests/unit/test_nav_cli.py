"""`elasticfog nav disparity`: the contract (float32 H×W .npy in pixels of the left image, NaN
where invalid) on a real pair written as image files, and one-line errors for bad input;
`nav assist`'s half width checked before anything starts."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner, Result

from common.cli import app
from nav.disparity import DisparityRunner
from nav.stereo_eval import stereo_motorcycle
from nav.stereo_params import StereoParams

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    """A crop of Motorcycle as PNG files (BGR on disk, as OpenCV writes them), and its RGB."""
    left, right, _ = stereo_motorcycle()
    left, right = left[100:220, 200:420], right[100:220, 200:420]
    folder = tmp_path_factory.mktemp("pair")
    paths = folder / "left.png", folder / "right.png"
    for path, rgb in zip(paths, (left, right), strict=True):
        assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return paths[0], paths[1], left, right


def invoke(*args: str) -> Result:
    return runner.invoke(app, ["nav", "disparity", *args])


def assert_one_line_error(result: Result, *fragments: str) -> None:
    assert result.exit_code == 2, result.output
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0]
    assert "Traceback" not in result.output


def test_writes_the_disparity_of_the_pair(
    pair: tuple[Path, Path, np.ndarray, np.ndarray], tmp_path: Path
) -> None:
    left, right, left_rgb, right_rgb = pair
    out = tmp_path / "d.npy"
    result = invoke(str(left), str(right), "--max-disparity", "64", "--out", str(out), "--json")
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert (info["width"], info["height"], info["max_disparity"]) == (220, 120, 64)
    disparity = np.load(out)
    assert disparity.dtype == np.float32 and disparity.shape == (120, 220)
    valid = np.isfinite(disparity)
    assert info["valid_share"] == pytest.approx(valid.mean(), abs=1e-4)
    assert 0.5 < valid.mean() < 1.0  # NaN where invalid, most pixels matched
    assert np.nanmin(disparity) >= 0 and np.nanmax(disparity) <= 63.5
    # the same numbers as the library on the same pixels (PNG is lossless)
    want = DisparityRunner(StereoParams(64))(left_rgb, right_rgb).disparity
    np.testing.assert_array_equal(disparity, want)


def test_console_script(pair: tuple[Path, Path, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    """The installed `elasticfog` knows `nav` (entry point) and prints one summary line."""
    left, right, _, _ = pair
    out = tmp_path / "d.npy"
    script = Path(sys.executable).with_name("elasticfog")
    argv = (
        [str(script)]
        if script.is_file()
        else [sys.executable, "-c", "from common.cli import main; main()"]
    )
    done = subprocess.run(
        [*argv, "nav", "disparity", str(left), str(right), "--max-disparity", "32",
         "--out", str(out)],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"wrote {out}: float32 220x120 disparity (0..31 px)")
    assert np.load(out).shape == (120, 220)


def test_missing_file(pair: tuple[Path, Path, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    left, _, _, _ = pair
    missing = tmp_path / "nope.png"
    result = invoke(str(left), str(missing), "--out", str(tmp_path / "d.npy"))
    assert_one_line_error(result, "right image not found", "nope.png")


def test_not_an_image(pair: tuple[Path, Path, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    _, right, _, _ = pair
    text = tmp_path / "notes.png"
    text.write_text("not a picture")
    result = invoke(str(text), str(right), "--out", str(tmp_path / "d.npy"))
    assert_one_line_error(result, "left image", "not an image OpenCV can read")


def test_size_mismatch(pair: tuple[Path, Path, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    left, _, _, right_rgb = pair
    smaller = tmp_path / "small.png"
    cv2.imwrite(str(smaller), right_rgb[:, :200])
    result = invoke(str(left), str(smaller), "--out", str(tmp_path / "d.npy"))
    assert_one_line_error(result, "220x120", "200x120", "one size")


@pytest.mark.parametrize(
    ("value", "fragment"),
    [("0", "2..512"), ("1", "2..512"), ("600", "2..512"), ("300", "more than the image width")],
)
def test_bad_max_disparity(
    pair: tuple[Path, Path, np.ndarray, np.ndarray], tmp_path: Path, value: str, fragment: str
) -> None:
    left, right, _, _ = pair
    out = tmp_path / "d.npy"
    result = invoke(str(left), str(right), "--max-disparity", value, "--out", str(out))
    assert_one_line_error(result, fragment)
    assert not out.exists()


def test_bad_output_path(pair: tuple[Path, Path, np.ndarray, np.ndarray], tmp_path: Path) -> None:
    left, right, _, _ = pair
    result = invoke(str(left), str(right), "--out", str(tmp_path / "d.txt"))
    assert_one_line_error(result, ".npy")
    result = invoke(str(left), str(right), "--out", str(tmp_path / "no" / "d.npy"))
    assert_one_line_error(result, "does not exist")


def test_assist_half_width_below_zero_is_one_line(tmp_path: Path) -> None:
    # Checked before the fleet file is read or a session opened.
    result = runner.invoke(
        app,
        ["nav", "assist", "--config", str(tmp_path / "fleet.yaml"), "--robot", "r",
         "--half-width", "-0.1"],
    )  # fmt: skip
    assert result.exit_code == 2
    assert "half_width_m must be ≥ 0, got -0.1" in result.output

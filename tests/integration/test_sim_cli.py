"""`elasticfog sim` through the real CLI app: the JSON contract, --compare, plots, bad input."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from common.cli import app

ROOT = Path(__file__).resolve().parents[2]
VGG = ROOT / "tests" / "data" / "profiles" / "vgg-like-3x240x320.json"
GLITCH = ROOT / "deploy" / "traces" / "glitch-10-3.yaml"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

runner = CliRunner()


def sim(*args: str) -> tuple[int, str, str]:
    result = runner.invoke(app, ["sim", *args])
    return result.exit_code, result.stdout, result.stderr


def test_json_output_follows_the_contract() -> None:
    code, out, _ = sim(
        "--profile", str(VGG), "--policy", "elastic", "--trace", str(GLITCH), "--json"
    )
    assert code == 0
    doc = json.loads(out)
    assert doc["policy"] == "elastic"
    assert doc["frames"] == 2000
    assert [s["index"] for s in doc["segments"]] == [0, 1]
    assert doc["ratio_to_oracle"] == pytest.approx(
        doc["mean_latency_s"] / doc["oracle_mean_latency_s"], rel=1e-4
    )
    assert doc["ratio_to_oracle"] < 1.05
    assert doc["segments"][1]["settle_frames"] <= 30
    assert sum(doc["actions"].values()) == 2000
    assert doc["regret_curve"][-1][0] == 2000
    assert doc["decision_us_median"] > 0


def test_same_seed_same_answer_and_seed_matters() -> None:
    args = ["--profile", str(VGG), "--policy", "ans", "--trace", str(GLITCH), "--json"]
    first = json.loads(sim(*args, "--seed", "4")[1])
    again = json.loads(sim(*args, "--seed", "4")[1])
    other = json.loads(sim(*args, "--seed", "5")[1])
    for doc in (first, again, other):
        doc.pop("decision_us_median")
    assert first == again
    assert first != other


def test_human_output_and_single_plot(tmp_path: Path) -> None:
    plot = tmp_path / "run.png"
    code, out, _ = sim(
        "--profile", str(VGG), "--policy", "cloud", "--trace", str(GLITCH), "--plot", str(plot)
    )
    assert code == 0
    assert "cloud on glitch-10-3.yaml: 2000 frames" in out
    assert "segment 1 (3 Mbit/s)" in out
    assert "never settled" in out  # full offload at 3 Mbit/s stays far from the oracle
    assert plot.read_bytes().startswith(PNG_MAGIC)


def test_compare_prints_a_table_and_one_plot(tmp_path: Path) -> None:
    plot = tmp_path / "compare.png"
    code, out, _ = sim(
        "--profile",
        str(VGG),
        "--trace",
        str(GLITCH),
        "--compare",
        "elastic,ans,neurosurgeon,robot,cloud",
        "--plot",
        str(plot),
    )
    assert code == 0
    rows = [line for line in out.splitlines() if line.startswith("| ")]
    assert rows[0].startswith("| policy | mean latency (s)")
    assert [r.split("|")[1].strip() for r in rows[1:]] == [
        "elastic",
        "ans",
        "neurosurgeon",
        "robot",
        "cloud",
    ]
    assert plot.read_bytes().startswith(PNG_MAGIC)
    assert list(tmp_path.iterdir()) == [plot]


def test_compare_json_has_one_summary_per_policy(tmp_path: Path) -> None:
    code, out, _ = sim(
        "--profile",
        str(VGG),
        "--trace",
        str(GLITCH),
        "--compare",
        "robot,oracle",
        "--json",
        "--plot",
        str(tmp_path / "c.png"),
    )
    assert code == 0
    results = json.loads(out)["results"]
    assert [r["policy"] for r in results] == ["robot", "oracle"]
    assert results[1]["cumulative_regret"] == 0


def write(tmp_path: Path, name: str, text: str) -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


BAD_TRACE = (
    "frames_per_second: 10\nsegments:\n  - {frames: 10, uplink_mbit: -2, downlink_mbit: 5,"
    " rtt_ms: 1, robot_cpu: 1, cloud_speedup: 1}\n"
)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--policy", "elastic", "--trace", "@bad_trace"], "segments[0].uplink_mbit"),
        (["--policy", "elastic", "--trace", "@zero_frames"], "segments[0].frames"),
        (["--policy", "elastic", "--trace", "@missing"], "no such file"),
        (["--policy", "elastic", "--trace", "@glitch", "--profile", "@bad_profile"], "bytes"),
        (["--policy", "elastic", "--trace", "@glitch", "--profile", "@no_full"], "full_ms"),
        (["--policy", "teleport", "--trace", "@glitch"], "unknown policy"),
        (["--trace", "@glitch"], "exactly one of --policy"),
        (["--policy", "robot", "--compare", "robot", "--trace", "@glitch"], "exactly one"),
        (["--compare", "robot,robot", "--trace", "@glitch"], "more than once"),
        (["--policy", "static:99", "--trace", "@glitch"], "cut 99"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, args: list[str], message: str) -> None:
    files = {
        "@bad_trace": write(tmp_path, "bad.yaml", BAD_TRACE),
        "@zero_frames": write(tmp_path, "zero.yaml", BAD_TRACE.replace("frames: 10", "frames: 0")),
        "@missing": str(tmp_path / "missing.yaml"),
        "@glitch": str(GLITCH),
        "@bad_profile": write(
            tmp_path,
            "p.json",
            json.dumps(
                {"full_ms": 5, "cuts": [{"index": 0, "bytes": 0, "prefix_ms": 0, "suffix_ms": 5}]}
            ),
        ),
        "@no_full": write(tmp_path, "q.json", json.dumps({"cuts": []})),
    }
    argv = [files.get(a, a) for a in args]
    if "--profile" not in argv:
        argv += ["--profile", str(VGG)]
    code, out, err = sim(*argv, "--plot", str(tmp_path / "x.png"))
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("error:")
    assert message in lines[0]


def test_param_overrides_reach_the_policy() -> None:
    cpu_drop = ROOT / "deploy" / "traces" / "cpu-drop.yaml"
    base = ["--profile", str(VGG), "--policy", "elastic", "--trace", str(cpu_drop), "--json"]
    default = json.loads(sim(*base)[1])
    assert default["actions"]["P"] > default["frames"] // 2
    # Every 2nd frame forced onto the cloud: at most half the frames can run on the robot.
    code, out, _ = sim(
        *base, "--param", "forced_schedule=every", "--param", "forced_every_frames=2"
    )
    assert code == 0
    forced = json.loads(out)
    assert forced["actions"]["P"] <= forced["frames"] // 2
    # A repeated key: the last one wins, so this is the default run again.
    code, out, _ = sim(*base, "--param", "beta=0.1", "--param", "beta=1.0")
    again = json.loads(out)
    for doc in (default, again):
        doc.pop("decision_us_median")
    assert again == default


def test_param_with_compare_goes_to_the_policies_that_take_it(tmp_path: Path) -> None:
    args = [
        "--profile",
        str(VGG),
        "--trace",
        str(GLITCH),
        "--json",
        "--plot",
        str(tmp_path / "c.png"),
    ]
    plain = json.loads(sim(*args, "--compare", "elastic,robot")[1])["results"]
    code, out, err = sim(*args, "--compare", "elastic,robot", "--param", "change_detection=false")
    assert code == 0, err
    tuned = json.loads(out)["results"]
    # Without change detection elastic sits on the stale cut after the glitch; robot is untouched.
    assert tuned[0]["segments"][1]["settle_frames"] != plain[0]["segments"][1]["settle_frames"]
    assert tuned[1]["mean_latency_s"] == plain[1]["mean_latency_s"]


@pytest.mark.parametrize(
    ("policy", "params", "message"),
    [
        (
            "elastic",
            ["betta=0.3"],
            "--param betta: policy elastic has no parameter 'betta' (did you mean beta?)",
        ),
        (
            "elastic",
            ["beta=-1"],
            "--param beta=-1: policy elastic: Input should be greater than or equal to 0",
        ),
        ("elastic", ["hedge=maybe"], "--param hedge=maybe"),
        ("elastic", ["forced_schedule=weekly"], "'doubling', 'every' or 'off'"),
        ("elastic", ["sigma_key=0.1", "sigma_nonkey=0.5"], "must be <= sigma_key"),
        ("elastic", ["beta"], "--param 'beta': expected KEY=VALUE"),
        ("elastic", ["=3"], "expected KEY=VALUE"),
        ("ans", ["change_detection=false"], "policy ans has no parameter 'change_detection'"),
        ("robot", ["beta=1"], "policy robot takes no parameters"),
        ("compare:elastic,robot", ["zeta=1"], "none of elastic, robot has a parameter 'zeta'"),
        ("compare:ans,neurosurgeon", ["ewma=2"], "--param ewma=2: policy neurosurgeon"),
    ],
)
def test_bad_param_is_one_line_and_exit_2(
    tmp_path: Path, policy: str, params: list[str], message: str
) -> None:
    which = (
        ["--compare", policy.split(":", 1)[1]]
        if policy.startswith("compare:")
        else ["--policy", policy]
    )
    argv = [
        "--profile",
        str(VGG),
        "--trace",
        str(GLITCH),
        *which,
        "--plot",
        str(tmp_path / "x.png"),
    ]
    for item in params:
        argv += ["--param", item]
    code, out, err = sim(*argv)
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("error:")
    assert message in lines[0]
    assert not (tmp_path / "x.png").exists()  # rejected before anything ran


def test_model_and_profile_are_exclusive(tmp_path: Path) -> None:
    code, _, err = sim(
        "--model", "zoo:vgg", "--profile", str(VGG), "--policy", "robot", "--trace", str(GLITCH)
    )
    assert code == 2
    assert "exactly one of --model" in err


def test_model_without_the_profiler_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "common.profiler", None)  # import fails
    code, _, err = sim("--model", "zoo:vgg", "--policy", "robot", "--trace", str(GLITCH))
    assert code == 2
    assert "--profile FILE" in err

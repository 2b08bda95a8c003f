"""Table I's repeated cells: the median run is reported, beside every run's mean latency."""

from __future__ import annotations

from experiments.single_edge import SingleEdgeResult
from experiments.stats import summary
from experiments.table1 import Table1Row, Table1Settings, markdown, median_run


def _run(latencies_s: list[float], lost: int = 0, policy: str = "elastic") -> Table1Row:
    records = [
        {
            "frame": n,
            "latency_s": latency,
            "robot_cpu_s": 0.002,
            "energy_j": 0.1,
            "bytes_up": 4000,
            "action": "cut:0:jpeg50",
            "deployment": "edge-1",
        }
        for n, latency in enumerate(latencies_s)
    ]
    return Table1Row(12.0, policy, summary(records), lost)


def test_the_median_run_is_reported_with_every_runs_mean_and_all_frames_lost() -> None:
    runs = [_run([0.05, 0.07]), _run([0.04]), _run([0.20], lost=2), _run([]), _run([0.045])]
    cell = median_run(runs)
    # Means 0.06, 0.04, 0.20, none (slowest), 0.045: the third of five in order is 0.06.
    assert cell.window.mean_latency_s == runs[0].window.mean_latency_s
    assert cell.lost == 2
    assert cell.runs_mean_latency_s == (
        runs[0].window.mean_latency_s,
        0.04,
        0.20,
        None,
        0.045,
    )
    assert cell.to_json()["runs_mean_latency_s"] == list(cell.runs_mean_latency_s)


def test_an_even_count_reports_the_lower_median_run() -> None:
    assert median_run([_run([0.3]), _run([0.1])]).window.mean_latency_s == 0.1


def test_a_single_run_keeps_the_rows_json_keys() -> None:
    cell = median_run([_run([0.05])])
    assert "runs_mean_latency_s" not in cell.to_json()
    assert list(cell.to_json())[:3] == ["uplink_mbit", "policy", "frames"]


def _result(repeat: int) -> SingleEdgeResult[Table1Settings, Table1Row]:
    settings = Table1Settings("zoo:mobilenet_v2", [3, 224, 224], 0.1, 130, 10, repeat=repeat)
    cells = [
        median_run([_run([0.04 + 0.01 * i], policy=p) for i in range(repeat)])
        for p in ("cloud:jpeg50", "elastic")
    ]
    return SingleEdgeResult(settings, cells)


def test_markdown_lists_each_run_only_when_repeated() -> None:
    assert "alternated runs" not in markdown(_result(1))
    text = markdown(_result(3))
    assert "mean latency of each of the 3 alternated runs" in text
    assert "| 12 | 0.040 / 0.050 / 0.060 | 0.040 / 0.050 / 0.060 |" in text

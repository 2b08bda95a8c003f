"""A scheduling round grows about linearly in robots: the median round of a simulated fleet of
1,000 robots against that of 100 robots, both measured in this test (ratio, not time: the
machine's speed cancels out). The fleet is benchmarks/registry_sim_fleet.py: the registry
daemon's own control loop, scheduler, switch protocol and sqlite RIB, no Zenoh, with churn and
latency reports at 10 Hz per robot.

Guards against per-round work that grows with robots x robots (each robot's probe profiles found
by scanning every window of the fleet made 10x the robots cost 100x) and against a RIB read per
robot and round.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

FLEET_SIM = Path(__file__).resolve().parents[2] / "benchmarks" / "registry_sim_fleet.py"
SMALL_ROBOTS = 100
LARGE_ROBOTS = 1000
DEPLOYMENTS = 20
WARMUP_S = 6.0
DURATION_S = 2.0
# Linear growth is 10x; robots x robots is 100x. Generous for a busy machine.
MAX_RATIO = 30.0


def _fleet_sim() -> ModuleType:
    """The benchmark's module, loaded from its file (benchmarks/ is not a package)."""
    spec = importlib.util.spec_from_file_location("registry_sim_fleet", FLEET_SIM)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    # Registered before it runs: its dataclasses look their module up while being made.
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_a_1000_robot_round_costs_about_ten_100_robot_rounds() -> None:
    sim = _fleet_sim()

    def run(robots: int) -> float:
        cfg = sim.SimConfig(
            robots=robots, deployments=DEPLOYMENTS, warmup_s=WARMUP_S, duration_s=DURATION_S
        )
        result = sim.simulate(cfg)
        assert result.rounds == round(DURATION_S / 0.1)
        return float(result.round_median_ms)

    small_ms, large_ms = run(SMALL_ROBOTS), run(LARGE_ROBOTS)
    ratio = large_ms / small_ms
    assert ratio <= MAX_RATIO, (
        f"a round of {LARGE_ROBOTS} robots took {large_ms:.1f} ms, {ratio:.0f}x the"
        f" {small_ms:.2f} ms of {SMALL_ROBOTS} robots (linear: 10x, allowed {MAX_RATIO:g}x)"
    )

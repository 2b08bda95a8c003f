"""How the load generator spaces a robot's frames: periodic ticks or Poisson arrivals."""

from __future__ import annotations

import random
import statistics

import pytest

from common.errors import UserError
from experiments.load_generator import LoadGenerator, frame_gap_s
from experiments.scale import ScaleOptions


def test_periodic_gaps_are_the_period() -> None:
    assert {frame_gap_s(0.1, None) for _ in range(5)} == {0.1}


def test_poisson_gaps_keep_the_mean_rate_and_vary_as_exponential_ones() -> None:
    rng = random.Random(7)
    gaps = [frame_gap_s(0.1, rng) for _ in range(4000)]
    mean = statistics.fmean(gaps)
    assert mean == pytest.approx(0.1, rel=0.08)
    # An exponential's spread equals its mean (a periodic stream has none).
    assert statistics.pstdev(gaps) / mean == pytest.approx(1.0, rel=0.1)
    assert min(gaps) > 0


def test_unknown_arrivals_are_refused_by_name() -> None:
    with pytest.raises(ValueError, match="arrivals must be one of periodic, poisson"):
        LoadGenerator(None, ["robot-1"], arrivals="uniform")  # type: ignore[arg-type]
    with pytest.raises(UserError, match="--arrivals 'uniform'"):
        ScaleOptions(arrivals="uniform").check()

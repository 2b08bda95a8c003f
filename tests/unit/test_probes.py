"""The probes' padding adapts to the uplink it measures: a small share of a slow link, a
frame-like transfer on a fast one."""

from __future__ import annotations

import pytest

from robotd.frame_path.probes import (
    PROBE_INTERVAL_S,
    PROBE_MAX_PADDING_BYTES,
    PROBE_MIN_PADDING_BYTES,
    PROBE_UPLINK_SHARE,
    next_padding_bytes,
    probe_padding_bytes,
)

CEILING = PROBE_MAX_PADDING_BYTES
ROUNDS = 40


def settle(rate_bytes_s: float, base_rtt_s: float, rounds: int = ROUNDS) -> list[int]:
    """Paddings over `rounds` probe rounds on a link of that rate and bare round trip."""
    padding = PROBE_MIN_PADDING_BYTES
    seen = [padding]
    for _ in range(rounds):
        rtt_s = base_rtt_s + padding / rate_bytes_s
        padding = next_padding_bytes(padding, rtt_s, interval_s=PROBE_INTERVAL_S, ceiling=CEILING)
        seen.append(padding)
    return seen


@pytest.mark.parametrize("mbit", [0.5, 1.0, 2.0])
def test_slow_uplink_gives_probes_a_small_share(mbit: float) -> None:
    rate = mbit * 1e6 / 8
    paddings = settle(rate, base_rtt_s=0.002)
    share = [p / (rate * PROBE_INTERVAL_S) for p in paddings]
    # Every round, not only the settled ones, stays within the budget (with the floor's slack).
    floor_share = PROBE_MIN_PADDING_BYTES / (rate * PROBE_INTERVAL_S)
    assert max(share) <= max(PROBE_UPLINK_SHARE, floor_share) * 1.01
    assert paddings[-1] < PROBE_MAX_PADDING_BYTES / 4


def test_fast_uplink_grows_to_a_frame_like_transfer() -> None:
    paddings = settle(20e6 / 8 * 10, base_rtt_s=0.001)  # 200 Mbit/s
    assert paddings[-1] == CEILING
    assert paddings.index(CEILING) <= 7  # doubling from 1 KiB: 64 KiB in 6 rounds


def test_padding_follows_a_rate_drop_down() -> None:
    fast = settle(200e6 / 8, base_rtt_s=0.001)
    padding = fast[-1]
    slow_rate = 1e6 / 8
    for _ in range(5):
        rtt_s = 0.001 + padding / slow_rate
        padding = next_padding_bytes(padding, rtt_s, interval_s=PROBE_INTERVAL_S, ceiling=CEILING)
    assert padding / (slow_rate * PROBE_INTERVAL_S) <= PROBE_UPLINK_SHARE * 1.01


def test_no_answer_halves_and_the_bounds_hold() -> None:
    assert next_padding_bytes(8192, None, interval_s=2.0, ceiling=CEILING) == 4096
    assert next_padding_bytes(1024, None, interval_s=2.0, ceiling=CEILING) == 1024
    assert next_padding_bytes(CEILING, 0.0001, interval_s=2.0, ceiling=CEILING) == CEILING
    # A model whose cuts are smaller than the floor: the ceiling wins.
    assert next_padding_bytes(512, 0.0001, interval_s=2.0, ceiling=300) == 300


def test_a_long_bare_round_trip_leaves_the_minimum_padding() -> None:
    paddings = settle(100e6 / 8, base_rtt_s=0.2)
    assert paddings[-1] == PROBE_MIN_PADDING_BYTES


def test_ceiling_is_a_typical_cut() -> None:
    assert probe_padding_bytes([10, 30, 20]) == 20
    assert probe_padding_bytes([10**6] * 3) == PROBE_MAX_PADDING_BYTES
    assert probe_padding_bytes([]) == 0

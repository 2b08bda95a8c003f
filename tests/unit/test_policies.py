"""Policies against synthetic costs: the learner's pieces, and baselines on hand-computed cases."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.errors import UserError
from robotd.policies import (
    PURE_ROBOT,
    Decision,
    FrameContext,
    Objective,
    Outcome,
    make_policy,
    policy_names,
)
from robotd.policies.base import CutTable
from robotd.policies.elastic import ElasticPolicy
from robotd.policies.params import RobotCostParams
from robotd.policies.ridge import RidgeEstimator
from robotd.policies.robotcost import RobotCostModel
from robotd.policies.schedule import ForcedSchedule

PROFILES = Path(__file__).resolve().parents[1] / "data" / "profiles"

# A tiny chain: bytes shrink, prefix time grows (ms on the profiling host).
TINY = {
    "full_ms": 100.0,
    "cuts": [
        {"index": 0, "bytes": 1_000_000, "prefix_ms": 0.0, "suffix_ms": 100.0},
        {"index": 1, "bytes": 100_000, "prefix_ms": 50.0, "suffix_ms": 50.0},
        {"index": 2, "bytes": 1_000, "prefix_ms": 90.0, "suffix_ms": 10.0},
    ],
}


def vgg_profile() -> dict[str, Any]:
    return json.loads((PROFILES / "vgg-like-3x240x320.json").read_text())


def elastic(profile: dict[str, Any] = TINY, **params: Any) -> ElasticPolicy:
    policy = make_policy("elastic", profile, params)
    assert isinstance(policy, ElasticPolicy)
    return policy


# -- ridge regression -------------------------------------------------------------------------


@pytest.mark.parametrize("updates", [5, 300, 3000])
def test_sherman_morrison_matches_a_fresh_inverse(updates: int) -> None:
    # Guards the plain-float update against drift: thousands of updates, no inverse in between.
    rng = np.random.default_rng(updates)
    contexts = np.column_stack([rng.uniform(0, 2, 16), rng.uniform(0, 1, 16), np.ones(16)])
    gamma = 0.7
    ridge = RidgeEstimator(contexts, gamma)
    q = gamma * np.eye(3)
    p = np.zeros(3)
    for _ in range(updates):
        row = int(rng.integers(16))
        y = float(contexts[row] @ [0.8, 0.05, 0.01] + rng.normal(0, 0.01))
        ridge.update(row, y)
        q += np.outer(contexts[row], contexts[row])
        p += contexts[row] * y
    q_inv = np.linalg.inv(q)
    np.testing.assert_allclose(ridge.q_inv, q_inv, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ridge.alpha, q_inv @ p, rtol=1e-7, atol=1e-10)
    widths = np.sqrt(np.einsum("ij,jk,ik->i", contexts, q_inv, contexts))
    np.testing.assert_allclose(ridge.width, widths, rtol=1e-7, atol=1e-10)
    assert ridge.samples == updates


def test_ridge_reset_forgets_evidence() -> None:
    contexts = np.array([[1.0, 0.5, 1.0], [0.1, 0.1, 1.0]])
    ridge = RidgeEstimator(contexts, 2.0)
    ridge.update(0, 3.0)
    ridge.reset()
    np.testing.assert_allclose(ridge.q_inv, np.eye(3) / 2.0)
    np.testing.assert_allclose(ridge.alpha, 0.0)
    np.testing.assert_allclose(ridge.pred, 0.0)
    np.testing.assert_allclose(ridge.width, np.sqrt((contexts**2).sum(axis=1) / 2.0))
    assert ridge.samples == 0


def test_ridge_takes_any_context_dimension() -> None:
    rng = np.random.default_rng(1)
    contexts = rng.uniform(0, 1, (5, 4))
    ridge = RidgeEstimator(contexts, 1.0)
    for row in (0, 3, 3, 1):
        ridge.update(row, 1.0)
    ridge.update_vector(np.array([0.5, 0.5, 0.5, 0.5]), 2.0)
    q = np.eye(4) + sum(np.outer(contexts[r], contexts[r]) for r in (0, 3, 3, 1))
    q += np.full((4, 4), 0.25)
    p = contexts[[0, 3, 3, 1]].sum(axis=0) + 1.0
    np.testing.assert_allclose(ridge.q_inv, np.linalg.inv(q), rtol=1e-12)
    np.testing.assert_allclose(ridge.pred, contexts @ np.linalg.solve(q, p), rtol=1e-12)


# -- forced sampling schedule ------------------------------------------------------------------


def test_doubling_schedule_forces_every_ceil_te_quarter_frames() -> None:
    schedule = ForcedSchedule("doubling", start_frames=200, exponent=0.25)
    forced = [n for n in range(3200) if schedule.is_forced(n)]
    # T_e = 200 → every 4 frames in [0, 200); 400 → 5 in [200, 400); 800 → 6 in [400, 800);
    # 1600 → 7 in [800, 1600); 3200 → 8 in [1600, 3200).
    expected = (
        list(range(0, 200, 4))
        + list(range(200, 400, 5))
        + list(range(400, 800, 6))
        + list(range(800, 1600, 7))
        + list(range(1600, 3200, 8))
    )
    assert forced == expected
    assert schedule.interval(25_600 * 2 - 1) == math.ceil(51_200**0.25)


def test_doubling_schedule_answers_frames_in_any_order() -> None:
    # Guards the cached epoch: a query outside it (backwards, or far ahead) must not reuse it.
    in_order = ForcedSchedule("doubling")
    expected = [in_order.is_forced(n) for n in range(6400)]
    shuffled = ForcedSchedule("doubling")
    order = np.random.default_rng(3).permutation(6400)
    assert all(shuffled.is_forced(int(n)) == expected[n] for n in order)


def test_every_and_off_schedules() -> None:
    every = ForcedSchedule("every", every_frames=10)
    assert [n for n in range(45) if every.is_forced(n)] == [0, 10, 20, 30, 40]
    off = ForcedSchedule("off")
    assert not any(off.is_forced(n) for n in range(1000))


def test_forced_frames_offload_even_when_robot_is_better() -> None:
    # A fast robot: P is far cheaper than any offload, yet forced frames still sample the cloud.
    policy = elastic(forced_schedule="every", forced_every_frames=5)
    actions = []
    for t in range(40):
        d = policy.decide(FrameContext(t, 0.5))
        actions.append(d.action)
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=0.1, latency_s=0.1))
        else:
            y = 5.0  # a terrible link
            policy.observe(d, Outcome(prefix_s=0.0005 * d.action, cloud_s=y, local_s=0.1))
    forced_frames = {t for t in range(40) if t % 5 == 0}
    assert all(actions[t] != PURE_ROBOT for t in forced_frames)
    assert any(a == PURE_ROBOT for t, a in enumerate(actions) if t not in forced_frames)


# -- σ step and exploration bonus --------------------------------------------------------------


def test_sigma_is_a_step_function_of_entropy() -> None:
    policy = elastic()
    assert policy.sigma(0.0) == 0.2
    assert policy.sigma(0.799) == 0.2
    assert policy.sigma(0.8) == 0.8
    assert policy.sigma(1.0) == 0.8
    custom = elastic(sigma_key=0.9, sigma_nonkey=0.1, key_entropy=0.5)
    assert custom.sigma(0.49) == 0.1
    assert custom.sigma(0.5) == 0.9


def test_key_frames_explore_less() -> None:
    # The same uncertain cut: its bonus beats P on a non-key frame but not on a key frame.
    policy = elastic(change_detection=False, forced_schedule="off")
    p_cost = policy._robot.full_cost
    policy._scores.base = [p_cost + 0.5, p_cost + 0.5, p_cost + 0.5]
    policy._bonus_scale = 1.0
    policy._scores.width = [0.0, 0.0, 0.8]  # score = base - sqrt(1-σ)·bonus
    policy._choose()
    nonkey = policy.decide(FrameContext(0, entropy=0.1))  # sqrt(0.8)·0.8 = 0.72 > 0.5
    key = policy.decide(FrameContext(1, entropy=0.95))  # sqrt(0.2)·0.8 = 0.36 < 0.5
    assert nonkey.action == 2
    assert key.action == PURE_ROBOT


# -- robot-side cost -------------------------------------------------------------------------


def test_a_short_run_does_not_set_the_first_robot_speed() -> None:
    # Under a CPU quota a 0.3 ms JPEG encode took 3 ms: taken as the robot's speed, it made P
    # look 10x dearer than it is. The profile (measured on the robot) keeps its scale until a
    # run of a real share of the model is timed.
    cuts = CutTable.from_profile(
        {"full_ms": 60.0, "cuts": [{"index": 0, "bytes": 5_000, "prefix_ms": 0.3, "suffix_ms": 60}]}
    )
    model = RobotCostModel(cuts, Objective(), RobotCostParams())
    assert model.observe(0.003, 0.0003) is None
    assert model.full_cost == pytest.approx(0.060)
    model.observe(0.066, cuts.full_s)  # the whole model, within the tolerance: the EWMA moves
    assert 0.060 < model.full_cost < 0.066


def test_one_slow_first_run_does_not_set_the_robot_speed() -> None:
    # The first frame's hedged local run took 0.23 s for a model that runs in 0.085 s on that
    # robot (cold caches, racing the offload). Adopted, it made P look 2.7x dearer than it is.
    # It is one miss against the profile's scale; a second one in the same direction confirms.
    cuts = CutTable.from_profile(
        {"full_ms": 85.0, "cuts": [{"index": 0, "bytes": 5_000, "prefix_ms": 0.3, "suffix_ms": 85}]}
    )
    model = RobotCostModel(cuts, Objective(), RobotCostParams())
    assert model.observe(0.23, cuts.full_s) == 1
    assert model.full_cost == pytest.approx(0.085)
    assert model.suspect
    assert model.observe(0.088, cuts.full_s) == 0  # the next run fits the profile: cleared
    assert not model.suspect
    assert model.full_cost == pytest.approx(0.085, rel=0.02)


def test_robot_cost_follows_a_cpu_drop_in_two_measurements() -> None:
    cuts = CutTable.from_profile(TINY)
    model = RobotCostModel(cuts, Objective(), RobotCostParams())
    # The robot is 10× slower than the profiling host: one run is a suspect, two adopt it.
    assert model.observe(1.0, cuts.full_s) == 1
    assert model.full_cost == pytest.approx(0.1)
    assert model.observe(1.0, cuts.full_s) == 1
    assert model.full_cost == pytest.approx(1.0)
    model.observe(3.0, cuts.full_s)  # one surprising run: held as a suspect, not adopted
    assert model.full_cost == pytest.approx(1.0)
    assert model.suspect
    model.observe(3.2, float(cuts.prefix_s[1]) * 2)  # the same slowdown seen on a prefix
    assert model.full_cost == pytest.approx(3.1)
    np.testing.assert_allclose(model.prefix_cost, cuts.prefix_s * 31)


def test_robot_cost_ignores_runs_too_short_to_time() -> None:
    cuts = CutTable.from_profile(TINY)
    model = RobotCostModel(cuts, Objective(), RobotCostParams())
    model.tick()
    model.observe(0.01, 0.0)  # cut 0's prefix: nothing ran, nothing to learn
    assert not model.timed
    assert model.full_cost == pytest.approx(0.1)  # still the profile's figure
    assert model.frames_since_timed == 1  # and the robot still counts as untimed


def test_robot_is_probed_while_only_raw_input_is_sent() -> None:
    # A fast link: cut 0 (no robot compute) is best, so nothing would time the robot.
    policy = elastic(robot_probe_frames=10, forced_schedule="off")
    hedges = []
    for t in range(200):
        d = policy.decide(FrameContext(t, 0.9))
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=1.0, latency_s=1.0))
            continue
        cut = int(d.action)
        prefix = (0.0, 0.5, 0.9)[cut]
        local = (1.0, 0.5, 0.1)[cut] if d.hedge else None
        y = 0.05 + 1e-7 * TINY["cuts"][cut]["bytes"]  # type: ignore[index]
        policy.observe(d, Outcome(prefix_s=prefix, cloud_s=y, local_s=local))
        if t >= 100:
            assert cut == 0
            hedges.append(d.hedge)
    # Once settled on cut 0, one frame in every robot_probe_frames is hedged to time the robot.
    assert sum(hedges) == pytest.approx(len(hedges) / 10, abs=2)


def test_a_forced_sample_while_p_is_best_makes_the_local_run_the_main_path() -> None:
    # A slow link: every cut costs far more than the whole model on the robot (0.1 s), so P is
    # chosen and forced frames explore. Their local run is the frame's expected path: it must
    # run at once at the loop's priority, not as starved speculative work.
    policy = elastic(forced_schedule="every", forced_every_frames=5)
    explored = []
    for t in range(120):
        d = policy.decide(FrameContext(t, 0.9))
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=0.1, latency_s=0.1))
            assert not d.local_expected
            continue
        cut = int(d.action)
        y = 0.3 + 8e-6 * TINY["cuts"][cut]["bytes"]  # type: ignore[index]
        local = (0.1, 0.05, 0.01)[cut]
        policy.observe(d, Outcome(prefix_s=(0.0, 0.05, 0.09)[cut], cloud_s=y, local_s=local))
        if t >= 60:
            explored.append(d)
    assert explored, "no forced frame explored after settling"
    assert all(d.forced and d.hedge and d.local_expected for d in explored)
    assert all(d.hedge_after_s == pytest.approx(0.0, abs=1e-9) for d in explored)


# -- change detection and the single-direction restriction -------------------------------------


def settle_on_cut(policy: ElasticPolicy, cut: int, y_of: dict[int, float], frames: int) -> None:
    """Feed consistent outcomes until the policy has left its initial update period on `cut`."""
    for t in range(frames):
        d = policy.decide(FrameContext(t, 0.9))
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=1.0, latency_s=1.0))
        else:
            c = int(d.action)
            policy.observe(d, Outcome(prefix_s=(0.0, 0.5, 0.9)[c], cloud_s=y_of[c], local_s=0.1))
    assert not policy.updating


def test_repeated_slower_misses_restrict_to_actions_sending_less() -> None:
    policy = elastic(forced_schedule="off", change_frames=3, fit_frames=50)
    y_of = {0: 0.15, 1: 0.06, 2: 0.05}  # 1e-7 s/byte + 0.05 s: cut 0 is best (0.15 < 0.56, 0.95)
    settle_on_cut(policy, 0, y_of, 400)
    slow = Decision(0)
    for _ in range(2):
        policy.observe(slow, Outcome(prefix_s=0.0, cloud_s=1.5))
        assert not policy.updating  # m - 1 misses are not a change
    policy.observe(slow, Outcome(prefix_s=0.0, cloud_s=1.5))
    assert policy.updating
    assert policy.update_periods == 1
    # Slower than predicted on cut 0 (1 MB): every cut sends no more than that, and P is allowed.
    assert policy.allowed_actions() == ["0", "1", "2", PURE_ROBOT]
    # The misses are the first evidence of the new conditions: the model now predicts them.
    assert policy.predicted_cloud_cost()["0"] == pytest.approx(1.5, rel=0.3)


def test_faster_misses_restrict_to_actions_sending_more_and_exclude_p() -> None:
    policy = elastic(forced_schedule="off", change_frames=2, fit_frames=50)
    y_of = {0: 1.05, 1: 0.15, 2: 0.051}  # 1e-6 s/byte + 0.05 s: cut 1 is best (0.65)
    settle_on_cut(policy, 1, y_of, 400)
    for _ in range(2):
        policy.observe(Decision(1), Outcome(prefix_s=0.5, cloud_s=0.01))
    assert policy.updating
    # Faster than predicted on cut 1 (100 kB): only cuts sending at least that much, no P.
    assert policy.allowed_actions() == ["0", "1"]
    for t in range(10):
        d = policy.decide(FrameContext(t, 0.9))
        assert d.action in (0, 1)
        assert d.hedge and d.updating  # exploring during an update period is hedged


def test_update_period_ends_when_predictions_fit_again() -> None:
    policy = elastic(forced_schedule="off", change_frames=2, fit_frames=4)
    y_of = {0: 0.15, 1: 0.06, 2: 0.05}
    settle_on_cut(policy, 0, y_of, 400)
    for _ in range(2):
        policy.observe(Decision(0), Outcome(prefix_s=0.0, cloud_s=1.5))
    assert policy.updating
    new_y = {0: 1.5, 1: 0.19, 2: 0.05}  # the uplink fell tenfold
    for t in range(200):
        d = policy.decide(FrameContext(t, 0.9))
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=1.0, latency_s=1.0))
        else:
            c = int(d.action)
            policy.observe(d, Outcome(prefix_s=(0.0, 0.5, 0.9)[c], cloud_s=new_y[c], local_s=0.1))
        if not policy.updating:
            break
    assert not policy.updating
    assert policy.allowed_actions() == ["0", "1", "2", PURE_ROBOT]
    # Now cut 1 (0.5 + 0.19) beats cut 0 (1.5), cut 2 (0.95) and P (1.0).
    greedy = [policy.decide(FrameContext(1000 + t, 1.0)).action for t in range(5)]
    assert greedy.count(1) >= 4


def test_a_timeout_teaches_that_the_action_is_expensive() -> None:
    policy = elastic(forced_schedule="off", change_frames=3)
    y_of = {0: 0.15, 1: 0.06, 2: 0.05}
    settle_on_cut(policy, 0, y_of, 400)
    deadline = 2.0
    for t in range(60):
        d = policy.decide(FrameContext(t, 0.9))
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=1.0, latency_s=1.0))
            continue
        # The cloud is gone: every attempt waits out the deadline and finishes locally.
        c = int(d.action)
        policy.observe(
            d, Outcome(prefix_s=(0.0, 0.5, 0.9)[c], cloud_s=None, waited_s=deadline, local_s=0.5)
        )
    assert policy.predicted_cloud_cost()["0"] > 1.0
    decisions = [policy.decide(FrameContext(100 + t, 1.0)) for t in range(20)]
    assert sum(d.action == PURE_ROBOT for d in decisions) >= 15


def test_ans_never_hedges_nor_restricts() -> None:
    policy = make_policy("ans", TINY)
    assert isinstance(policy, ElasticPolicy)
    for t in range(300):
        d = policy.decide(FrameContext(t, 0.5))
        assert not d.hedge and not d.updating
        if d.action == PURE_ROBOT:
            policy.observe(d, Outcome(prefix_s=1.0, latency_s=1.0))
        else:
            policy.observe(d, Outcome(prefix_s=0.0, cloud_s=5.0 if t > 150 else 0.1))
    assert policy.update_periods == 0
    assert policy.allowed_actions() == ["0", "1", "2", PURE_ROBOT]


def test_ans_first_decision_matches_the_hand_computed_lcb() -> None:
    # Nothing observed: α̂ = 0, Q⁻¹ = I/γ, so score_a = E_a - β·E_P·sqrt((1-σ)·|v_a|²/γ).
    policy = make_policy("ans", TINY, {"beta": 1.0, "gamma": 1.0, "forced_schedule": "off"})
    e_p = 0.1  # full_ms on the profiling host, not yet rescaled by a measurement
    v = np.array([[1.0, 1.0, 1.0], [0.1, 0.5, 1.0], [0.001, 0.1, 1.0]])
    prefix = np.array([0.0, 0.05, 0.09])
    scores = prefix - e_p * np.sqrt(0.8 * (v * v).sum(axis=1))
    assert policy.decide(FrameContext(0, entropy=0.0)).action == int(np.argmin(scores))


# -- baselines on hand-computed cases ------------------------------------------------------------


def test_fixed_baselines() -> None:
    ctx = FrameContext(0, 0.5)
    assert make_policy("robot", TINY).decide(ctx).action == PURE_ROBOT
    assert make_policy("cloud", TINY).decide(ctx).action == 0
    assert make_policy("static:2", TINY).decide(ctx) == Decision(2)
    shuffled = {"full_ms": 10, "cuts": [TINY["cuts"][2], TINY["cuts"][1]]}  # type: ignore[index]
    assert make_policy("cloud", shuffled).decide(ctx).action == 1  # the lowest cut present


def test_oracle_picks_the_least_true_cost() -> None:
    oracle = make_policy("oracle", TINY)
    assert oracle.decide(FrameContext(0, 0.5, expected_costs=(0.9, 0.4, 0.6, 0.5))).action == 1
    assert oracle.decide(FrameContext(0, 0.5, expected_costs=(0.9, 0.4, 0.6, 0.3))).action == "P"
    with pytest.raises(UserError, match="simulator"):
        oracle.decide(FrameContext(0, 0.5))


def test_neurosurgeon_predicts_from_profile_and_measured_transfers() -> None:
    policy = make_policy(
        "neurosurgeon",
        TINY,
        {"uplink_mbit": 10, "rtt_ms": 20, "cloud_speedup": 4, "ewma": 1.0},
    )
    # The robot runs the whole model in 1 s: 10× slower than the profile (twice: one run alone
    # is a suspect).
    for _ in range(2):
        policy.observe(Decision(PURE_ROBOT), Outcome(prefix_s=1.0, latency_s=1.0))
    # cut 0: 0 + 0.02 + 0.8 + 0.025 = 0.845; cut 1: 0.5 + 0.02 + 0.08 + 0.0125 = 0.6125;
    # cut 2: 0.9 + 0.02 + 0.0008 + 0.0025 = 0.9233; P: 1.0.
    first = policy.decide(FrameContext(0, 0.5))
    assert first.action == 1
    assert first.predicted_cost == pytest.approx(0.6125)
    # The uplink turns out to be 1 Mbit/s: 100 kB took 0.8 s on top of the RTT.
    policy.observe(
        first, Outcome(prefix_s=0.5, cloud_s=0.02 + 0.8 + 0.0125, cloud_compute_s=0.0125)
    )
    assert policy.state()["uplink_mbit"] == pytest.approx(1.0)
    # cut 1: 0.5 + 0.02 + 0.8 + 0.0125 = 1.3325; cut 2: 0.9 + 0.02 + 0.008 + 0.0025 = 0.9305.
    second = policy.decide(FrameContext(1, 0.5))
    assert second.action == 2
    assert second.predicted_cost == pytest.approx(0.9305)


# -- make_policy and parameters --------------------------------------------------------------


def test_every_named_policy_builds_on_a_real_profile() -> None:
    profile = vgg_profile()
    for name in policy_names():
        if name.startswith("option:"):
            continue  # builds on a model naming its points cut: test_nav_options
        placeholders = {"static:K": "static:3", "static:K:CODEC": "static:3:raw"}
        spec = placeholders.get(name, name.replace("CODEC", "raw"))
        policy = make_policy(spec, profile)
        assert policy.name == spec


@pytest.mark.parametrize(
    ("spec", "params", "objective", "message"),
    [
        ("teleport", None, None, "unknown policy 'teleport'"),
        ("static:x", None, None, "static needs a cut index"),
        ("static:7", None, None, "cut 7 is not in the profile"),
        ("elastic", {"betta": 1}, None, "betta"),
        ("elastic", {"beta": -1}, None, "beta"),
        ("elastic", {"sigma_key": 0.1, "sigma_nonkey": 0.5}, None, "sigma_nonkey"),
        ("ans", {"change_detection": True}, None, "change_detection"),
        ("robot", {"beta": 1}, None, "beta"),
        ("neurosurgeon", {"uplink_mbit": 0}, None, "uplink_mbit"),
        ("elastic", None, {"latency": 1, "watts": 2}, "watts"),
        ("elastic", None, {"latency": 0}, "at least one"),
        ("elastic", None, {"power": {"idle_w": 5, "busy_w": 1}}, "busy_w"),
    ],
)
def test_bad_policy_input_is_one_clear_error(
    spec: str, params: dict[str, Any] | None, objective: dict[str, Any] | None, message: str
) -> None:
    with pytest.raises(UserError, match=message) as info:
        make_policy(spec, TINY, params, objective)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("profile", "message"),
    [
        ({"cuts": TINY["cuts"]}, "full_ms"),
        ({"full_ms": 10, "cuts": []}, "cuts"),
        (
            {"full_ms": 10, "cuts": [{"index": 0, "bytes": -1, "prefix_ms": 0, "suffix_ms": 1}]},
            "bytes",
        ),
        ({"full_ms": 10, "cuts": [TINY["cuts"][0], TINY["cuts"][0]]}, "more than once"),  # type: ignore[index]
        ([1, 2], "JSON object"),
    ],
)
def test_bad_profiles_are_named(profile: Any, message: str) -> None:
    with pytest.raises(UserError, match=message):
        make_policy("elastic", profile)


def test_objective_weighs_latency_cpu_energy_and_bytes() -> None:
    goal = Objective.parse(
        {
            "latency": 1,
            "cpu": 0.5,
            "energy": 0.1,
            "bytes": 0.01,
            "power": {"idle_w": 2, "busy_w": 6, "tx_w": 3},
        }
    )
    # 0.4 s latency, 0.3 CPU-s, 0.1 s of radio, 2 MB: energy = 2·0.4 + 4·0.3 + 1·0.1 = 2.1 J.
    assert goal.energy_j(0.4, 0.3, 0.1) == pytest.approx(2.1)
    assert goal.frame_cost(0.4, 0.3, 0.1, 2.0) == pytest.approx(0.4 + 0.15 + 0.21 + 0.02)
    # The learner's split adds up to the same for an offloaded frame (prefix 0.3 s, y 0.1 s,
    # no server compute reported, 2 MB).
    split = goal.robot_rate * 0.3 + goal.cloud_part(0.1, None) + goal.bytes * 2.0
    assert split == pytest.approx(goal.frame_cost(0.4, 0.3, 0.1, 2.0))
    assert Objective.parse(None) == Objective()


# -- (cut, codec) actions --------------------------------------------------------------------------
CODEC_PROFILE = {
    "full_ms": 40.0,
    "cuts": [
        {
            "index": 0,
            "bytes": 230_400,
            "prefix_ms": 0.0,
            "suffix_ms": 40.0,
            "codecs": [
                {"name": "raw", "bytes": 230_400},
                {"name": "jpeg80", "bytes": 6_000, "encode_ms": 1.0, "decode_ms": 1.0},
            ],
        },
        {"index": 1, "bytes": 120_000, "prefix_ms": 20.0, "suffix_ms": 20.0},
    ],
}


def test_codecs_of_a_cut_are_separate_actions_in_profile_order() -> None:
    table = CutTable.from_profile(CODEC_PROFILE)
    assert table.labels == ("0", "0:jpeg80", "1", PURE_ROBOT)
    assert table.position(0, "jpeg80") == 1
    # Encoding is the robot's cost, decoding the cloud's; the local suffix needs neither.
    assert table.prefix_s[1] == pytest.approx(0.001)
    assert table.cloud_s[1] == pytest.approx(0.041)
    assert table.suffix_s[1] == pytest.approx(0.040)
    with pytest.raises(UserError, match="cut 1 with codec png is not in the profile"):
        table.position(1, "png")


def test_codec_baselines_name_their_action() -> None:
    ctx = FrameContext(0, 0.5)
    assert make_policy("cloud:jpeg80", CODEC_PROFILE).decide(ctx) == Decision(0, codec="jpeg80")
    assert make_policy("cloud", CODEC_PROFILE).decide(ctx) == Decision(0)
    assert make_policy("static:0:jpeg80", CODEC_PROFILE).decide(ctx).label == "0:jpeg80"
    with pytest.raises(UserError, match="codec png"):
        make_policy("cloud:png", CODEC_PROFILE)


def test_learners_follow_the_bytes_an_action_really_sends() -> None:
    """A JPEG's size follows the content: the profile says 6 KB, noisy frames send 200 KB. A
    learner that kept the profile's size would read the 0.2 s as a slow 6 KB transfer (and
    expect the raw frame to take ~8 s); following the bytes, it learns the link's 1 MB/s."""
    seconds_per_byte = 1e-6
    jpeg = Decision(0, codec="jpeg80")
    outcome = Outcome(prefix_s=0.001, cloud_s=0.005 + 200_000 * seconds_per_byte, bytes_up=200_000)
    # Both codecs stay actions (the profile's JPEG size would make the raw frame dominated).
    elastic = make_policy(
        "elastic", CODEC_PROFILE, {"forced_schedule": "off", "prune_dominated": False}
    )
    neurosurgeon = make_policy("neurosurgeon", CODEC_PROFILE)
    raw = Decision(0)
    for _ in range(100):
        elastic.observe(jpeg, outcome)
        neurosurgeon.observe(jpeg, outcome)
        # A few raw frames over the same link pin down the per-byte cost.
        elastic.observe(raw, Outcome(prefix_s=0.0, cloud_s=0.005 + 230_400 * seconds_per_byte))
    assert isinstance(elastic, ElasticPolicy)
    assert elastic.learned_bytes()["0:jpeg80"] == pytest.approx(200_000, rel=0.02)
    assert elastic.predicted_cloud_cost()["0:jpeg80"] == pytest.approx(0.205, rel=0.1)
    assert neurosurgeon.state()["uplink_mbit"] == pytest.approx(8.0, rel=0.2)


def _profile(rows: list[tuple[int, str, int, float]], full_ms: float = 40.0) -> dict[str, Any]:
    """A profile of (cut, codec, bytes, prefix ms) rows (suffix: the rest of the model)."""
    cuts: dict[int, dict[str, Any]] = {}
    for index, codec, size, prefix_ms in rows:
        cut = cuts.setdefault(
            index,
            {
                "index": index,
                "bytes": size,
                "prefix_ms": prefix_ms,
                "suffix_ms": full_ms - prefix_ms,
                "codecs": [],
            },
        )
        cut["codecs"].append({"name": codec, "bytes": size})
    return {"full_ms": full_ms, "cuts": list(cuts.values())}


def test_actions_beaten_at_every_link_speed_are_left_out() -> None:
    table = CutTable.from_profile(
        _profile(
            [
                (0, "raw", 230_400, 0.0),  # the JPEG of the same frame sends less for no work
                (0, "jpeg80", 7_000, 0.0),
                (4, "raw", 7_300_000, 4.0),  # more bytes and more robot work than the JPEG
                (20, "int8", 5_000, 30.0),  # less than the JPEG: stays
                (20, "raw", 20_000, 30.0),  # the same cut sends less in int8
                (52, "int8", 1_300, 39.9),  # P does all but 0.1 ms of it, sending nothing
            ]
        )
    )
    kept = table.undominated(0.05)
    assert kept.labels == ("0:jpeg80", "20:int8", PURE_ROBOT)
    assert kept.bytes.tolist() == [7_000, 5_000]
    # P beats the only offloading action, which still stays: a learner needs one.
    alone = CutTable.from_profile(_profile([(52, "raw", 1_300, 39.9)]))
    assert alone.undominated(0.05).labels == ("52", PURE_ROBOT)


def test_learners_never_explore_a_dominated_action() -> None:
    profile = _profile([(0, "jpeg80", 7_000, 0.0), (4, "raw", 7_300_000, 4.0)])
    for spec in ("elastic", "ans"):
        policy = make_policy(spec, profile)
        seen = {policy.decide(FrameContext(index=i)).label for i in range(200)}
        assert "4" not in seen, spec
        kept = make_policy(spec, profile, {"prune_dominated": False})
        assert "4" in kept.cuts.labels

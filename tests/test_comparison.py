"""Paired bootstrap differences between arms, on outcomes whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest

from capvector.errors import CapVectorError
from capvector.eval.comparison import (
    ArmOutcomes,
    PairedBootstrap,
    area_under_curve,
    arm_from_episodes,
    bootstrap_p_value,
    compare,
    exact,
    format_difference,
    holm,
    interval,
)

SEEDS = list(range(50))


def arm(label: str, outcomes: np.ndarray, points: list | None = None) -> ArmOutcomes:
    points = points if points is not None else list(range(outcomes.shape[1]))
    return ArmOutcomes(label, points, SEEDS, outcomes.astype(float))


def test_certain_outcomes_give_exact_differences_and_intervals() -> None:
    always = arm("always", np.ones((5, 2, 50)), [0, 600])
    never = arm("never", np.zeros((5, 2, 50)), [0, 600])
    (row,) = compare([never, always], ["never"], resamples=200)
    assert row["points"][600] == {"difference": 1.0, "ci95": pytest.approx([1.0, 1.0])}
    assert row["auc"]["difference"] == pytest.approx(1.0)
    assert format_difference(row["points"][600]) == "**+100 pts (+100, +100)**"


def test_float_rounding_does_not_decide_which_side_of_0_a_difference_is_on() -> None:
    # Averaged 0/1 outcomes: a resampled difference that is 0 comes out ±1e-17 in floats, which
    # made an interval touching 0 bold ("detected") or not (the LIBERO upstream tables did both).
    rng = np.random.default_rng(0)
    a, b = arm("a", rng.random((3, 1, 50)) < 0.4), arm("b", rng.random((3, 1, 50)) < 0.4)
    bootstrap = PairedBootstrap(SEEDS, 500, 0)
    raw = bootstrap.rates(b) - bootstrap.rates(a)
    assert ((raw != 0) & (np.abs(raw) < 1e-12)).any()  # the noise is there
    assert ((exact(raw) == 0) == (np.abs(raw) < 1e-12)).all()
    # An end that is not 0 keeps a decimal where it would round to 0; one that is 0 is not bold.
    assert (
        format_difference({"difference": 0.087, "ci95": [0.0033, 0.17]}) == "**+9 pts (+0.3, +17)**"
    )
    assert format_difference({"difference": 0.08, "ci95": [0.0, 0.16]}) == "+8 pts (+0, +16)"
    assert (
        format_difference({"difference": -0.09, "ci95": [-0.19, -0.004]})
        == "**-9 pts (-19, -0.4)**"
    )


def test_pairing_by_evaluation_seed_narrows_the_interval() -> None:
    # Half the initial states are easy for everyone; B also solves 10 of the hard ones.
    rng = np.random.default_rng(0)
    easy = rng.permutation(50) < 25
    a = np.broadcast_to(easy, (5, 1, 50)).copy()
    b = a.copy()
    b[:, :, np.flatnonzero(~easy)[:10]] = 1
    (row,) = compare([arm("A", a), arm("B", b)], ["A"], resamples=2000)
    paired = row["points"][0]["ci95"]
    assert row["points"][0]["difference"] == pytest.approx(0.2)
    assert paired[0] > 0.05  # detected
    # Drawing evaluation seeds independently per arm (no pairing) cannot see it as clearly.
    first, second = PairedBootstrap(SEEDS, 2000, 1), PairedBootstrap(SEEDS, 2000, 2)
    unpaired = interval(second.rates(arm("B", b))[:, 0] - first.rates(arm("A", a))[:, 0])
    assert paired[1] - paired[0] < 0.7 * (unpaired[1] - unpaired[0])  # theory: 0.59


def test_training_seeds_are_resampled_per_arm() -> None:
    # One seed of five fails everything: the interval must reflect seed-to-seed spread.
    good = np.ones((5, 1, 50))
    flaky = good.copy()
    flaky[0] = 0
    (row,) = compare([arm("good", good), arm("flaky", flaky)], ["good"], resamples=2000)
    low, high = row["points"][0]["ci95"]
    assert row["points"][0]["difference"] == pytest.approx(-0.2)
    assert low <= -0.4 and high == 0.0


def test_area_under_curve_is_a_mean_success_rate() -> None:
    assert area_under_curve([0, 300, 600], np.array([0.0, 0.5, 1.0])) == pytest.approx(0.5)
    assert area_under_curve([0, 200, 600], np.array([0.0, 1.0, 1.0])) == pytest.approx(5 / 6)


def test_arms_must_share_points_and_evaluation_seeds() -> None:
    per_seed = [{0: {1: True, 2: False}, 300: {1: True, 2: True}}]
    built = arm_from_episodes("x", per_seed)
    assert built.points == [0, 300] and built.eval_seeds == [1, 2]
    assert built.rates().tolist() == [0.5, 1.0]
    with pytest.raises(CapVectorError, match="training seed 1, point 300: evaluated on 1 other"):
        arm_from_episodes("x", [*per_seed, {0: {1: True, 2: False}, 300: {1: True}}])
    with pytest.raises(CapVectorError, match="no arm named \\['z'\\]"):
        compare([built], ["z"])


def test_holm_holds_the_ith_smallest_p_to_alpha_over_m_minus_i_with_a_running_maximum() -> None:
    """Holm (1979) on bootstrap p-values: raw 0.04 and 0.03 (2 % and 1.5 % of resampled
    differences at or below 0) adjust to 0.06 both, the larger by the running maximum; the
    smaller p's rank asks for a 97.5 % interval, the larger's for 95 %."""
    first = np.concatenate([-np.ones(20), np.ones(980)])  # p = 2 × 0.02
    second = np.concatenate([-np.ones(15), np.ones(985)])  # p = 2 × 0.015
    assert bootstrap_p_value(first) == pytest.approx(0.04)
    a, b = holm([first, second])
    assert (a["p"], b["p"]) == (pytest.approx(0.06), pytest.approx(0.06))
    assert (a["level"], b["level"]) == (pytest.approx(0.95), pytest.approx(0.975))
    assert a["ci"] == interval(first, 0.95) and b["ci"] == interval(second, 0.975)
    (alone,) = holm([first])  # a family of one is not adjusted
    assert alone["p"] == pytest.approx(0.04) and alone["level"] == pytest.approx(0.95)


def test_compare_adjusts_the_arms_compared_with_one_reference() -> None:
    """Two arms against plain SFT: a certain gain (p = 0) and no difference (p = 1); one arm
    alone against a reference gets no Holm entry."""
    seeds = list(range(20))
    sft = ArmOutcomes("plain SFT", [100], seeds, np.zeros((2, 1, 20)))
    better = ArmOutcomes("better", [100], seeds, np.ones((2, 1, 20)))
    same = ArmOutcomes("same", [100], seeds, np.zeros((2, 1, 20)))
    rows = compare([sft, better, same], ["plain SFT"], resamples=500)
    holms = {r["arm"]: r["points"][100]["holm"] for r in rows}
    assert holms["better"] == {"p": 0.0, "level": pytest.approx(0.975), "ci": pytest.approx([1, 1])}
    assert holms["same"] == {"p": 1.0, "level": pytest.approx(0.95), "ci": pytest.approx([0, 0])}
    assert "holm" not in compare([sft, better], ["plain SFT"], resamples=500)[0]["points"][100]

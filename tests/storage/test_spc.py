"""The QA dashboard's statistics: control limits, Western Electric rules, yields, Pareto."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calstation.storage.spc import (
    D2,
    ControlLimits,
    Yield,
    baseline_size,
    control_limits,
    pareto,
    western_electric,
)


def test_control_limits_come_from_the_moving_range_of_the_baseline() -> None:
    values = [1.0, 3.0, 1.0, 3.0] + [100.0] * 10  # the later points are not the baseline
    lim = control_limits(values, baseline=4)
    assert lim.centre == pytest.approx(2.0)
    assert lim.sigma == pytest.approx(2.0 / D2)
    assert lim.upper == pytest.approx(2.0 + 6.0 / D2)
    assert lim.lower == pytest.approx(2.0 - 6.0 / D2)
    assert lim.baseline == 4


def test_the_moving_range_estimates_sigma_of_normal_noise() -> None:
    rng = np.random.default_rng(3)
    lim = control_limits(list(rng.normal(5.0, 0.2, 4000)))
    assert lim.baseline == 1000
    assert lim.centre == pytest.approx(5.0, abs=0.02)
    assert lim.sigma == pytest.approx(0.2, rel=0.06)


def test_baseline_is_a_quarter_of_the_history_and_at_least_twenty_points() -> None:
    assert baseline_size(10) == 10
    assert baseline_size(40) == 20
    assert baseline_size(400) == 100


def test_no_value_is_a_clear_error_and_nan_is_skipped() -> None:
    with pytest.raises(ValueError, match="at least one finite value"):
        control_limits([math.nan])
    assert control_limits([1.0, math.nan, 1.0]).sigma == 0.0


LIM = ControlLimits(centre=0.0, sigma=1.0, baseline=20)


def test_rule_1_flags_a_point_beyond_3_sigma() -> None:
    flags = western_electric([0.1, -3.2, 0.2, 2.9], LIM)
    assert flags == [[], [1], [], []]


def test_rule_2_two_of_three_beyond_2_sigma_on_one_side() -> None:
    assert western_electric([2.5, 0.0, 2.2], LIM)[2] == [2]
    # on opposite sides: no flag
    assert western_electric([2.5, 0.0, -2.2], LIM)[2] == []


def test_rule_3_four_of_five_beyond_1_sigma_on_one_side() -> None:
    flags = western_electric([1.5, 1.2, 0.0, 1.4, 1.1], LIM)
    assert 3 in flags[4]
    assert all(3 not in f for f in flags[:4])


def test_rule_4_eight_in_a_row_on_one_side() -> None:
    flags = western_electric([0.3] * 7 + [0.2], LIM)
    assert flags[7] == [4] and flags[6] == []
    assert western_electric([0.3] * 7 + [-0.2], LIM)[7] == []


def test_in_control_noise_is_rarely_flagged_and_a_drift_is() -> None:
    rng = np.random.default_rng(7)
    noise = list(rng.normal(0.0, 1.0, 200))
    lim = control_limits(noise)
    flagged = sum(1 for f in western_electric(noise, lim) if f)
    assert flagged <= 8  # the four rules together: a few percent false alarms
    drift = noise + [v + 0.05 * i for i, v in enumerate(rng.normal(0.0, 1.0, 100))]
    flags = western_electric(drift, lim)
    assert sum(1 for f in flags[200:] if f) > 50


def test_yield_and_first_pass_yield_count_finished_runs() -> None:
    y = Yield()
    y.add("passed", True, 300.0)
    y.add("passed", False, 500.0)  # a step repeated
    y.add("failed", False, 100.0)
    y.add("aborted", False, None)
    y.add("running", False, None)
    d = y.as_dict()
    assert d["runs"] == 5 and d["finished"] == 4
    assert d["yield"] == pytest.approx(0.5)
    assert d["first_pass_yield"] == pytest.approx(0.25)
    assert d["median_cycle_s"] == pytest.approx(300.0)
    assert Yield().as_dict()["yield"] is None


def test_pareto_orders_reasons_and_accumulates_their_share() -> None:
    out = pareto(["cube: edge", "spin: σ ry", "cube: edge", "preflight: lidar", "cube: edge"])
    assert out[0] == ("cube: edge", 3, pytest.approx(0.6))
    assert [r for r, _, _ in out[1:]] == ["preflight: lidar", "spin: σ ry"]
    assert out[-1][2] == pytest.approx(1.0)
    assert pareto([]) == []

"""Range plausibility at a controller's input (mission_runner.runner.plausibility)."""

import logging
import math

import pytest

from mission_runner.bus import StepMessage
from mission_runner.checks import validate_scenario
from mission_runner.runner.plausibility import (
    DEFAULT_RADIO_REACH_M,
    CommandGate,
    RangeGate,
    RangeLimits,
    range_limits,
)

from .flying import load

LIMITS = RangeLimits(max_range_m=100.0, max_relative_speed_m_s=20.0, margin_m=0.2)


def test_a_steady_range_is_accepted_and_each_impossible_one_counted_by_reason():
    gate = RangeGate(LIMITS, vehicle_id=2)
    assert gate.accept(1, 4.0, 10.0)
    assert gate.accept(1, 4.1, 10.125)
    assert not gate.accept(1, -1.0, 10.25)
    assert not gate.accept(1, math.nan, 10.25)
    assert not gate.accept(1, math.inf, 10.25)
    assert not gate.accept(1, 150.0, 10.25)
    assert not gate.accept(1, 40.0, 10.25)  # 36 m in 0.125 s: 288 m/s
    assert gate.rejected == {"invalid": 3, "beyond_reach": 1, "jump": 1}
    assert gate.rejected_total == 5


def test_the_band_widens_with_time_since_the_last_accepted_range():
    gate = RangeGate(LIMITS)
    assert gate.accept(1, 4.0, 0.0)
    assert not gate.accept(1, 10.0, 0.125)  # 6 m > 20 m/s * 0.125 s + 0.2 m
    assert gate.accept(1, 10.0, 0.5)  # 6 m <= 20 m/s * 0.5 s + 0.2 m: it may really have moved
    assert gate.accept(0, 10.0, 0.125)  # pairs are independent (peer 0: the target)


def test_rejections_are_logged_rate_limited(caplog: pytest.LogCaptureFixture):
    gate = RangeGate(LIMITS, vehicle_id=3)
    gate.accept(1, 4.0, 0.0)
    with caplog.at_level(logging.WARNING, logger="mission_runner.runner.plausibility"):
        for k in range(1, 50):
            gate.accept(1, 40.0, k * 0.001)
    assert len(caplog.records) == 1
    assert "vehicle 3: range to vehicle 1 of 40.0 m rejected" in caplog.text


def test_limits_follow_the_scenario():
    scenario = load("paper_tracking_flyable")
    limits = range_limits(scenario)
    fastest = max(v.speed_limit_m_s for v in scenario.vehicles)
    assert limits.max_range_m == (scenario.sensors.range_max_m or DEFAULT_RADIO_REACH_M)
    assert limits.max_relative_speed_m_s == 2 * fastest
    data = scenario.model_dump(mode="json")
    data["sensors"]["range_noise_std_m"] = 0.05
    data["flight"]["range_check"] = {"max_range_m": 60.0}
    limits = range_limits(validate_scenario(data))
    assert limits.max_range_m == 60.0
    assert limits.margin_m == pytest.approx(0.2 + 6 * math.sqrt(2) * 0.05)


def stepping(north_m_s, east_m_s, vehicle_id=2):
    return StepMessage(
        vehicle_id, 7, 0.875, 0.0, 1.0, 2.0, command_north_m_s=north_m_s, command_east_m_s=east_m_s
    )


def test_a_command_faster_than_any_vehicle_may_fly_is_dropped_and_counted(
    caplog: pytest.LogCaptureFixture,
):
    gate = CommandGate(max_speed_m_s=5.0, vehicle_id=1)
    possible = stepping(3.0, 4.0)  # 5 m/s: at the limit
    assert gate.checked(possible) is possible
    without = StepMessage(2, 7, 0.875, 0.0, 1.0, 2.0)
    assert gate.checked(without) is without
    with caplog.at_level(logging.WARNING, logger="mission_runner.runner.plausibility"):
        checked = gate.checked(stepping(30.0, -40.0, vehicle_id=3))
    # The rest of the message stands: only the command is not believed.
    assert checked.command_m_s is None
    assert (checked.vehicle_id, checked.step, checked.odometry_east_m) == (3, 7, 2.0)
    assert gate.rejected == {"command_speed": 1}
    assert "vehicle 3's step 7 command of 50 m/s dropped" in caplog.text

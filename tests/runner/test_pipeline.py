"""The pure part of a controller's step: the decision, and each link of the command chain
alone (the controller's tests fly them together)."""

import math

import numpy as np
import pytest

from mission_runner.enclosing import VehicleCommand
from mission_runner.enclosing.target import LOST, OBSERVED, PREDICTED
from mission_runner.records import ControllerState
from mission_runner.runner.pipeline import (
    CommandShaper,
    SeparationSettings,
    StepCommand,
    StepDecision,
    altitude_hold_m_s,
    clamp_horizontal,
    decide,
    separated,
)

STEP_S = 0.125

# --- the decision --------------------------------------------------------------------------------


def decided(**changes):
    """The decision on a step with everything in order (fresh, in control, odometry, target
    observed, no hold), ``changes`` applied."""
    inputs = {
        "has_odometry": True,
        "stale_s": 0.1,
        "silence_timeout_s": 0.5,
        "in_control": True,
        "operator_hold": False,
        "target_status": OBSERVED,
        "target_on_lost": "hold",
    }
    return decide(**{**inputs, **changes})


FOLLOW = StepDecision(ControllerState.FOLLOWING, flies=True)
HOLD = StepDecision(ControllerState.HOLDING, flies=False)
HELD = StepDecision(ControllerState.HELD, flies=False)


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({}, FOLLOW),
        ({"target_status": PREDICTED}, FOLLOW),  # a hidden target predicted is still followed
        ({"stale_s": 0.5}, FOLLOW),  # the silence timeout itself is not over yet
        ({"stale_s": 0.51}, HOLD),
        ({"stale_s": math.inf}, HOLD),  # nothing ever heard
        ({"in_control": False}, HOLD),  # not seen armed in OFFBOARD
        ({"has_odometry": False}, HOLD),
        ({"operator_hold": True}, HELD),
        ({"operator_hold": True, "has_odometry": False}, HELD),
        # Holding for stale data or lost control is what the vehicle does, whatever the operator
        # asked: the status says so.
        ({"operator_hold": True, "stale_s": 1.0}, HOLD),
        ({"operator_hold": True, "in_control": False}, HOLD),
        ({"target_status": LOST}, StepDecision(ControllerState.TARGET_LOST, flies=False)),
        (
            {"target_status": LOST, "target_on_lost": "orbit"},
            StepDecision(ControllerState.TARGET_LOST, flies=True),
        ),
        ({"target_status": LOST, "has_odometry": False}, HOLD),
        ({"target_status": LOST, "operator_hold": True}, HELD),
    ],
)
def test_decide(changes, expected):
    assert decided(**changes) == expected


def test_the_decision_states_are_the_names_written_out():
    assert decided().state == "following"
    assert decided(stale_s=1.0).state == "holding"
    assert decided(operator_hold=True).state == "held"
    assert decided(target_status=LOST).state == "target_lost"


# --- lead ----------------------------------------------------------------------------------------


def shaper(**changes):
    settings = {
        "step_s": STEP_S,
        "lead_s": 0.25,
        "gain_1_s": 0.0,
        "integral_gain_1_s2": 0.0,
        "max_correction_m_s": 1.0,
    }
    return CommandShaper(**{**settings, **changes})


def test_lead_adds_the_commands_rate_times_the_lead():
    lead = shaper()
    # The first command has no rate to lead.
    np.testing.assert_array_equal(lead.lead([1.0, 0.5]), [1.0, 0.5])
    # (2, 0.5) after (1, 0.5) in 0.125 s: 8 m/s^2 north, led 0.25 s: +2 m/s.
    np.testing.assert_allclose(lead.lead([2.0, 0.5]), [4.0, 0.5])
    # The rate is from the command before, not from the led one.
    np.testing.assert_allclose(lead.lead([2.0, 0.0]), [2.0, -1.0])


def test_no_lead_passes_the_command_through():
    lead = shaper(lead_s=0.0)
    lead.lead([1.0, 0.0])
    np.testing.assert_array_equal(lead.lead([3.0, -1.0]), [3.0, -1.0])


def test_a_hold_leads_from_nothing():
    lead = shaper()
    lead.lead([1.0, 0.0])
    lead.hold()
    np.testing.assert_array_equal(lead.lead([3.0, 0.0]), [3.0, 0.0])


# --- displacement tracking -----------------------------------------------------------------------


def test_tracking_is_off_with_both_gains_zero():
    tracking = shaper()
    for _ in range(3):
        np.testing.assert_array_equal(tracking.tracking([1.0, 0.0], [0.0, 0.0]), [0.0, 0.0])
    assert tracking.reference_m is None


def test_tracking_pulls_towards_where_the_commands_would_have_taken_the_vehicle():
    tracking = shaper(gain_1_s=2.0)
    # The reference starts where the vehicle is: no correction yet; the command (1, 0) moves it
    # 0.125 m north.
    np.testing.assert_array_equal(tracking.tracking([1.0, 0.0], [3.0, 4.0]), [0.0, 0.0])
    np.testing.assert_allclose(tracking.reference_m, [3.125, 4.0])
    # The vehicle did not move: 0.125 m behind, gain 2/s: 0.25 m/s north.
    np.testing.assert_allclose(tracking.tracking([0.0, 0.0], [3.0, 4.0]), [0.25, 0.0])
    # 0.0625 m past the reference east: pulled back west.
    np.testing.assert_allclose(tracking.tracking([0.0, 0.0], [3.125, 4.0625]), [0.0, -0.125])


def test_tracking_correction_is_bounded_in_norm():
    tracking = shaper(gain_1_s=2.0, max_correction_m_s=0.1)
    tracking.tracking([0.0, 0.0], [0.0, 0.0])
    # 3 m north and 4 m east behind: 10 m/s wanted, 0.1 m/s given, same direction.
    np.testing.assert_allclose(tracking.tracking([0.0, 0.0], [-3.0, -4.0]), [0.06, 0.08])


def test_the_integral_stops_growing_while_the_correction_is_saturated():
    tracking = shaper(integral_gain_1_s2=4.0, max_correction_m_s=0.05)
    tracking.tracking([1.0, 0.0], [0.0, 0.0])  # the reference goes 0.125 m north
    # The error (0.125 m) integrates: 4 * 0.125 m * 0.125 s; the correction used is the integral
    # before this step's (0).
    np.testing.assert_array_equal(tracking.tracking([0.0, 0.0], [0.0, 0.0]), [0.0, 0.0])
    np.testing.assert_allclose(tracking.integral_m_s, [0.0625, 0.0])
    # Now 0.0625 m/s, over the 0.05 m/s bound: clamped, and the integral no longer grows.
    for _ in range(3):
        np.testing.assert_allclose(tracking.tracking([0.0, 0.0], [0.0, 0.0]), [0.05, 0.0])
        np.testing.assert_allclose(tracking.integral_m_s, [0.0625, 0.0])


def test_a_hold_restarts_tracking_and_a_skip_only_its_reference():
    skipped, held = shaper(integral_gain_1_s2=4.0), shaper(integral_gain_1_s2=4.0)
    for tracking in (skipped, held):
        tracking.lead([1.0, 0.0])
        tracking.tracking([1.0, 0.0], [0.0, 0.0])
        tracking.tracking([0.0, 0.0], [0.0, 0.0])
    skipped.skip()
    held.hold()
    assert skipped.reference_m is None and held.reference_m is None
    # The skip keeps what the integral learned and the command to lead from.
    np.testing.assert_allclose(skipped.tracking([0.0, 0.0], [5.0, 5.0]), [0.0625, 0.0])
    np.testing.assert_allclose(skipped.lead([1.0, 0.0]), [1.0, 0.0])
    np.testing.assert_allclose(skipped.lead([2.0, 0.0]), [4.0, 0.0])
    np.testing.assert_array_equal(held.tracking([0.0, 0.0], [5.0, 5.0]), [0.0, 0.0])
    np.testing.assert_array_equal(held.integral_m_s, [0.0, 0.0])


# --- separation ----------------------------------------------------------------------------------

SEPARATION = SeparationSettings(
    min_separation_m=2.0,
    gain_1_s=2.0,  # gamma = 0.25 at T = 0.125 s
    step_s=STEP_S,
    margin_m=0.0,
    braking_m_s2=None,
    latency_s=0.0,
    range_noise_std_m=0.0,
)


def law_command(velocity_m_s, estimates_m, bearing_std_rad=None):
    """The law's command with these estimates of p_i - p_j by peer id (0: the target)."""
    return VehicleCommand(
        velocity_m_s=np.asarray(velocity_m_s, dtype=float),
        consensus_m_s=np.zeros(2),
        estimates_m={peer: np.asarray(e, dtype=float) for peer, e in estimates_m.items()},
        neighbours_used=tuple(p for p in estimates_m if p != 0),
        bearing_std_rad=bearing_std_rad or {},
    )


def guarded(range_m, velocity=(-1.0, 0.0), *, bearing_std_rad=0.0, own=None, theirs=None):
    """The command ``velocity`` (by default heading north at 1 m/s) through the guard, vehicle 2
    ``range_m`` south of this one (p_i - p_j = (range_m, 0), its estimate agreeing with the
    range), its bearing that far off at most (None: not known)."""
    command = law_command(
        velocity,
        {0: [5.0, 5.0], 2: [range_m, 0.0]},
        None if bearing_std_rad is None else {2: bearing_std_rad},
    )
    return separated(
        np.asarray(velocity, dtype=float),
        command,
        {2: range_m},
        own_in_force_m_s=own,
        in_force_m_s=theirs or {},
        settings=SEPARATION,
    )


def test_separation_leaves_a_command_alone_far_from_everyone():
    np.testing.assert_array_equal(guarded(10.0), [-1.0, 0.0])


def test_separation_bounds_the_closing_speed_by_the_clearance():
    # 0.5 m of clearance: the pair may close gamma 0.5 m / T = 1 m/s, this vehicle half of it.
    np.testing.assert_allclose(guarded(2.5), [-0.5, 0.0])
    # Moving across the line closes nothing: left alone.
    np.testing.assert_array_equal(guarded(2.5, (0.0, -1.0)), [0.0, -1.0])


def test_separation_at_the_minimum_turns_right_instead_of_closing():
    # Heading north at the minimum distance: no closing left; part of it is given back to the
    # right (west), which closes nothing.
    np.testing.assert_allclose(guarded(2.0), [0.0, -0.5], atol=1e-12)


def test_separation_shares_the_closing_around_the_commands_in_force():
    # Vehicle 2 comes north at 1 m/s: it takes the pair's whole allowance, this one may not close.
    np.testing.assert_allclose(guarded(2.5, theirs={2: (1.0, 0.0)}), [0.0, 0.0], atol=1e-12)
    # It goes south at 1 m/s, or this one already flies north at 1 m/s: 1 m/s closing is fine.
    np.testing.assert_allclose(guarded(2.5, theirs={2: (-1.0, 0.0)}), [-1.0, 0.0])
    np.testing.assert_allclose(guarded(2.5, own=(-1.0, 0.0)), [-1.0, 0.0])
    # Not known (None, or no message): as if standing still.
    np.testing.assert_allclose(guarded(2.5, theirs={2: None}), [-0.5, 0.0])


def test_separation_without_a_trusted_bearing_caps_the_speed_in_every_direction():
    # No bearing spread known: no direction to trust; the vehicle keeps below half the allowed
    # closing speed (1 m/s at 0.5 m clearance) whichever way it flies, and stops at the minimum.
    np.testing.assert_allclose(guarded(2.5, (0.0, -1.0), bearing_std_rad=None), [0.0, -0.5])
    np.testing.assert_allclose(guarded(2.0, bearing_std_rad=None), [0.0, 0.0], atol=1e-12)


def test_separation_without_neighbours_returns_the_command():
    velocity = np.array([-1.0, 0.0])
    only_target = law_command(velocity, {0: [0.5, 0.0]})
    kept = separated(
        velocity, only_target, {}, own_in_force_m_s=None, in_force_m_s={}, settings=SEPARATION
    )
    assert kept is velocity


# --- clamp and altitude --------------------------------------------------------------------------


def test_clamp_scales_the_horizontal_speed_down_keeping_its_direction():
    assert clamp_horizontal(np.array([3.0, -4.0]), 2.5) == pytest.approx((1.5, -2.0))
    assert clamp_horizontal(np.array([1.0, -2.0]), 2.5) == (1.0, -2.0)
    assert all(type(v) is float for v in clamp_horizontal(np.array([1.0, 2.0]), 5.0))


def test_altitude_hold_climbs_to_the_altitude_within_the_vertical_limit():
    hold = {"altitude_m": 5.0, "gain_1_s": 1.0, "limit_m_s": 1.0}
    assert altitude_hold_m_s(-4.5, **hold) == pytest.approx(-0.5)  # 0.5 m low: up (NED)
    assert altitude_hold_m_s(-5.25, **hold) == pytest.approx(0.25)  # 0.25 m high: down
    assert altitude_hold_m_s(0.0, **hold) == -1.0  # on the ground: the limit
    assert altitude_hold_m_s(-5.5, altitude_m=5.0, gain_1_s=4.0, limit_m_s=1.0) == 1.0
    assert altitude_hold_m_s(None, **hold) == 0.0  # no odometry: no vertical command


def test_a_hold_commands_nothing_and_records_nothing_of_the_law():
    hold = StepCommand()
    assert hold.velocity_m_s == (0.0, 0.0) and hold.consensus_m_s == (0.0, 0.0)
    assert hold.neighbours_used == () and hold.gated == ()
    assert hold.estimates_m == {} and hold.ranges_m == {}
    assert StepCommand().ranges_m is not hold.ranges_m  # each hold's record its own

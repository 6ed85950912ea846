"""The separation guard: the smallest change to a command that keeps the barrier condition."""

import numpy as np
import pytest

from mission_runner.enclosing.separation import separation_guard

GAIN = 4.0
D_MIN = 1.0


def guard(command, relative, distance, own=None, other=None, **kwargs):
    return separation_guard(
        np.asarray(command, dtype=float),
        np.asarray(relative, dtype=float),
        np.asarray(distance, dtype=float),
        None if own is None else np.asarray(own, dtype=float),
        None if other is None else np.asarray(other, dtype=float),
        min_separation_m=D_MIN,
        gain_1_s=GAIN,
        **kwargs,
    )


def test_a_neighbour_far_away_changes_nothing():
    command = np.array([3.0, -1.0])
    assert np.array_equal(guard(command, [[-10.0, 0.0]], [10.0]), command)


def test_closing_head_on_is_slowed_to_the_allowed_closing_speed():
    # The neighbour is 1.2 m north (p_i - p_j points south); we fly north at 5 m/s, both still.
    out = guard([5.0, 0.0], [[-1.2, 0.0]], [1.2], own=[0.0, 0.0], other=[[0.0, 0.0]])
    # n = (-1, 0): n.u >= -gain * (1.2 - 1.0) / 2 = -0.4  ->  u_north <= 0.4, east untouched.
    assert out == pytest.approx([0.4, 0.0])


def test_closer_than_the_minimum_the_guard_pushes_apart():
    out = guard([0.0, 0.0], [[-0.8, 0.0]], [0.8], own=[0.0, 0.0], other=[[0.0, 0.0]])
    assert out[0] == pytest.approx(-0.5 * GAIN * 0.2)  # moves south, away from it
    assert out[1] == pytest.approx(0.0)


def test_a_pair_turning_rigidly_is_left_alone():
    # Both fly east at 6 m/s side by side 1.3 m apart: no distance closes.
    out = guard([6.0, 0.0], [[0.0, -1.3]], [1.3], own=[6.0, 0.0], other=[[6.0, 0.0]])
    assert out == pytest.approx([6.0, 0.0])


def test_two_binding_neighbours_give_the_exact_projection():
    # Neighbours 1.1 m north and 1.1 m east; the command heads north-east at 2 m/s.
    out = guard(
        [2.0, 2.0],
        [[-1.1, 0.0], [0.0, -1.1]],
        [1.1, 1.1],
        own=[0.0, 0.0],
        other=[[0.0, 0.0], [0.0, 0.0]],
    )
    # Two half-planes u_n <= 0.2 and u_e <= 0.2: the closest point is their corner.
    assert out == pytest.approx([0.2, 0.2], abs=1e-9)


def test_an_estimate_that_disagrees_with_the_range_gives_no_direction_and_the_vehicle_brakes():
    # The estimator still says 5 m; the radio says 1.3 m: no direction to project on.
    out = guard([3.0, 4.0], [[-5.0, 0.0]], [1.3], own=[0.0, 0.0], other=[[0.0, 0.0]])
    assert np.hypot(*out) == pytest.approx(0.5 * GAIN * 0.3)
    assert out[1] / out[0] == pytest.approx(4.0 / 3.0)  # the direction is kept


def test_unknown_neighbours_and_missing_ranges_are_skipped_or_use_the_estimate():
    nan = np.nan
    out = guard([5.0, 0.0], [[nan, nan], [-1.2, 0.0]], [nan, nan])
    assert out == pytest.approx([0.4, 0.0])  # the second one, at the estimate's length


def test_batched_calls_equal_one_call_per_vehicle():
    rng = np.random.default_rng(3)
    commands = rng.normal(scale=3.0, size=(5, 4, 2))
    relative = rng.normal(scale=1.5, size=(5, 4, 3, 2))
    distance = np.linalg.norm(relative, axis=-1) * rng.uniform(0.9, 1.1, size=(5, 4, 3))
    own = rng.normal(size=(5, 4, 2))
    others = rng.normal(size=(5, 4, 3, 2))
    batched = guard(commands, relative, distance, own, others)
    for b in range(5):
        for i in range(4):
            single = guard(commands[b, i], relative[b, i], distance[b, i], own[b, i], others[b, i])
            assert batched[b, i] == pytest.approx(single)

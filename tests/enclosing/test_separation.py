"""The separation guard: the smallest change to a command that keeps the barrier condition."""

import numpy as np
import pytest

from mission_runner.enclosing import separation
from mission_runner.enclosing.separation import allowed_closing_m_s, separation_guard

GAIN = 4.0
STEP = 0.125  # gamma = GAIN * STEP = 0.5
D_MIN = 1.0


def guard(command, relative, distance, own=None, other=None, **kwargs):
    settings = {"min_separation_m": D_MIN, "gain_1_s": GAIN, "step_s": STEP} | kwargs
    return separation_guard(
        np.asarray(command, dtype=float),
        np.asarray(relative, dtype=float),
        np.asarray(distance, dtype=float),
        None if own is None else np.asarray(own, dtype=float),
        None if other is None else np.asarray(other, dtype=float),
        **settings,
    )


def fly_pair(start, laws, steps, **kwargs):
    """Two vehicles, each running the guard on exact relative positions and ranges and the
    other's command in force, moving p += T u. ``laws(k, positions)`` gives the commands
    ``(2, 2)``. Returns the positions ``(steps + 1, 2, 2)``."""
    positions = [np.asarray(start, dtype=float)]
    in_force = np.full((2, 2), np.nan)
    for k in range(steps):
        p = positions[-1]
        law = laws(k, p)
        out = np.empty((2, 2))
        for i, j in ((0, 1), (1, 0)):
            relative = p[i] - p[j]
            out[i] = guard(
                law[i], [relative], [np.hypot(*relative)], in_force[i], [in_force[j]], **kwargs
            )
        in_force = out
        positions.append(p + STEP * out)
    return np.array(positions)


def gap(positions):
    return np.linalg.norm(positions[:, 0] - positions[:, 1], axis=-1)


def test_a_neighbour_far_away_changes_nothing():
    command = np.array([3.0, -1.0])
    assert np.array_equal(guard(command, [[-10.0, 0.0]], [10.0]), command)


def test_closing_head_on_is_slowed_to_half_the_pairs_allowed_closing_speed():
    # The neighbour is 1.5 m north (p_i - p_j points south); we fly north at 5 m/s, both still.
    out = guard([5.0, 0.0], [[-1.5, 0.0]], [1.5], own=[0.0, 0.0], other=[[0.0, 0.0]])
    # w = gamma h / T = 0.5 * 0.5 / 0.125 = 2 m/s for the pair, 1 m/s each.
    assert out == pytest.approx([1.0, 0.0])


def test_closer_than_the_minimum_the_guard_pushes_apart():
    out = guard([0.0, 0.0], [[-0.8, 0.0]], [0.8], own=[0.0, 0.0], other=[[0.0, 0.0]])
    assert out[0] == pytest.approx(-0.5 * GAIN * 0.2)  # moves south, away from it
    assert out[1] == pytest.approx(0.0)


def test_a_pair_turning_rigidly_is_left_alone():
    # Both fly east at 6 m/s side by side 1.3 m apart: no distance closes.
    out = guard([6.0, 0.0], [[0.0, -1.3]], [1.3], own=[6.0, 0.0], other=[[6.0, 0.0]])
    assert out == pytest.approx([6.0, 0.0])


def test_two_binding_neighbours_give_the_exact_projection():
    # Neighbours 1.3 m north and 1.3 m east; the command heads north-east at 2 m/s.
    out = guard(
        [2.0, 2.0],
        [[-1.3, 0.0], [0.0, -1.3]],
        [1.3, 1.3],
        own=[0.0, 0.0],
        other=[[0.0, 0.0], [0.0, 0.0]],
    )
    # Two half-planes u_n <= 0.6 and u_e <= 0.6: the closest point is their corner.
    assert out == pytest.approx([0.6, 0.6], abs=1e-9)


def test_the_neighbours_command_in_force_sets_how_much_of_the_budget_is_ours():
    # In tandem, 1.5 m behind a neighbour (w = 2 m/s for the pair); we fly north at 1 m/s and
    # the law wants 6. The reference is half the pair's commands in force along the line.
    def follow(neighbour):
        return guard([6.0, 0.0], [[-1.5, 0.0]], [1.5], own=[1.0, 0.0], other=[neighbour])

    assert follow([1.0, 0.0]) == pytest.approx([2.0, 0.0])  # flies away with us: all of w
    assert follow([0.0, 0.0]) == pytest.approx([1.5, 0.0])  # hovers
    assert follow([np.nan, np.nan]) == pytest.approx([1.5, 0.0])  # unknown: as if hovering
    assert follow([-1.0, 0.0]) == pytest.approx([1.0, 0.0])  # comes at us: half of w


def test_a_pair_using_the_same_commands_in_force_closes_no_faster_than_allowed():
    rng = np.random.default_rng(11)
    for _ in range(200):
        relative = rng.normal(size=2) * 2.0
        distance = np.hypot(*relative)
        if distance < D_MIN:
            continue
        laws, in_force = rng.normal(scale=4.0, size=(2, 2)), rng.normal(scale=4.0, size=(2, 2))
        u_i = guard(laws[0], [relative], [distance], in_force[0], [in_force[1]])
        u_j = guard(laws[1], [-relative], [distance], in_force[1], [in_force[0]])
        closing = -np.dot(relative / distance, u_i - u_j)
        allowed = allowed_closing_m_s(np.array(distance - D_MIN), step_s=STEP, gain_1_s=GAIN)
        assert closing <= allowed + 1e-9


def test_disagreeing_references_still_keep_the_minimum_after_the_step():
    # A lost step message: one side counts the other's command as zero. The clip bounds what
    # that costs (at most twice the allowed closing), which at gamma = 1/2 still lands >= d_min.
    rng = np.random.default_rng(12)
    for _ in range(200):
        relative = rng.normal(size=2) * 2.0
        distance = np.hypot(*relative)
        if distance < D_MIN:
            continue
        laws, in_force = rng.normal(scale=6.0, size=(2, 2)), rng.normal(scale=6.0, size=(2, 2))
        u_i = guard(laws[0], [relative], [distance], in_force[0], [in_force[1]])
        u_j = guard(laws[1], [-relative], [distance], in_force[1], [[np.nan, np.nan]])
        assert np.hypot(*(relative + STEP * (u_i - u_j))) >= D_MIN - 1e-9


def test_the_condition_is_on_the_next_step_so_a_high_gain_cannot_overshoot():
    # gain T = 2.5: a continuous-time condition would let the pair close 2.5 h in one step and
    # land 0.75 m apart. Discrete time caps gamma at 1: they land exactly at d_min.
    positions = fly_pair(
        [[0.0, 0.0], [1.5, 0.0]],
        lambda k, p: np.array([[10.0, 0.0], [-10.0, 0.0]]),
        steps=5,
        gain_1_s=20.0,
    )
    assert gap(positions).min() >= D_MIN - 1e-12
    assert gap(positions)[1] == pytest.approx(D_MIN)


def test_braking_limits_the_closing_speed_to_what_can_still_stop():
    # h = 2 m, braking 1 m/s^2 each: the pair may close at 2 sqrt(1 * 2) = 2.83 m/s, not 8.
    out = guard([10.0, 0.0], [[-3.0, 0.0]], [3.0], [0.0, 0.0], [[0.0, 0.0]], braking_m_s2=1.0)
    assert out[0] == pytest.approx(np.sqrt(2.0))


def test_latency_counts_what_the_commands_in_force_still_close():
    # Commands in force close the pair at 4 m/s for another 0.25 s: 1 m of the 2 m clearance is
    # gone before the new command acts, so w = 0.5 * 1 / 0.125 = 4 m/s, half of it ours
    # around a reference of zero (the pair's commands cancel along n).
    out = guard([10.0, 0.0], [[-3.0, 0.0]], [3.0], [2.0, 0.0], [[-2.0, 0.0]], latency_s=0.25)
    assert out[0] == pytest.approx(2.0)


def test_two_vehicles_head_on_slide_past_each_other_instead_of_locking():
    def swap(k, p):  # each heads for the other's start at up to 3 m/s
        goals = np.array([[4.0, 0.0], [0.0, 0.0]])
        return separation._capped(goals - p, np.array([3.0, 3.0]))

    start = [[0.0, 0.0], [4.0, 0.0]]
    passed = fly_pair(start, swap, steps=120)
    assert gap(passed).min() >= D_MIN - 1e-9
    assert np.allclose(passed[-1], [[4.0, 0.0], [0.0, 0.0]], atol=0.05)
    # Each turned to its own right (the first heads north, so east; the second south, so west).
    assert passed[:, 0, 1].max() > 0.1 and passed[:, 1, 1].min() < -0.1

    original = separation.TURN_FRACTION
    try:
        separation.TURN_FRACTION = 0.0
        locked = fly_pair(start, swap, steps=120)
    finally:
        separation.TURN_FRACTION = original
    assert gap(locked).min() >= D_MIN - 1e-9
    assert np.abs(locked[-1, 0, 0] - 1.5) < 0.1  # stuck half a minimum separation off centre


def test_the_result_meets_every_condition_zero_meets_even_when_many_bind():
    rng = np.random.default_rng(5)
    for _ in range(100):
        relative = rng.normal(size=(6, 2)) * 1.5
        distance = np.linalg.norm(relative, axis=-1)
        keep = distance > D_MIN
        relative, distance = relative[keep], distance[keep]
        in_force = rng.normal(scale=3.0, size=(len(distance), 2))
        own = rng.normal(scale=3.0, size=2)
        out = guard(rng.normal(scale=8.0, size=2), relative, distance, own, in_force)
        normal = relative / distance[:, None]
        clearance = distance - D_MIN
        half = 0.5 * allowed_closing_m_s(clearance, step_s=STEP, gain_1_s=GAIN)
        reference = np.clip(0.5 * normal @ own + 0.5 * np.sum(normal * in_force, -1), -half, half)
        assert np.all(normal @ out >= reference - half - 1e-9)
        # A speed limit after it (scaling towards zero) keeps it inside.
        assert np.all(normal @ (0.3 * out) >= reference - half - 1e-9)


def test_an_estimate_that_disagrees_with_the_range_gives_no_direction_and_the_vehicle_brakes():
    # The estimator still says 5 m; the radio says 1.3 m: no direction to project on.
    out = guard([3.0, 4.0], [[-5.0, 0.0]], [1.3], own=[0.0, 0.0], other=[[0.0, 0.0]])
    assert np.hypot(*out) == pytest.approx(0.5 * GAIN * 0.3)
    assert out[1] / out[0] == pytest.approx(4.0 / 3.0)  # the direction is kept


def test_braking_for_a_blind_neighbour_holds_after_the_others_push():
    # A trusted neighbour pushes us south (we are inside its minimum separation); a blind one
    # 1.1 m away allows 0.2 m/s whichever way: the push may not exceed it.
    out = guard(
        [0.0, 0.0],
        [[-0.8, 0.0], [3.0, 3.0]],
        [0.8, 1.1],
        own=[0.0, 0.0],
        other=[[0.0, 0.0], [0.0, 0.0]],
    )
    assert np.hypot(*out) <= 0.2 + 1e-9


def test_unknown_neighbours_and_missing_ranges_are_skipped_or_use_the_estimate():
    nan = np.nan
    out = guard([5.0, 0.0], [[nan, nan], [-1.5, 0.0]], [nan, nan])
    assert out == pytest.approx([1.0, 0.0])  # the second one, at the estimate's length


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


def test_range_noise_sets_the_default_margin_and_an_explicit_one_is_kept():
    # 1.5 m measured, both still, heading at the neighbour at 5 m/s. 5 cm noise: 1.15 m kept,
    # w = 0.5 * 0.35 / 0.125 = 1.4 m/s, 0.7 each; an explicit 0.3 m margin at 2 m: 1.3 m kept,
    # w = 0.5 * 0.7 / 0.125 = 2.8 m/s, 1.4 each.
    ahead = {"own": [0.0, 0.0], "other": [[0.0, 0.0]], "range_noise_std_m": 0.05}
    assert guard([5.0, 0.0], [[-1.5, 0.0]], [1.5], **ahead) == pytest.approx([0.7, 0.0])
    explicit = guard([5.0, 0.0], [[-2.0, 0.0]], [2.0], margin_m=0.3, **ahead)
    assert explicit == pytest.approx([1.4, 0.0])


def test_a_direction_is_trusted_only_within_how_far_its_bearing_may_be_off():
    # The estimate puts the neighbour due north, 1.5 m, but its bearing may be 0.6 rad (34
    # degrees) off either way (CONE_SIGMAS bearing stds). Flying 34 degrees east of north,
    # straight at where the neighbour may truly be, the guard must slow the approach along that
    # line to half the pair's allowed closing speed; taking the estimate as exact it lets 5 m/s
    # through across it.
    heading = np.array([np.cos(0.6), np.sin(0.6)])
    settings = {"own": [0.0, 0.0], "other": [[0.0, 0.0]], "range_noise_std_m": 0.05}
    std = [0.6 / separation.CONE_SIGMAS]
    out = guard(5.0 * heading, [[-1.5, 0.0]], [1.5], bearing_std_rad=std, **settings)
    half = 0.5 * allowed_closing_m_s(np.array(1.5 - 1.15), step_s=STEP, gain_1_s=GAIN)
    for angle in np.linspace(-0.6, 0.6, 13):  # every direction of the cone
        assert np.array([np.cos(angle), np.sin(angle)]) @ out <= half + 1e-9
    # A bearing that may be off by more than MAX_CONE_RAD gives no direction: the vehicle brakes
    # to that speed; one not known at all (NaN) likewise.
    for unknown in (1.1 * separation.MAX_CONE_RAD / separation.CONE_SIGMAS, np.nan):
        wide = guard(5.0 * heading, [[-1.5, 0.0]], [1.5], bearing_std_rad=[unknown], **settings)
        assert np.hypot(*wide) == pytest.approx(float(half))

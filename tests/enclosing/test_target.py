"""The target track: observed, predicted at constant velocity, lost after target_lost_after_s."""

import math

import numpy as np

from mission_runner.enclosing import LOST, OBSERVED, PREDICTED, TargetTrack, track_target

T = 0.125
VELOCITY = np.array([0.8, -0.3])


def follow(observed, *, lost_after_s=1.0, own=None, shape=()):
    """Step a track through ``observed`` (per step: True = seen at that step by someone, with
    the target's true displacement ``VELOCITY * k T`` when ``own`` says this vehicle saw it)."""
    track = TargetTrack.initial(shape)
    out = []
    for k, seen in enumerate(observed):
        mine = seen and (own is None or own[k])
        track, estimate = track_target(
            track,
            k,
            velocity_m_s=VELOCITY if seen else (math.nan, math.nan),
            observed_step=k if seen else math.nan,
            own_odometry_m=VELOCITY * k * T + 5.0 if mine else (math.nan, math.nan),
            step_s=T,
            lost_after_s=lost_after_s,
        )
        out.append(estimate)
    return out


def test_a_constant_velocity_target_is_predicted_exactly_through_an_occlusion():
    # Hidden for 6 steps (within 1 s): the odometry goes on as if observed, the feed-forward too.
    observed = [True] * 5 + [False] * 6 + [True] * 5
    estimates = follow(observed)
    status = [int(e.status) for e in estimates]
    assert status == [OBSERVED] * 5 + [PREDICTED] * 6 + [OBSERVED] * 5
    for k, estimate in enumerate(estimates):
        np.testing.assert_allclose(estimate.odometry_m, VELOCITY * k * T, atol=1e-12)
        np.testing.assert_allclose(estimate.velocity_m_s, VELOCITY)
    assert [float(e.age_s) for e in estimates[4:12]] == [0.0, *(T * a for a in range(1, 7)), 0.0]


def test_the_target_is_lost_once_unseen_for_longer_than_lost_after_s_and_back_when_seen():
    observed = [True] * 3 + [False] * 12 + [True] * 2
    estimates = follow(observed, lost_after_s=1.0)  # 8 steps of 0.125 s
    status = [int(e.status) for e in estimates]
    # Last seen at step 2: predicted while the age is <= 1 s (steps 3..10), lost from step 11.
    assert status == [OBSERVED] * 3 + [PREDICTED] * 8 + [LOST] * 4 + [OBSERVED] * 2
    for estimate in estimates[11:15]:
        np.testing.assert_array_equal(estimate.velocity_m_s, [0.0, 0.0])  # orbit, not follow
    # Once lost the estimate stops where the prediction was (one step after the last predicted).
    frozen = estimates[11].odometry_m
    for estimate in estimates[11:16]:
        np.testing.assert_array_equal(estimate.odometry_m, frozen)
    np.testing.assert_allclose(frozen, VELOCITY * 11 * T, atol=1e-12)


def test_a_target_never_seen_is_lost_after_lost_after_s_from_the_start():
    estimates = follow([False] * 10, lost_after_s=0.5)
    assert [int(e.status) for e in estimates] == [PREDICTED] * 5 + [LOST] * 5
    for estimate in estimates:
        np.testing.assert_array_equal(estimate.velocity_m_s, [0.0, 0.0])


def test_the_own_observed_odometry_joins_the_track_without_a_jump():
    # Relayed first (no own odometry: integrated), then observed by this vehicle in its own frame
    # (origin 5 m away): the track goes on where it was and follows the own displacements.
    observed = [True] * 10
    own = [False] * 4 + [True] * 6
    estimates = follow(observed, own=own)
    for k, estimate in enumerate(estimates):
        np.testing.assert_allclose(estimate.odometry_m, VELOCITY * k * T, atol=1e-12)


def test_an_older_observation_never_replaces_a_fresher_one():
    track = TargetTrack.initial()
    track, _ = track_target(
        track,
        0,
        velocity_m_s=(1.0, 0.0),
        observed_step=0,
        own_odometry_m=(math.nan, math.nan),
        step_s=T,
        lost_after_s=1.0,
    )
    track, estimate = track_target(
        track,
        1,
        velocity_m_s=(9.0, 9.0),
        observed_step=-1,  # a stale relay
        own_odometry_m=(math.nan, math.nan),
        step_s=T,
        lost_after_s=1.0,
    )
    assert int(estimate.status) == PREDICTED
    np.testing.assert_array_equal(estimate.velocity_m_s, [1.0, 0.0])


def test_batched_tracks_step_independently():
    # Two runs: one sees the target throughout, the other loses it after step 0.
    track = TargetTrack.initial((2,))
    for k in range(12):
        seen = np.array([True, k == 0])
        track, estimate = track_target(
            track,
            k,
            velocity_m_s=np.where(seen[:, None], VELOCITY, np.nan),
            observed_step=np.where(seen, float(k), np.nan),
            own_odometry_m=np.full((2, 2), np.nan),
            step_s=T,
            lost_after_s=1.0,
        )
    assert estimate.status.tolist() == [OBSERVED, LOST]

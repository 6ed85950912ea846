import pytest

from mission_runner.runner.odometry import OdometrySample, OdometryTrack


def track(*samples):
    result = OdometryTrack(capacity=8)
    for sample in samples:
        result.add(OdometrySample(*sample))
    return result


def test_interpolates_between_the_samples_that_bracket_the_instant():
    odometry = track((0.00, 0.0, 0.0, -5.0), (0.02, 0.2, -0.1, -5.0))
    assert odometry.at(0.005) == pytest.approx((0.05, -0.025, -5.0))
    assert odometry.at(0.02) == (0.2, -0.1, -5.0)


def test_no_value_outside_the_samples():
    odometry = track((0.0, 0.0, 0.0, 0.0), (0.02, 1.0, 0.0, 0.0))
    assert odometry.at(-0.001) is None
    assert odometry.at(0.021) is None  # not yet: the controller waits for the next sample


def test_old_and_repeated_samples_are_ignored():
    odometry = track((0.0, 0.0, 0.0, 0.0), (0.02, 1.0, 0.0, 0.0))
    assert not odometry.add(OdometrySample(0.01, 9.0, 9.0, 9.0))
    assert not odometry.add(OdometrySample(0.02, 9.0, 9.0, 9.0))
    assert odometry.latest.north_m == 1.0


def test_capacity_bounds_memory():
    odometry = track(*[(0.01 * i, i, 0, 0) for i in range(20)])
    assert odometry.at(0.05) is None  # dropped
    assert odometry.at(0.185) == pytest.approx((18.5, 0, 0))


def test_just_past_the_newest_sample_it_is_extrapolated_at_that_samples_velocity():
    """The controller takes t_k from the newest sample at its velocity instead of waiting up to
    a telemetry period for the next one; only that close, and only with a velocity."""
    odometry = track(
        (0.00, 0.0, 0.0, -5.0, 2.0, -1.0, 0.0), (0.02, 0.04, -0.02, -5.0, 2.0, -1.0, 0.5)
    )
    assert odometry.at(0.03) is None  # not asked to
    assert odometry.at(0.03, extrapolate_s=0.03) == pytest.approx((0.06, -0.03, -4.995))
    assert odometry.at(0.051, extrapolate_s=0.03) is None  # too far past the newest
    assert odometry.at(0.01, extrapolate_s=0.03) == pytest.approx((0.02, -0.01, -5.0))
    no_velocity = track((0.00, 0.0, 0.0, 0.0), (0.02, 1.0, 0.0, 0.0))
    assert no_velocity.at(0.021, extrapolate_s=0.03) is None

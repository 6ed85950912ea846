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

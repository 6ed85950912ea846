import threading

import pytest

from mission_runner.runner.odometry import FedTrack, OdometrySample, OdometryTrack


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


def test_a_fed_track_files_what_another_thread_handed_over_when_read():
    odometry = FedTrack(capacity=8)
    fed = []
    odometry.on_feed = lambda: fed.append(threading.get_ident())
    feeder = threading.Thread(
        target=lambda: [
            odometry.feed(OdometrySample(n * 0.02, float(n), 0.0, 0.0)) for n in range(5)
        ]
    )
    feeder.start()
    feeder.join()
    assert fed == [feeder.ident] * 5  # called in the feeding thread, once a sample
    assert odometry.fed
    assert odometry.at(0.05) == pytest.approx((2.5, 0.0, 0.0))
    assert not odometry.fed
    assert odometry.latest.north_m == 4.0


def test_a_fed_track_nobody_reads_keeps_only_the_newest():
    odometry = FedTrack(capacity=8)
    for n in range(1000):
        odometry.feed(OdometrySample(n * 0.02, float(n), 0.0, 0.0))
    assert odometry.latest.north_m == 999.0
    assert odometry.at(991 * 0.02) is None  # older than the 8 kept
    assert odometry.at(992 * 0.02) == (992.0, 0.0, 0.0)


def test_a_fed_track_still_ignores_old_samples_in_any_order_of_feed_and_add():
    odometry = FedTrack(capacity=8)
    odometry.feed(OdometrySample(0.04, 4.0, 0.0, 0.0))
    assert not odometry.add(OdometrySample(0.02, 2.0, 0.0, 0.0))  # the fed one is newer
    odometry.feed(OdometrySample(0.03, 3.0, 0.0, 0.0))
    assert odometry.latest.north_m == 4.0

"""The autopilot clock mapping: rate and offset from SYSTEM_TIME pairs, as PX4 SITL's clock
behaves (a boot clock at 0.986x or 1.93x the host's), with quantisation, outliers and jumps."""

import math
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mission_runner.runner.timesync import (
    ClockFollower,
    ClockMapping,
    ClockMappingError,
    FedClockMapping,
    MissionTime,
)

UNIX_AT_BOOT = 1_764_000_000.0


def pairs(boot_rate, seconds, *, every_s=1.0, boot_offset_s=37.2, jitter_s=0.0, seed=0):
    """SYSTEM_TIME pairs of an autopilot whose boot clock runs ``boot_rate`` boot seconds per
    UNIX second, with time_boot_ms quantised to the millisecond like the message."""
    rng = np.random.default_rng(seed)
    out = []
    for unix in np.arange(0.0, seconds, every_s):
        unix_s = UNIX_AT_BOOT + unix + (rng.normal(scale=jitter_s) if jitter_s else 0.0)
        boot_s = math.floor((boot_offset_s + boot_rate * unix) * 1000.0) / 1000.0
        out.append((boot_s, unix_s))
    return out


@pytest.mark.parametrize("boot_rate", [0.986, 1.0, 1.93, 5.0])
def test_the_fit_follows_a_boot_clock_far_from_wall_speed(boot_rate):
    mapping = ClockMapping()
    for boot_s, unix_s in pairs(boot_rate, 30.0):
        assert mapping.add(boot_s, unix_s)
    assert mapping.fit.boot_rate == pytest.approx(boot_rate, rel=1e-4)
    # A sample half a second after the last pair maps to within a millisecond.
    boot_s = 37.2 + boot_rate * 29.5
    assert mapping.unix_s(boot_s) == pytest.approx(UNIX_AT_BOOT + 29.5, abs=1e-3)
    assert mapping.boot_s(mapping.unix_s(boot_s)) == pytest.approx(boot_s, abs=1e-9)


def test_an_offset_estimated_once_drifts_where_the_fit_does_not():
    """The failure seen on PX4 SIH: 14 ms per second of drift with a one-time offset."""
    history = pairs(0.986, 60.0)
    once = ClockMapping(window_s=1e-3)  # keeps one pair: what a one-time offset does
    once.add(*history[0])
    fitted = ClockMapping()
    for boot_s, unix_s in history:
        fitted.add(boot_s, unix_s)
    boot_s = 37.2 + 0.986 * 59.0
    truth = UNIX_AT_BOOT + 59.0
    assert abs(once.unix_s(boot_s) - truth) > 0.5  # ~0.8 s off after a minute
    assert fitted.unix_s(boot_s) == pytest.approx(truth, abs=1e-3)


def test_a_lone_outlier_is_rejected_and_counted():
    mapping = ClockMapping()
    history = pairs(1.0, 20.0)
    for boot_s, unix_s in history[:10]:
        mapping.add(boot_s, unix_s)
    rate = mapping.fit.rate
    assert not mapping.add(history[10][0], history[10][1] + 5.0)
    assert mapping.rejected == 1
    for boot_s, unix_s in history[11:]:
        assert mapping.add(boot_s, unix_s)
    assert mapping.fit.rate == pytest.approx(rate, rel=1e-6)
    assert mapping.refits == 0


def test_a_stepped_unix_clock_is_followed_after_three_pairs():
    mapping = ClockMapping()
    history = pairs(1.0, 30.0)
    for boot_s, unix_s in history[:10]:
        mapping.add(boot_s, unix_s)
    stepped = [(boot_s, unix_s + 3600.0) for boot_s, unix_s in history[10:]]
    assert not mapping.add(*stepped[0])
    assert not mapping.add(*stepped[1])
    assert mapping.add(*stepped[2])
    assert mapping.refits == 1
    assert mapping.unix_s(stepped[2][0]) == pytest.approx(stepped[2][1], abs=1e-3)


def test_a_reboot_restarts_the_fit():
    mapping = ClockMapping()
    for boot_s, unix_s in pairs(1.0, 40.0):
        mapping.add(boot_s, unix_s)
    assert mapping.add(0.5, UNIX_AT_BOOT + 100.0)  # boot clock back near zero
    assert mapping.unix_s(0.5) == pytest.approx(UNIX_AT_BOOT + 100.0)


def test_impossible_pairs_are_rejected():
    mapping = ClockMapping()
    for bad in [(math.nan, 1.0), (1.0, math.inf), (-1.0, UNIX_AT_BOOT), (1.0, 0.0)]:
        assert not mapping.add(*bad)
    assert mapping.rejected == 4
    with pytest.raises(ClockMappingError, match="no SYSTEM_TIME pair"):
        mapping.unix_s(1.0)


def test_before_the_pairs_span_enough_the_rate_is_nominal():
    mapping = ClockMapping(nominal_rate=1.0)
    mapping.add(10.0, UNIX_AT_BOOT)
    mapping.add(10.5, UNIX_AT_BOOT + 0.55)  # 0.5 s apart: too short to trust a rate
    assert mapping.fit.rate == 1.0


@settings(max_examples=50, deadline=None)
@given(
    boot_rate=st.floats(0.2, 10.0),
    jitter_s=st.floats(0.0, 0.005),
    seed=st.integers(0, 2**31),
)
def test_the_fit_is_within_the_jitter_for_any_rate(boot_rate, jitter_s, seed):
    mapping = ClockMapping()
    for boot_s, unix_s in pairs(boot_rate, 20.0, every_s=0.5, jitter_s=jitter_s, seed=seed):
        mapping.add(boot_s, unix_s)
    boot_s = 37.2 + boot_rate * 19.0
    assert mapping.unix_s(boot_s) == pytest.approx(UNIX_AT_BOOT + 19.0, abs=3 * jitter_s + 2e-3)


def test_mission_time_scales_unix_time_around_its_reference():
    now = {"unix": 1000.0}
    time = MissionTime(unix=lambda: now["unix"])
    assert time.now_s() == 1000.0 and not time.started
    time.set(1.93, reference_s=1000.0)
    assert time.started
    now["unix"] = 1010.0
    assert time.now_s() == pytest.approx(1019.3)
    assert time.to_unix(time.from_unix(1234.5)) == pytest.approx(1234.5)
    with pytest.raises(ClockMappingError, match="rate"):
        time.set(0.0, 1000.0)


def test_the_mission_clock_rate_is_the_autopilots_median_or_exactly_one():
    assert MissionTime.rate_for([0.986, 0.985, 0.987, 0.990]) == pytest.approx(0.9865)
    assert MissionTime.rate_for([1.93, 1.92, 1.94]) == 1.93
    assert MissionTime.rate_for([1.00004, 0.99997]) == 1.0  # hardware crystals: UNIX time
    assert MissionTime.rate_for([]) == 1.0


def test_a_jittery_simulated_clock_is_followed_between_pairs():
    """PX4 SIH on a loaded machine: its boot clock strays tens of ms from any line."""
    mapping = ClockMapping()

    def boot_at(unix):  # 0.986x with a 30 ms wobble
        return 5.0 + 0.986 * unix + 0.03 * math.sin(2 * math.pi * unix / 3.7)

    for unix in np.arange(0.0, 20.0, 0.1):
        mapping.add(round(boot_at(unix), 3), UNIX_AT_BOOT + unix)
    assert mapping.fit.residual_s > 0.015  # no line fits it
    for unix in np.arange(5.03, 19.9, 0.37):
        assert mapping.unix_s(boot_at(unix)) == pytest.approx(UNIX_AT_BOOT + unix, abs=2e-3)
        assert mapping.boot_s(UNIX_AT_BOOT + unix) == pytest.approx(boot_at(unix), abs=2e-3)


def test_pairs_fed_from_another_thread_are_taken_in_order_when_the_mapping_is_read():
    """MAVSDK's thread feeds SYSTEM_TIME pairs; the loop's thread reads the mapping: the same
    fit, pair for pair, as adding them there (outliers and a clock step included)."""
    fed = pairs(1.93, 30.0, every_s=0.1, jitter_s=0.002, seed=4)
    fed[100] = (fed[100][0], fed[100][1] + 5.0)  # a lone outlier
    fed[200:] = [(boot, unix + 60.0) for boot, unix in fed[200:]]  # the UNIX clock stepped
    added, mapping = ClockMapping(), FedClockMapping()
    assert not mapping.ready
    feeder = threading.Thread(target=lambda: [mapping.feed(*pair) for pair in fed])
    feeder.start()
    feeder.join()
    assert not mapping.fitted  # queued, not taken: nothing read it yet
    for pair in fed:
        added.add(*pair)
    assert mapping.ready and mapping.fitted
    assert mapping.fit == added.fit
    assert (mapping.rejected, mapping.refits) == (added.rejected, added.refits) == (3, 1)
    assert mapping.recent_boot_rate() == added.recent_boot_rate()
    mapping.feed(fed[-1][0] + 0.1, fed[-1][1] + 0.1 / 1.93)
    added.add(fed[-1][0] + 0.1, fed[-1][1] + 0.1 / 1.93)
    assert mapping.unix_s(fed[-1][0] + 0.05) == added.unix_s(fed[-1][0] + 0.05)
    assert mapping.boot_s(fed[-1][1]) == added.boot_s(fed[-1][1])


@pytest.mark.slow  # 144 000 pairs, one by one
def test_the_running_fit_is_the_windows_least_squares_line_after_hours():
    """The fit is kept from running sums (a refit at every SYSTEM_TIME must not cost the whole
    window); after four hours of pairs at 10 Hz, a jump and a sliding window it is still the
    least-squares line through exactly the pairs in the window."""
    mapping = ClockMapping()
    sequence = pairs(1.93, 4 * 3600.0, every_s=0.1, jitter_s=0.003, seed=7)
    jumped = [(boot_s, unix_s + 30.0) for boot_s, unix_s in sequence[-400:]]  # NTP stepped
    for boot_s, unix_s in sequence[:-400] + jumped:
        mapping.add(boot_s, unix_s)
    window = [pair for pair in sequence[:-400] + jumped if pair[0] >= jumped[-1][0] - 20.0]
    boots, unixes = np.array(window).T
    rate, intercept = np.polyfit(boots - boots[0], unixes - unixes[0], 1)
    fit = mapping.fit
    assert mapping.refits == 1 and fit.pairs == len(window)
    assert fit.rate == pytest.approx(rate, rel=1e-9)
    assert fit.unix_s(boots[-1]) == pytest.approx(  # a microsecond: 1.7e9 s in a double
        unixes[0] + intercept + rate * (boots[-1] - boots[0]), abs=1e-6
    )
    residual = unixes - (unixes[0] + intercept + rate * (boots - boots[0]))
    assert fit.residual_s == pytest.approx(np.sqrt(np.mean(residual**2)), rel=1e-4)


def test_the_recent_rate_follows_a_clock_that_changes_pace_where_the_fit_lags():
    """PX4 SIH sharing the CPU with the mission's start runs its clock slower, then not."""
    mapping = ClockMapping()
    for boot_s, unix_s in pairs(0.9, 20.0, every_s=0.1):
        mapping.add(boot_s, unix_s)
    assert mapping.recent_boot_rate() == pytest.approx(0.9, rel=1e-3)
    boot_at_change = 37.2 + 0.9 * 20.0
    for boot_s, unix_s in pairs(1.0, 4.5, every_s=0.1, boot_offset_s=boot_at_change):
        mapping.add(boot_s, unix_s + 20.0)
    assert mapping.recent_boot_rate(span_s=4.0) == pytest.approx(1.0, rel=2e-3)
    assert mapping.fit.boot_rate < 0.95  # the 20 s window still holds the slower part


def test_a_rate_change_keeps_the_mission_clock_continuous_and_invertible():
    now = {"unix": 1000.0}
    time = MissionTime(unix=lambda: now["unix"])
    time.set(0.63, reference_s=1000.0)
    at_mission_s = time.from_unix(1010.0)
    time.change(1.0, 1010.0, at_mission_s)
    now["unix"] = 1005.0
    assert time.rate == 0.63 and time.latest_rate == 1.0  # not yet in force
    assert time.now_s() == pytest.approx(1000.0 + 0.63 * 5.0)
    now["unix"] = 1012.0
    assert time.rate == 1.0
    assert time.now_s() == pytest.approx(at_mission_s + 2.0)
    for unix_s in (995.0, 1003.0, 1010.0, 1030.0):
        assert time.to_unix(time.from_unix(unix_s)) == pytest.approx(unix_s)
    # A change at or before a pending one's instant replaces it.
    time.change(2.0, 1011.0, time.from_unix(1011.0))
    time.change(0.5, 1010.5, time.from_unix(1010.5))
    assert time.latest_rate == 0.5 and time.from_unix(1020.0) == pytest.approx(
        at_mission_s + 0.5 + 0.5 * 9.5
    )
    with pytest.raises(ClockMappingError, match="rate"):
        time.change(1000.0, 1020.0, 0.0)


def follower(rate=1.0, **kwargs):
    now = {"unix": 1000.0}
    time = MissionTime(unix=lambda: now["unix"])
    time.set(rate, reference_s=1000.0)
    return ClockFollower(time, **kwargs), time, now


def test_the_ground_follows_autopilots_that_change_pace_for_longer_than_its_hold():
    clock, time, now = follower(0.63, band=0.03, hold_s=2.0, lead_s=0.5)
    for unix_s in np.arange(1000.0, 1003.0, 0.5):
        now["unix"] = unix_s
        for vehicle in (1, 2, 3):
            clock.heard(vehicle, 0.64, unix_s)  # within the band: nothing to do
        assert clock.due(unix_s) is None
    seen = []
    for unix_s in np.arange(1003.0, 1010.0, 0.5):
        now["unix"] = unix_s
        for vehicle, rate in ((1, 0.99), (2, 1.0), (3, 1.01)):
            clock.heard(vehicle, rate, unix_s)
        seen.append((unix_s, clock.due(unix_s)))
    changes = [(unix_s, change) for unix_s, change in seen if change is not None]
    assert len(changes) == 1 and clock.changes == 1
    sent_s, change = changes[0]
    assert sent_s == 1005.0  # off the band for the hold
    assert (change.rate, change.at_unix_s) == (1.0, 1005.5)
    assert change.mission_s == pytest.approx(1000.0 + 0.63 * 5.5)
    assert time.latest_rate == 1.0


def test_the_ground_ignores_stale_and_impossible_rates_and_hardware_clocks():
    clock, time, _ = follower(1.0, hold_s=0.0)
    clock.heard(1, 0.5, 990.0)  # heard 10 s ago: not a rate of now
    clock.heard(2, float("nan"), 1000.0)
    clock.heard(3, 1e9, 1000.0)
    assert clock.due(1000.0) is None
    clock.heard(1, 1.00004, 1000.0)  # a crystal: the mission clock stays UNIX time
    assert clock.due(1000.0) is None and time.latest_rate == 1.0

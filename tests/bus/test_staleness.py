"""The silence watchdog, on a manual clock."""

from __future__ import annotations

import pytest

from mission_runner.bus import SilenceWatchdog


class FakeTime:
    """A clock the test sets by hand: the watchdog only ever reads time."""

    def __init__(self, now_s: float) -> None:
        self.now_s = now_s

    def now(self) -> float:
        return self.now_s


@pytest.fixture
def clock() -> FakeTime:
    return FakeTime(100.0)


def test_fresh_after_feeding_silent_after_timeout(clock: FakeTime) -> None:
    watchdog = SilenceWatchdog(0.5, now=clock.now)
    watchdog.feed()
    clock.now_s += 0.5  # exactly the timeout is still fresh
    assert not watchdog.is_silent()
    clock.now_s += 0.01
    assert watchdog.is_silent()
    assert watchdog.silence_s() == pytest.approx(0.51)
    watchdog.feed()
    assert not watchdog.is_silent()
    assert watchdog.last_arrival_s == pytest.approx(100.51)


def test_never_fed_counts_silence_from_construction_and_reset(clock: FakeTime) -> None:
    watchdog = SilenceWatchdog(1.0, now=clock.now)
    clock.now_s += 1.5
    assert watchdog.is_silent()
    assert watchdog.last_arrival_s is None
    watchdog.reset()
    assert not watchdog.is_silent()


def test_sources_go_silent_independently(clock: FakeTime) -> None:
    watchdog = SilenceWatchdog(0.3, now=clock.now)
    for vehicle_id in (1, 2, 3):
        watchdog.feed(vehicle_id)
    clock.now_s += 0.2
    watchdog.feed(1)
    watchdog.feed(2)
    clock.now_s += 0.2
    assert watchdog.silent_sources() == [3]
    assert watchdog.fresh_sources() == [1, 2]
    assert watchdog.is_silent(3)
    assert not watchdog.is_silent()  # someone is still talking
    watchdog.forget(3)
    assert watchdog.silent_sources() == []


def test_an_unknown_source_is_silent_since_construction(clock: FakeTime) -> None:
    watchdog = SilenceWatchdog(0.3, now=clock.now)
    watchdog.feed(1)
    assert not watchdog.is_silent(9)
    clock.now_s += 0.4
    assert watchdog.is_silent(9)


def test_out_of_order_arrival_times_do_not_move_time_back(clock: FakeTime) -> None:
    watchdog = SilenceWatchdog(1.0, now=clock.now)
    watchdog.feed(1, at_s=100.5)
    watchdog.feed(1, at_s=100.2)
    assert watchdog.last_arrival_s == 100.5
    clock.now_s = 101.4
    assert not watchdog.is_silent(1)


@pytest.mark.parametrize("timeout_s", [0.0, -1.0, float("inf"), float("nan")])
def test_timeout_must_be_positive_and_finite(timeout_s: float) -> None:
    with pytest.raises(ValueError, match="timeout_s"):
        SilenceWatchdog(timeout_s)

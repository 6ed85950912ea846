"""The in-process mission's lockstep pacer (take-off and landing run under it): it takes part in
the emulator's clock only inside its block, and a failure of its task ends the block with the
error instead of vanishing with the task."""

import asyncio

import pytest

from mission_runner.runner.mission import (
    HEARD_PACE_PERIOD_S,
    PACE_LEAD_S,
    PACE_PERIOD_S,
    _paced,
    heard_until,
)
from mission_runner.runner.odometry import OdometrySample, OdometryTrack
from sitl.clock import Clock
from sitl.errors import ClockError

pytestmark = pytest.mark.asyncio


async def test_the_pacer_releases_lockstep_time_only_inside_its_block():
    clock = Clock("lockstep")
    async with _paced(clock, speed=10.0):
        await asyncio.sleep(3 * PACE_PERIOD_S)
        assert clock.participants["pace"] == pytest.approx(10.0 * PACE_PERIOD_S)
    assert "pace" not in clock.participants


async def test_the_pacer_is_a_no_op_in_real_time():
    clock = Clock("realtime")
    async with _paced(clock):
        await asyncio.sleep(3 * PACE_PERIOD_S)
        assert clock.participants == {}


@pytest.mark.timeout(10)
async def test_a_failing_pacer_ends_its_block_with_the_error():
    clock = Clock("lockstep")
    with pytest.raises(ExceptionGroup) as caught:
        async with _paced(clock):
            clock.unregister("pace")  # what the clock does to a participant that stalled
            await asyncio.sleep(5.0)  # cancelled as soon as the pacer next acts
    assert caught.group_contains(ClockError, match="not registered")


async def test_the_pacer_runs_ahead_of_what_was_heard_by_at_most_its_lead():
    clock = Clock("lockstep")
    heard: list[float | None] = [None]
    async with _paced(clock, speed=10.0, heard=lambda: heard[0]):
        await asyncio.sleep(3 * HEARD_PACE_PERIOD_S)
        floor = clock.participants["pace"]
        assert floor == pytest.approx(10.0 * HEARD_PACE_PERIOD_S)  # nothing heard: 10x
        heard[0] = 7.0  # the vehicles' telemetry is far ahead of the floor: follow it
        await asyncio.sleep(3 * HEARD_PACE_PERIOD_S)
        assert clock.participants["pace"] == pytest.approx(7.0 + PACE_LEAD_S)
        heard[0] = 1.0  # heard lags what was released: never taken back
        await asyncio.sleep(3 * HEARD_PACE_PERIOD_S)
        assert clock.participants["pace"] == pytest.approx(7.0 + PACE_LEAD_S)


async def test_heard_until_is_the_oldest_of_the_vehicles_newest_odometry():
    class Vehicle:
        def __init__(self, *times: float) -> None:
            self.track = OdometryTrack()
            for t in times:
                self.track.add(OdometrySample(t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))

    assert heard_until([Vehicle(1.0, 2.0), Vehicle(1.5)]) == 1.5
    assert heard_until([Vehicle(1.0), Vehicle()]) is None  # one not heard yet
    assert heard_until([]) is None

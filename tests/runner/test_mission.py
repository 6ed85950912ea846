"""The in-process mission's lockstep pacer (take-off and landing run under it): it takes part in
the emulator's clock only inside its block, and a failure of its task ends the block with the
error instead of vanishing with the task."""

import asyncio

import pytest

from mission_runner.runner.mission import PACE_PERIOD_S, _paced
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

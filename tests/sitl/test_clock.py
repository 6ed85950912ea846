"""The shared clock: realtime with speed factor, lockstep with participants."""

from __future__ import annotations

import asyncio

import pytest

from sitl.clock import Clock
from sitl.errors import ClockError


class FakeWall:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_realtime_scales_wall_time_by_speed() -> None:
    wall = FakeWall()
    clock = Clock("realtime", 5.0, wall_time=wall)
    assert clock.now_s() == 0.0  # not started
    clock.start()
    wall.now += 2.0
    assert clock.now_s() == pytest.approx(10.0)
    assert clock.allowed_time_s() == pytest.approx(10.0)
    # Participants do not hold real time back.
    clock.register("controller")
    assert clock.allowed_time_s() == pytest.approx(10.0)


def test_a_realtime_clock_changes_pace_as_a_starved_simulator_does() -> None:
    """PX4 SITL sharing its CPU ran at 0.7x while everything started, then at about 1x."""
    wall = FakeWall()
    clock = Clock("realtime", 0.7, pace=[(10.0, 0.986), (20.0, 2.0)], wall_time=wall)
    clock.start()
    wall.now += 5.0
    assert (clock.now_s(), clock.current_speed) == (pytest.approx(3.5), 0.7)
    wall.now += 10.0  # 15 s: 10 s at 0.7, 5 at 0.986
    assert (clock.now_s(), clock.current_speed) == (pytest.approx(7.0 + 4.93), 0.986)
    wall.now += 10.0  # 25 s: then 5 at 2
    assert clock.now_s() == pytest.approx(7.0 + 9.86 + 10.0)
    with pytest.raises(ClockError, match="pace"):
        Clock("realtime", 1.0, pace=[(1.0, 0.0)])


def test_lockstep_allows_the_minimum_release() -> None:
    clock = Clock("lockstep", wall_time=FakeWall())
    clock.start()
    assert clock.allowed_time_s() == float("inf")
    clock.register("a")
    clock.register("b")
    assert clock.allowed_time_s() == 0.0
    clock.acted("a", 1.0)
    assert clock.allowed_time_s() == 0.0
    clock.acted("b", 0.5)
    assert clock.allowed_time_s() == 0.5
    clock.advance_to(0.5)
    assert clock.now_s() == 0.5
    with pytest.raises(ClockError, match="beyond allowed"):
        clock.advance_to(0.6)
    clock.unregister("b")
    assert clock.allowed_time_s() == 1.0


def test_misuse_is_a_clock_error() -> None:
    clock = Clock("lockstep")
    clock.register("a")
    with pytest.raises(ClockError, match="already registered"):
        clock.register("a")
    clock.acted("a", 2.0)
    with pytest.raises(ClockError, match="before its earlier release"):
        clock.acted("a", 1.0)
    with pytest.raises(ClockError, match="not registered"):
        clock.acted("ghost", 1.0)
    clock.unregister("ghost")  # harmless
    with pytest.raises(ClockError, match="mode"):
        Clock("warp")  # type: ignore[arg-type]


def test_lockstep_speed_cap() -> None:
    wall = FakeWall()
    clock = Clock("lockstep", lockstep_max_speed=10.0, wall_time=wall)
    clock.start()
    wall.now += 0.5
    assert clock.allowed_time_s() == pytest.approx(5.0)


@pytest.mark.asyncio
async def test_sleepers_wake_when_the_driver_advances() -> None:
    clock = Clock("lockstep")
    clock.start()
    woke: list[float] = []

    async def sleeper(t: float) -> None:
        await clock.sleep_until(t)
        woke.append(clock.now_s())

    async with asyncio.TaskGroup() as tg:
        tg.create_task(sleeper(0.3))
        tg.create_task(sleeper(0.1))
        await asyncio.sleep(0)
        for step in range(1, 5):
            clock.advance_to(step * 0.1)
            await asyncio.sleep(0)
    assert woke == pytest.approx([0.1, 0.30000000000000004])


@pytest.mark.asyncio
async def test_participant_context_unregisters_even_on_error() -> None:
    clock = Clock("lockstep")
    with pytest.raises(RuntimeError, match="boom"):
        async with clock.participant("p") as me:
            me.acted(1.0)
            assert clock.participants == {"p": 1.0}
            raise RuntimeError("boom")
    assert clock.participants == {}


@pytest.mark.asyncio
async def test_driver_waits_for_participants_and_resumes_on_act() -> None:
    clock = Clock("lockstep")
    clock.start()
    clock.register("p")
    waiter = asyncio.create_task(clock.wait_until_allowed_beyond(0.0), name="driver-wait")
    await asyncio.sleep(0)
    assert not waiter.done()
    clock.acted("p", 0.2)
    await asyncio.wait_for(waiter, 1.0)


@pytest.mark.asyncio
async def test_a_dead_participant_is_dropped_after_the_stall_timeout() -> None:
    clock = Clock("lockstep", participant_timeout_s=0.05)
    clock.start()
    clock.register("alive")
    clock.register("dead")
    clock.acted("alive", 10.0)
    await asyncio.wait_for(clock.wait_until_allowed_beyond(0.0), 2.0)
    assert "dead" not in clock.participants
    assert clock.allowed_time_s() == 10.0


@pytest.mark.asyncio
async def test_realtime_sleep_uses_scaled_wall_time() -> None:
    clock = Clock("realtime", 50.0)
    clock.start()
    await asyncio.wait_for(clock.sleep(1.0), 1.0)  # 1 simulated s = 20 ms wall
    assert clock.now_s() >= 1.0


@pytest.mark.asyncio
async def test_a_release_between_steps_wakes_the_sleeper_at_the_last_step_before_it() -> None:
    clock = Clock("lockstep")
    clock.set_step(0.02)
    clock.start()
    clock.register("p")
    clock.acted("p", 0.05)
    sleeper = asyncio.create_task(clock.sleep_until(0.05), name="sleeper")
    await asyncio.sleep(0)
    clock.advance_to(0.02)
    await asyncio.sleep(0)
    assert not sleeper.done()
    clock.advance_to(0.04)  # the next step (0.06) would pass the release
    await asyncio.wait_for(sleeper, 1.0)

"""A controller's view of the emulator's lockstep clock: a command is applied at its release
time, the world held there until the vehicle has taken the setpoint (woken by the vehicle as it
takes one, not by polling)."""

import asyncio

import pytest

from mission_runner.runner.clock import EmulatorClock
from sitl.clock import Clock

pytestmark = pytest.mark.asyncio


class Vehicle:
    """The emulated vehicle's setpoint count and listeners (``Px4Autopilot``'s)."""

    def __init__(self):
        self.accepted_setpoints = 0
        self.listeners = []

    def add_setpoint_listener(self, listener):
        self.listeners.append(listener)

    def remove_setpoint_listener(self, listener):
        self.listeners.remove(listener)

    def take(self):
        self.accepted_setpoints += 1
        for listener in self.listeners:
            listener()


async def settle():
    """Let every ready task run until each waits again."""
    for _ in range(5):
        await asyncio.sleep(0)


async def test_a_lockstep_command_ends_only_once_the_vehicle_took_the_setpoint():
    vehicle, sent = Vehicle(), []

    async def command(clock):
        async with clock.commanding(0.0):
            sent.append(vehicle.accepted_setpoints)

    async with EmulatorClock(Clock("lockstep"), "vehicle-1", setpoints=vehicle) as clock:
        assert len(vehicle.listeners) == 1
        commanding = asyncio.create_task(command(clock))
        await settle()
        assert sent == [0] and not commanding.done()
        vehicle.listeners[0]()  # a wake-up without a setpoint taken: still waiting
        await settle()
        assert not commanding.done()
        vehicle.take()
        await settle()
        assert commanding.done()
        await commanding
    assert vehicle.listeners == []  # the clock's listener goes with it


async def test_in_real_time_nothing_is_waited_for_or_listened_to():
    vehicle = Vehicle()
    async with EmulatorClock(Clock("realtime"), "vehicle-1", setpoints=vehicle) as clock:
        assert vehicle.listeners == []
        async with clock.commanding(0.0):
            pass

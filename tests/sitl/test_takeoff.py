"""MAV_CMD_NAV_TAKEOFF as PX4 (1.15 on) answers it, over UDP with a pymavlink client: the
mode switch while disarmed, MIS_TAKEOFF_ALT above the vehicle when no altitude is given, and
param 7 read as AMSL, never descending; with PX4's texts."""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl import Emulator, EmulatorConfig
from sitl.config import ClockConfig
from sitl.modes import FlightMode
from tests.sitl.helpers import RawClient, free_port_config

ACCEPTED, TAKEOFF = 0, 22
AUTO, AUTO_TAKEOFF = 4, 2
Message = mavlink.MAVLink_message


def config(n: int) -> EmulatorConfig:
    return EmulatorConfig(vehicles=n, ports=free_port_config(n), clock=ClockConfig(speed=10.0))


def text_of(sysid: int, text: str) -> Callable[[Message], bool]:
    return lambda m: m.get_type() == "STATUSTEXT" and m.get_srcSystem() == sysid and m.text == text


def height_m(emulator: Emulator, index: int) -> float:
    return -float(emulator.truth.position_ned_m[index, 2])


@pytest.mark.asyncio
async def test_takeoff_while_disarmed_switches_mode_and_climbs_to_mis_takeoff_alt_on_arming() -> (
    None
):
    cfg = config(1)
    async with Emulator(cfg) as emulator, RawClient(cfg.ports.api_remote_port(0)) as client:
        await client.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "heartbeat")
        await emulator.run_for(1.0)
        assert await client.command(1, TAKEOFF, -1, 0, 0, *[math.nan] * 4) == ACCEPTED
        heartbeat = await client.expect(
            lambda m: m.get_type() == "HEARTBEAT" and m.custom_mode >> 24 == AUTO_TAKEOFF,
            3,
            "a heartbeat in Takeoff mode",
        )
        assert heartbeat.custom_mode >> 16 & 0xFF == AUTO
        assert not heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        with client.matching(text_of(1, "Using default takeoff altitude: 2.5 m\t")) as text:
            assert await client.command(1, 400, 1) == ACCEPTED
            await emulator.run_for(0.5)
            assert text.done()
        assert text.result().severity == mavlink.MAV_SEVERITY_INFO
        await emulator.wait_for(
            lambda: emulator.vehicle_status(0).mode is FlightMode.HOLD, timeout_s=15, what="Hold"
        )
        assert height_m(emulator, 0) == pytest.approx(2.5, abs=0.1)


@pytest.mark.asyncio
async def test_takeoff_below_the_vehicle_stays_there_and_says_so() -> None:
    """MAVProxy's ``takeoff 5`` sends param 7 = 5, which PX4 reads as 5 m AMSL."""
    cfg = config(1)
    home_amsl_m = cfg.home.altitude_amsl_m
    async with Emulator(cfg) as emulator, RawClient(cfg.ports.api_remote_port(0)) as client:
        await client.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "heartbeat")
        await emulator.run_for(1.0)
        assert await client.command(1, 400, 1) == ACCEPTED
        with client.matching(text_of(1, "Already higher than takeoff altitude\t")) as text:
            assert await client.command(
                1, TAKEOFF, -1, 0, 0, math.nan, math.nan, math.nan, 5.0
            ) == (ACCEPTED)
            await emulator.run_for(3.0)
            assert text.done()
        assert text.result().severity == mavlink.MAV_SEVERITY_CRITICAL
        assert emulator.vehicle_status(0).mode is FlightMode.TAKEOFF
        assert height_m(emulator, 0) < 0.05
        # An altitude above the vehicle, as PX4 wants it (AMSL): climbs there, no text.
        up = [math.nan] * 3 + [home_amsl_m + 5.0]
        assert await client.command(1, TAKEOFF, -1, 0, 0, *up) == ACCEPTED
        await emulator.wait_for(
            lambda: emulator.vehicle_status(0).mode is FlightMode.HOLD, timeout_s=15, what="Hold"
        )
        assert height_m(emulator, 0) == pytest.approx(5.0, abs=0.1)

"""100 000 random and malformed datagrams at every port while a vehicle flies offboard:
nothing crashes, the vehicle keeps flying and keeps answering."""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import socket
from collections.abc import Callable, Iterator

import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl import Emulator, EmulatorConfig
from sitl.config import ClockConfig
from sitl.modes import FlightMode
from tests.sitl.helpers import RawClient, free_port_config

DATAGRAMS = 100_000
BATCH = 40
OWN = 1  # the flying vehicle's system id
NAN, INF = math.nan, math.inf


def _ownerless_message(rng: random.Random) -> mavlink.MAVLink_message:
    """A well-formed message for a system that is not there."""
    target = rng.choice([0, 3, 77, 200])
    return rng.choice(
        [
            lambda: mavlink.MAVLink_command_long_message(
                target, 1, 400, 0, 0, 21196, 0, 0, 0, 0, 0
            ),
            lambda: mavlink.MAVLink_command_long_message(target, 1, 21, 0, 0, 0, 0, 0, 0, 0, 0),
            lambda: mavlink.MAVLink_set_position_target_local_ned_message(
                0, target, 1, 1, 2503, 0, 0, 0, 5, 5, 5, 0, 0, 0, 0, 0
            ),
            lambda: mavlink.MAVLink_param_set_message(target, 1, b"MPC_XY_VEL_MAX", 0.0, 9),
            lambda: mavlink.MAVLink_mission_clear_all_message(target, 1, 0),
            lambda: mavlink.MAVLink_set_mode_message(target, 1, 100925440),  # LAND
        ]
    )()


def _nonsense_for_us(rng: random.Random) -> mavlink.MAVLink_message:
    """Well-formed messages for the flying vehicle whose content makes no sense."""
    bad = rng.choice([NAN, INF, -INF, 1e30, -1e30])
    choices: list[Callable[[], mavlink.MAVLink_message]] = [
        lambda: mavlink.MAVLink_set_position_target_local_ned_message(
            0, OWN, 1, rng.choice([1, 8]), 2503, 0, 0, 0, bad, 0, 0, 0, 0, 0, 0, 0
        ),
        lambda: mavlink.MAVLink_set_position_target_local_ned_message(
            0, OWN, 1, 1, 0xFFFF, 0, 0, 0, 1, 1, 1, 0, 0, 0, 0, 0
        ),
        lambda: mavlink.MAVLink_set_position_target_local_ned_message(
            0, OWN, 1, rng.randrange(10, 256), 2503, 0, 0, 0, 1, 1, 1, 0, 0, 0, 0, 0
        ),
        lambda: mavlink.MAVLink_set_position_target_local_ned_message(
            0, OWN, 1, 1, 3135, 0, 0, 0, 0, 0, 0, bad, 0, 0, 0, 0
        ),
        lambda: mavlink.MAVLink_set_attitude_target_message(
            0, OWN, 1, 0, [NAN, 0, 0, 0], 0, 0, 0, 0.5
        ),
        lambda: mavlink.MAVLink_set_position_target_global_int_message(
            0, OWN, 1, 6, 3576, 2**31 - 1, 2**31 - 1, bad, 0, 0, 0, 0, 0, 0, 0, 0
        ),
        lambda: mavlink.MAVLink_command_long_message(
            OWN, 1, rng.randrange(40000, 60000), 0, bad, bad, bad, bad, bad, bad, bad
        ),
        lambda: mavlink.MAVLink_command_long_message(
            OWN, 1, 176, 0, rng.choice([NAN, 1.0, 0.0]), rng.randrange(8, 256), bad, 0, 0, 0, 0
        ),
        lambda: mavlink.MAVLink_command_long_message(OWN, 1, 400, 0, bad, bad, 0, 0, 0, 0, 0),
        lambda: mavlink.MAVLink_command_long_message(
            OWN, 1, 512, 0, rng.choice([bad, 1e6, -1.0, 2.0**40]), 0, 0, 0, 0, 0, 0
        ),
        lambda: mavlink.MAVLink_command_long_message(
            OWN, 1, rng.choice([178, 179, 224, 510]), 0, bad, bad, bad, bad, bad, bad, bad
        ),
        lambda: mavlink.MAVLink_command_int_message(
            OWN,
            1,
            rng.randrange(256),
            192,
            0,
            0,
            bad,
            1,
            0,
            bad,
            2_000_000_000,
            -2_000_000_000,
            bad,
        ),
        lambda: mavlink.MAVLink_param_set_message(
            OWN,
            1,
            rng.choice([b"NO_SUCH", b"\xff\xfe\x00", b"MPC_XY_VEL_MAX"]),
            bad,
            rng.randrange(256),
        ),
        lambda: mavlink.MAVLink_param_request_read_message(
            OWN, 1, bytes(rng.randrange(256) for _ in range(16)), rng.randrange(-32768, 32767)
        ),
        lambda: mavlink.MAVLink_mission_item_int_message(
            OWN,
            1,
            rng.randrange(65535),
            rng.randrange(256),
            rng.randrange(65535),
            0,
            1,
            bad,
            bad,
            bad,
            bad,
            rng.randrange(-(2**31), 2**31),
            rng.randrange(-(2**31), 2**31),
            bad,
            rng.randrange(256),
        ),
        lambda: mavlink.MAVLink_mission_count_message(
            OWN, 1, rng.randrange(65535), rng.randrange(256)
        ),
        lambda: mavlink.MAVLink_mission_request_int_message(
            OWN, 1, rng.randrange(65535), rng.randrange(256)
        ),
        lambda: mavlink.MAVLink_mission_ack_message(OWN, 1, rng.randrange(256), rng.randrange(256)),
        lambda: mavlink.MAVLink_ping_message(rng.randrange(2**63), rng.randrange(2**32), 0, 0),
        lambda: mavlink.MAVLink_timesync_message(0, rng.randrange(-(2**63), 2**63)),
    ]
    return rng.choice(choices)()


def fuzz_datagrams(rng: random.Random, encoder: mavlink.MAVLink) -> Iterator[bytes]:
    """Endless stream of bad datagrams of many kinds."""
    while True:
        kind = rng.randrange(8)
        if kind == 0:  # noise
            yield bytes(rng.randrange(256) for _ in range(rng.randrange(0, 300)))
        elif kind == 1:  # noise that starts like MAVLink 2 / 1
            head = bytes([rng.choice([0xFD, 0xFE]), rng.randrange(256), rng.randrange(256)])
            yield head + bytes(rng.randrange(256) for _ in range(rng.randrange(0, 280)))
        else:
            msg = _ownerless_message(rng) if kind == 2 else _nonsense_for_us(rng)
            frame = bytearray(msg.pack(encoder))
            if kind == 3:  # corrupted byte (CRC no longer matches)
                frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
            elif kind == 4:  # truncated
                frame = frame[: rng.randrange(1, len(frame))]
            elif kind == 5:  # several frames with garbage in between
                frame += bytes(rng.randrange(256) for _ in range(rng.randrange(5)))
                frame += _nonsense_for_us(rng).pack(encoder)
            yield bytes(frame)


@pytest.mark.slow
@pytest.mark.asyncio
async def test_hundred_thousand_bad_datagrams_do_not_stop_a_flying_vehicle() -> None:
    cfg = EmulatorConfig(
        vehicles=2,
        ports=free_port_config(2),
        clock=ClockConfig(speed=1.0),
        params={"COM_OF_LOSS_T": 3.0},
    )
    rng = random.Random(20240601)
    async with Emulator(cfg) as emulator, RawClient(cfg.ports.api_remote_port(0)) as client:
        await client.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "heartbeat")
        client.heartbeat()
        await emulator.run_for(1.0)
        assert await client.command(OWN, 400, 1) == 0
        assert await client.command(OWN, 22, *[NAN] * 7) == 0
        await emulator.wait_for(
            lambda: (
                emulator.vehicle_status(0).mode is FlightMode.HOLD
                and not emulator.vehicle_status(0).landed
            ),
            timeout_s=15,
            what="airborne",
        )
        client.velocity(OWN, 0.0, 0.0, 0.0, yaw=0.0)
        assert await client.command(OWN, 176, 1, 6, 0) == 0
        altitude = -emulator.truth.position_ned_m[0, 2]

        async def stream_setpoints() -> None:
            while True:
                client.heartbeat()
                client.velocity(OWN, 0.0, 0.0, 0.0, yaw=0.0)
                await asyncio.sleep(0.1)

        ports = [ep.api_local_port for ep in emulator.endpoints]
        ports += [ep.gcs_local_port for ep in emulator.endpoints if ep.gcs_local_port]
        fuzz_encoder = mavlink.MAVLink(None, srcSystem=66, srcComponent=66)
        datagrams = fuzz_datagrams(rng, fuzz_encoder)
        before = emulator.stats().rx_datagrams
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as fuzzer:
            fuzzer.setblocking(False)
            async with asyncio.TaskGroup() as tg:
                setpoints = tg.create_task(stream_setpoints(), name="setpoint-stream")
                sent = 0
                while sent < DATAGRAMS:
                    for _ in range(BATCH):
                        with contextlib.suppress(BlockingIOError):  # a full buffer drops it
                            fuzzer.sendto(next(datagrams), ("127.0.0.1", ports[sent % len(ports)]))
                        sent += 1
                    # Let the emulator read what was sent before sending more (bounded).
                    for _ in range(200):
                        if emulator.stats().rx_datagrams - before >= sent - BATCH:
                            break
                        await asyncio.sleep(0)
                    await asyncio.sleep(0)
                await emulator.run_for(1.0)
                setpoints.cancel()

        stats = emulator.stats()
        assert stats.rx_datagrams - before >= 0.95 * DATAGRAMS
        assert stats.rx_bad > 10_000
        assert stats.handler_errors == 0
        status = emulator.vehicle_status(0)
        assert status.armed and status.mode is FlightMode.OFFBOARD and not status.failsafe
        assert -emulator.truth.position_ned_m[0, 2] == pytest.approx(altitude, abs=0.3)
        assert emulator.vehicle_status(1).alive and not emulator.vehicle_status(1).armed
        # Still answering: commands, parameters, telemetry.
        assert await client.command(OWN, 520) == 0
        with client.matching(lambda m: m.get_type() == "PARAM_VALUE") as value:
            client.send(mavlink.MAVLink_param_request_read_message(OWN, 1, b"MPC_XY_VEL_MAX", -1))
            assert (await asyncio.wait_for(value, 3)).param_value == 12.0
        await client.expect(lambda m: m.get_type() == "LOCAL_POSITION_NED", 3)

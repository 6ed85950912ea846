"""Clocks like PX4 SITL: every vehicle stamps its messages with its own boot clock, and SYSTEM_TIME
can follow the host's clock while simulated time runs at another rate (SIH: 0.986x)."""

from __future__ import annotations

import asyncio
import time
import types

import numpy as np
import pytest
from pydantic import ValidationError
from pymavlink.dialects.v20 import common as mavlink

from sitl import Clock, Emulator, EmulatorConfig
from sitl.config import BootClockConfig, ClockConfig
from tests.sitl.helpers import Bench, RawClient, free_port_config

REQUEST_MESSAGE = 512
SYSTEM_TIME = 2


# ------------------------------------------------------------------ state machine, no sockets
def test_every_timestamp_a_vehicle_sends_is_on_its_own_boot_clock() -> None:
    bench = Bench(2, boot_offsets_s=[0.0, 12.5], ready_after_s=1.0)
    bench.run(1.0)
    late = bench.autopilots[1].telemetry
    assert late.local_position_ned(bench.t).time_boot_ms == 13_500
    assert late.global_position_int(bench.t).time_boot_ms == 13_500
    assert late.attitude(bench.t).time_boot_ms == 13_500
    assert late.attitude_quaternion(bench.t).time_boot_ms == 13_500
    assert late.system_time(bench.t).time_boot_ms == 13_500
    assert late.gps_raw_int(bench.t).time_usec == 13_500_000
    assert late.altitude(bench.t).time_usec == 13_500_000
    assert late.home_position(bench.t).time_usec == 13_500_000
    assert bench.autopilots[0].telemetry.local_position_ned(bench.t).time_boot_ms == 1_000
    # TIMESYNC answers on the boot clock too (PX4: hrt_absolute_time() in ns).
    bench.links[1].clear()
    bench.deliver(mavlink.MAVLink_timesync_message(0, 777), vehicle=1)
    (reply,) = bench.links[1].of_type("TIMESYNC")
    assert (reply.tc1, reply.ts1) == (13_500_000_000, 777)


def test_timers_inside_the_vehicle_stay_on_simulated_time() -> None:
    bench = Bench(1, boot_offsets_s=[100.0], ready_after_s=1.0)
    bench.run(0.5)
    assert not bench.ap.ready(bench.t)  # 100.5 s on the boot clock, but 0.5 s simulated
    bench.run(0.6)
    assert bench.ap.ready(bench.t)


def test_system_time_unix_clock_is_injectable_and_defaults_to_epoch_plus_simulated_time() -> None:
    bench = Bench(1)
    bench.ap.unix_epoch_start_us = 1_700_000_000_000_000
    bench.run(2.0)
    msg = bench.ap.telemetry.system_time(bench.t)
    assert msg.time_unix_usec == 1_700_000_002_000_000 and msg.time_boot_ms == 2_000
    host = Bench(1, unix_time_us=lambda now_s: 1_800_000_000_000_000 + int(now_s * 0.5e6))
    host.run(2.0)
    assert host.ap.telemetry.system_time(host.t).time_unix_usec == 1_800_000_001_000_000


# ------------------------------------------------------------------ settings
def test_boot_clock_settings_are_checked_against_the_vehicle_count() -> None:
    assert EmulatorConfig(vehicles=2, boot_clock={"offset_s": [0, 3.5]}).boot_clock.offset_s == [
        0.0,
        3.5,
    ]
    with pytest.raises(ValidationError, match="one per vehicle"):
        EmulatorConfig(vehicles=3, boot_clock={"offset_s": [0, 3.5]})
    with pytest.raises(ValidationError, match="not both"):
        EmulatorConfig(vehicles=2, boot_clock={"offset_s": [0, 1], "spread_s": 5})
    with pytest.raises(ValidationError):
        BootClockConfig(offset_s=[-1.0])
    assert ClockConfig().unix_time == "simulated"


# ------------------------------------------------------------------ over UDP
async def _system_times(client: RawClient, sysids: list[int]) -> dict[int, mavlink.MAVLink_message]:
    replies = {}
    for sysid in sysids:
        with client.matching(
            lambda m, s=sysid: m.get_type() == "SYSTEM_TIME" and m.get_srcSystem() == s
        ) as reply:
            assert await client.command(sysid, REQUEST_MESSAGE, SYSTEM_TIME) == 0
            replies[sysid] = await reply
    return replies


@pytest.mark.asyncio
async def test_random_boot_offsets_are_seeded_and_within_the_spread() -> None:
    offsets = []
    for seed in (7, 7, 8):
        cfg = EmulatorConfig(
            vehicles=5,
            seed=seed,
            ports=free_port_config(5, gcs=False),
            clock=ClockConfig(mode="lockstep"),
            boot_clock=BootClockConfig(spread_s=30.0),
        )
        clock = Clock("lockstep")
        clock.register("test")
        async with Emulator(cfg, clock=clock) as emulator:
            offsets.append(emulator.truth.boot_clock_offset_s.copy())
    assert np.array_equal(offsets[0], offsets[1])
    assert not np.array_equal(offsets[0], offsets[2])
    assert np.all((offsets[0] >= 0) & (offsets[0] <= 30.0))
    assert len(set(offsets[0].tolist())) == 5


@pytest.mark.asyncio
async def test_vehicles_boot_clocks_differ_by_their_offsets_in_lockstep() -> None:
    n = 2
    cfg = EmulatorConfig(
        vehicles=n,
        ports=free_port_config(n, gcs=False),
        clock=ClockConfig(mode="lockstep", unix_time="host"),
        boot_clock=BootClockConfig(offset_s=[0.0, 30.25]),
    )
    clock = Clock("lockstep")
    clock.register("test")
    async with (
        Emulator(cfg, clock=clock) as emulator,
        RawClient(cfg.ports.api_remote_port(0)) as c0,
        RawClient(cfg.ports.api_remote_port(1)) as c1,
    ):

        def heartbeat(m: mavlink.MAVLink_message) -> bool:
            return m.get_type() == "HEARTBEAT"

        # Nothing is sent before time moves: release it with the matchers in place.
        with c0.matching(heartbeat) as seen0, c1.matching(heartbeat) as seen1:
            clock.acted("test", 1.0)
            await clock.sleep_until(1.0)
            await asyncio.wait_for(asyncio.gather(seen0, seen1), 5)
        first = {**await _system_times(c0, [1]), **await _system_times(c1, [2])}
        clock.acted("test", 3.0)
        await clock.sleep_until(3.0)
        later = {**await _system_times(c0, [1]), **await _system_times(c1, [2])}
        assert emulator.time_s == pytest.approx(3.0)
    # Time is held while the requests are answered: exact boot clocks.
    assert (first[1].time_boot_ms, first[2].time_boot_ms) == (1_000, 31_250)
    assert (later[1].time_boot_ms, later[2].time_boot_ms) == (3_000, 33_250)
    # Lockstep has no relation to the host's clock: UNIX time is epoch + simulated time.
    for sysid in (1, 2):
        unix_step_us = later[sysid].time_unix_usec - first[sysid].time_unix_usec
        assert unix_step_us == pytest.approx(2_000_000, abs=1)


@pytest.mark.asyncio
async def test_system_time_follows_the_host_clock_while_simulated_time_runs_at_its_speed() -> None:
    """At speed 2 the boot clock gains a second per wall second on the host clock; the same
    mechanism makes speed 0.986 reproduce SIH's drift of 14 ms per second."""
    speed = 2.0
    cfg = EmulatorConfig(
        vehicles=1,
        ports=free_port_config(1, gcs=False),
        clock=ClockConfig(speed=speed, unix_time="host"),
        boot_clock=BootClockConfig(offset_s=[4.0]),
    )
    async with Emulator(cfg) as emulator, RawClient(cfg.ports.api_remote_port(0)) as client:
        await client.expect(lambda m: m.get_type() == "HEARTBEAT", 5, "heartbeat")
        first = (await _system_times(client, [1]))[1]
        received_s = time.time()
        await emulator.run_for(3.0)
        later = (await _system_times(client, [1]))[1]
    assert abs(first.time_unix_usec * 1e-6 - received_s) < 0.25
    boot_s = (later.time_boot_ms - first.time_boot_ms) * 1e-3
    unix_s = (later.time_unix_usec - first.time_unix_usec) * 1e-6
    assert boot_s >= 3.0
    assert boot_s / unix_s == pytest.approx(speed, rel=0.15)
    assert first.time_boot_ms >= 4_000  # on the vehicle's own boot clock


@pytest.mark.asyncio
async def test_unix_time_zero_is_when_simulated_time_starts_however_long_the_setup(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Every autopilot's SYSTEM_TIME UNIX epoch is the instant the clock starts, not when the
    vehicles were built: on a loaded machine binding the sockets took 0.06-0.16 s for four
    vehicles here (longer elsewhere), and a world publishing on the autopilots' UNIX time ran
    that far behind the host's clock, past the controllers' deadlines."""
    reads: list[float] = []

    def host_time() -> float:  # a host clock 1 s on at every read
        reads.append(1_800_000_000.0 + len(reads))
        return reads[-1]

    monkeypatch.setattr(  # the emulator's reads only
        "sitl.emulator.time", types.SimpleNamespace(time=host_time, monotonic=time.monotonic)
    )
    cfg = EmulatorConfig(
        vehicles=3, ports=free_port_config(3, gcs=False), clock=ClockConfig(mode="lockstep")
    )
    clock = Clock("lockstep")
    clock.register("test")
    async with Emulator(cfg, clock=clock) as emulator:
        epochs = {emulator.autopilot(i).unix_time_us(0.0) for i in range(3)}
    # One epoch for every vehicle: the host's time when the clock started, its last read.
    assert epochs == {int(reads[-1] * 1e6)}

"""Benchmarks of the vehicle emulator; prints figures, asserts nothing.

    python bench/sitl_bench.py            # all figures (about a minute)
    python bench/sitl_bench.py --quick    # shorter runs

1. CPU per vehicle at the default telemetry rates, in real time, vehicles hovering
   (PX4 SITL measured ~9 % of one core per instance; the target here is <= 0.9 %).
2. 50 vehicles in one process holding real time: achieved step rate and lateness (jitter)
   of the physics/telemetry loop.
3. Maximum lockstep speed-up for 4 and 16 vehicles, with nobody holding the clock back and
   with one trivial participant that acts every 50 ms of simulated time.

Nobody listens on the client ports: telemetry is encoded and sent, the kernel drops it.
Commands are handed to the vehicles' state machines directly (no client in the process).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

from pymavlink.dialects.v20 import common as mavlink

# Run from a checkout without installing: the repository root holds the sitl package.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sitl import Clock, Emulator, EmulatorConfig
from sitl.config import ClockConfig, PortsConfig

BASE_PORT = 31000


def ports(n: int) -> PortsConfig:
    # A private range far from PX4's so the bench can run beside a real SITL.
    return PortsConfig(
        api_remote_base=BASE_PORT,
        api_local_base=BASE_PORT + 300,
        gcs_local_base=BASE_PORT + 600,
        gcs_remote_port=BASE_PORT + 999,
    )


def inject(emulator: Emulator, index: int, msg: mavlink.MAVLink_message) -> None:
    """Deliver ``msg`` to vehicle ``index`` as if it came from a client on its API link."""
    encoder = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    decoded = mavlink.MAVLink(None).parse_buffer(msg.pack(encoder))
    assert decoded
    link = emulator._links[index][0]  # bench only: reach the link object directly
    emulator.autopilot(index).handle_message(decoded[0], link, emulator.time_s)


async def hover_all(emulator: Emulator) -> None:
    await emulator.run_for(1.1, timeout_s=30)
    n = emulator.config.vehicles
    for i in range(n):
        inject(
            emulator, i, mavlink.MAVLink_command_long_message(i + 1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        )
        inject(emulator, i, mavlink.MAVLink_command_long_message(i + 1, 1, 22, 0, *[math.nan] * 7))
    await emulator.wait_for(
        lambda: all(emulator.truth.position_ned_m[:, 2] < -2.3), timeout_s=60, what="all airborne"
    )


async def cpu_per_vehicle(n: int, seconds: float, rate_hz: float = 50.0) -> tuple[float, float]:
    """Percent of one core used by the whole process / per vehicle, in real time."""
    cfg = EmulatorConfig(vehicles=n, ports=ports(n), physics={"rate_hz": rate_hz})
    async with Emulator(cfg) as emulator:
        await hover_all(emulator)
        cpu0, wall0 = time.process_time(), time.monotonic()
        await asyncio.sleep(seconds)
        cpu = time.process_time() - cpu0
        wall = time.monotonic() - wall0
    total = 100.0 * cpu / wall
    return total, total / n


async def realtime_jitter(n: int, seconds: float) -> dict[str, float]:
    cfg = EmulatorConfig(vehicles=n, ports=ports(n))
    lateness: list[float] = []
    async with Emulator(cfg) as emulator:
        await hover_all(emulator)
        clock = emulator.clock
        start_sim = emulator.time_s
        steps0 = emulator.stats().steps
        wall0 = time.monotonic()

        def record(time_s: float, _truth: object) -> None:
            # How late this step ran compared with when simulated time reached it.
            lateness.append(clock.now_s() - time_s)

        remove = emulator.add_step_listener(record)
        cpu0 = time.process_time()
        await asyncio.sleep(seconds)
        remove()
        cpu = time.process_time() - cpu0
        wall = time.monotonic() - wall0
        stats = emulator.stats()
        sim = emulator.time_s - start_sim
    late_ms = sorted(v * 1000.0 for v in lateness)
    return {
        "step_rate_hz": (stats.steps - steps0) / wall,
        "target_hz": cfg.physics.rate_hz,
        "sim_per_wall": sim / wall,
        "late_mean_ms": statistics.fmean(late_ms),
        "late_p99_ms": late_ms[int(0.99 * (len(late_ms) - 1))],
        "late_max_ms": late_ms[-1],
        "max_lag_s": stats.max_lag_s,
        "cpu_percent": 100.0 * cpu / wall,
    }


async def lockstep_speedup(n: int, seconds: float, participant: bool) -> float:
    cfg = EmulatorConfig(vehicles=n, ports=ports(n), clock=ClockConfig(mode="lockstep"))
    clock = Clock.from_config(cfg.clock)
    async with Emulator(cfg, clock=clock) as emulator:
        await hover_all(emulator)

        async def trivial() -> None:
            async with clock.participant("trivial") as me:
                t = clock.now_s()
                while True:
                    t += 0.05
                    me.acted(t)
                    await clock.sleep_until(t)

        task = asyncio.create_task(trivial(), name="trivial-participant") if participant else None
        sim0, wall0 = emulator.time_s, time.monotonic()
        await asyncio.sleep(seconds)
        sim, wall = emulator.time_s - sim0, time.monotonic() - wall0
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
    return sim / wall


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="shorter measurement windows")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    window = 4.0 if args.quick else 10.0

    def run(title: str, coro_factory: Callable[[], object]) -> object:
        started = time.monotonic()
        result = asyncio.run(coro_factory())  # type: ignore[arg-type]
        print(f"  ({title}: {time.monotonic() - started:.0f} s)")
        return result

    print("1. CPU per vehicle, real time, default telemetry, hovering")
    for n, rate in ((10, 50.0), (50, 50.0), (10, 200.0)):
        total, per = run(f"{n} vehicles", lambda n=n, rate=rate: cpu_per_vehicle(n, window, rate))  # type: ignore[misc]
        print(
            f"   {n:3d} vehicles, {rate:.0f} Hz physics: {total:5.1f} % of one core in total, "
            f"{per:.2f} % per vehicle"
        )

    print("2. 50 vehicles holding real time")
    figures = run("50 vehicles", lambda: realtime_jitter(50, window))
    assert isinstance(figures, dict)
    print(
        "   step rate {step_rate_hz:.2f} Hz (target {target_hz:.0f}), simulated/wall "
        "{sim_per_wall:.4f}, step lateness mean {late_mean_ms:.2f} ms, p99 {late_p99_ms:.2f} ms, "
        "max {late_max_ms:.2f} ms, max backlog {max_lag_s:.3f} s, CPU {cpu_percent:.1f} %".format(
            **figures
        )
    )

    print("3. Lockstep speed-up (simulated s per wall s)")
    for n in (4, 16):
        free = run(f"{n} free", lambda n=n: lockstep_speedup(n, window / 2, False))
        held = run(f"{n} held", lambda n=n: lockstep_speedup(n, window / 2, True))
        print(
            f"   {n:3d} vehicles: {free:6.1f}x with nobody holding the clock, "
            f"{held:6.1f}x with a trivial 20 Hz participant"
        )


if __name__ == "__main__":
    main()

"""What one vehicle link costs a process at rest, by odometry rate. Prints figures; asserts nothing.

    mission-runner px4-sitl configs/px4_sih_tracking.yaml --px4-dir ~/PX4-Autopilot &   # or emulate
    python bench/link_bench.py --url udpin://0.0.0.0:14540 --system-id 1 --rates 50 25 10 0

For each rate: a fresh :class:`MavsdkVehicle` on the link (odometry, status texts, mode and armed
watches, as a flying vehicle has), the streams it never reads stopped, LOCAL_POSITION_NED asked
for at the rate (0: stopped), then the process's CPU (all its threads, MAVSDK's included) over
``--seconds``, as a share of one core, and how many samples came.
"""

from __future__ import annotations

import argparse
import asyncio
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pymavlink.dialects.v20 import common as mavlink

from mission_runner.runner.links import MavsdkVehicle, connected_vehicles


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


async def one_rate(url: str, system_id: int, rate_hz: float, seconds: float) -> str:
    async with (
        connected_vehicles([url], [system_id]) as systems,
        MavsdkVehicle(systems[system_id], system_id) as vehicle,
    ):
        await vehicle.quiet_unread_streams()
        await vehicle.request_interval(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, rate_hz)
        await asyncio.sleep(2.0)  # the new rate settles
        fed = [0]
        wake = vehicle.track.on_feed

        def counted() -> None:
            fed[0] += 1
            if wake is not None:
                wake()

        vehicle.track.on_feed = counted
        cpu0, wall0 = cpu_s(), time.monotonic()
        await asyncio.sleep(seconds)
        cpu1, wall1 = cpu_s(), time.monotonic()
        samples = fed[0] / (wall1 - wall0)
    share = 100 * (cpu1 - cpu0) / (wall1 - wall0)
    return f"{rate_hz:8g} {samples:10.1f} {share:12.2f}"


async def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--url", default="udpin://0.0.0.0:14540")
    parser.add_argument("--system-id", type=int, default=1)
    parser.add_argument("--rates", type=float, nargs="+", default=[50.0, 25.0, 10.0, 0.0])
    parser.add_argument("--seconds", type=float, default=20.0)
    options = parser.parse_args()
    print(f"{'asked Hz':>8} {'samples/s':>10} {'% of a core':>12}")
    for rate_hz in options.rates:
        print(await one_rate(options.url, options.system_id, rate_hz, options.seconds), flush=True)


if __name__ == "__main__":
    asyncio.run(main())

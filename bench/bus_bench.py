"""Benchmarks of the vehicle bus. Prints figures; asserts nothing about time.

    python bench/bus_bench.py                 # in-process and MQTT, 4 and 16 vehicles
    python bench/bus_bench.py --quick         # shorter runs
    python bench/bus_bench.py --kinds inprocess --vehicles 4 16 64

Each vehicle is one bus client (one MQTT connection) that, like a controller, publishes a
StepMessage every step (8 Hz, all vehicles at the same step boundary, the worst case for
bursts) and subscribes to every vehicle's steps, decoding each one. Reported per run:
deliveries per second (N vehicles x N subscribers x rate), end-to-end latency percentiles
from publish call to decoded message in the subscriber task, and drops. Everything runs in
one process and one event loop on loopback, against a private mosquitto on a free port.

A second table ("flood") publishes as fast as the bus accepts for a short time to show the
ceiling of one event loop.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mission_runner.bus import (  # noqa: E402
    Bus,
    BusConnectionError,
    BusKey,
    InProcessBus,
    MqttBus,
    StepMessage,
    Topics,
)

TOPICS = Topics.for_mission("bench")
#: Every message is signed and checked (HMAC-SHA256), as in a mission.
KEY = BusKey.generate("bench")


@dataclass
class Result:
    kind: str
    vehicles: int
    mode: str
    seconds: float
    published: int
    delivered: int
    dropped: int
    latencies_s: list[float]

    def row(self) -> str:
        rate = self.delivered / self.seconds
        if self.latencies_s:
            ordered = sorted(self.latencies_s)
            p50 = statistics.median(ordered) * 1e3
            p99 = ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] * 1e3
            worst = ordered[-1] * 1e3
            latency = f"{p50:8.3f} {p99:8.3f} {worst:8.3f}"
        else:
            latency = f"{'-':>8} {'-':>8} {'-':>8}"
        return (
            f"{self.kind:>9} {self.mode:>6} {self.vehicles:>4} {self.published:>9} "
            f"{self.delivered:>10} {rate:>11.0f} {latency} {self.dropped:>7}"
        )


HEADER = (
    f"{'bus':>9} {'mode':>6} {'N':>4} {'published':>9} {'delivered':>10} {'deliveries/s':>11} "
    f"{'p50 ms':>8} {'p99 ms':>8} {'max ms':>8} {'dropped':>7}"
)


async def run(
    make_buses: Callable[[int], tuple[list[Bus], list[Bus]]],
    kind: str,
    vehicles: int,
    *,
    rate_hz: float | None,
    seconds: float,
) -> Result:
    """N vehicles publish steps (paced at rate_hz, or flat out if None) and receive all.

    ``make_buses(n)`` returns the buses to open and the bus of each vehicle.
    """
    to_open, buses = make_buses(vehicles)
    latencies: list[float] = []
    published = 0
    delivered = 0
    async with contextlib.AsyncExitStack() as stack:
        for bus in to_open:
            await stack.enter_async_context(bus)
        subscriptions = [
            await stack.enter_async_context(bus.subscribe(TOPICS.all_steps(), queue_size=4096))
            for bus in buses
        ]
        stop = asyncio.Event()

        async def consume(index: int) -> None:
            nonlocal delivered
            async for _, message in subscriptions[index].messages(StepMessage):
                latencies.append(time.monotonic() - message.time_s)
                delivered += 1

        async def publish(vehicle_id: int, bus: Bus, start_s: float) -> None:
            nonlocal published
            k = 0
            while not stop.is_set():
                if rate_hz is not None:
                    # Wait for the next step boundary: all vehicles publish together.
                    await asyncio.sleep(max(0.0, start_s + k / rate_hz - time.monotonic()))
                    if stop.is_set():
                        break
                message = StepMessage(vehicle_id, k, time.monotonic(), 0.0, 0.1 * k, 0.0)
                try:
                    await bus.publish_message(TOPICS.step(vehicle_id), message, timeout=1.0)
                except BusConnectionError:
                    continue
                published += 1
                k += 1
                if rate_hz is None:
                    await asyncio.sleep(0)  # let consumers and the network run

        async with asyncio.TaskGroup() as group:
            consumers = [
                group.create_task(consume(i), name=f"consumer {i}") for i in range(vehicles)
            ]
            start_s = time.monotonic() + 0.05
            publishers = [
                group.create_task(publish(i + 1, bus, start_s), name=f"publisher {i + 1}")
                for i, bus in enumerate(buses)
            ]
            await asyncio.sleep(seconds)
            stop.set()
            await asyncio.gather(*publishers)
            # Let in-flight messages arrive: wait until deliveries stop growing.
            settled = -1
            while settled != delivered:
                settled = delivered
                await asyncio.sleep(0.2)
            for task in consumers:
                task.cancel()
        dropped = sum(subscription.dropped for subscription in subscriptions)
    return Result(kind, vehicles, "8 Hz" if rate_hz else "flood", seconds, published,
                  delivered, dropped, latencies)  # fmt: skip


async def main(arguments: argparse.Namespace) -> None:
    print(HEADER)

    def in_process_buses(count: int) -> tuple[list[Bus], list[Bus]]:
        # One in-process bus is the whole network; every vehicle uses it.
        bus = InProcessBus(key=KEY)
        return [bus], [bus] * count

    runs: list[tuple[str, Callable[[int], tuple[list[Bus], list[Bus]]]]] = []
    broker = None
    if "inprocess" in arguments.kinds:
        runs.append(("inprocess", in_process_buses))
    if "mqtt" in arguments.kinds:
        from tests.mosquitto import MosquittoBroker  # noqa: PLC0415 (needs mosquitto)

        directory = Path(tempfile.mkdtemp(prefix="bus-bench-"))
        broker = MosquittoBroker(directory)
        await broker.astart()
        port = broker.port

        def mqtt_buses(count: int) -> tuple[list[Bus], list[Bus]]:
            # One connection per vehicle, as on real vehicles.
            buses: list[Bus] = [
                MqttBus("127.0.0.1", port, key=KEY, client_id=f"bench-{count}-{i}", queue_size=4096)
                for i in range(count)
            ]
            return buses, buses

        runs.append(("mqtt", mqtt_buses))
    try:
        for kind, factory in runs:
            for vehicles in arguments.vehicles:
                result = await run(
                    factory, kind, vehicles, rate_hz=arguments.rate_hz, seconds=arguments.seconds
                )
                print(result.row(), flush=True)
        for kind, factory in runs:
            for vehicles in arguments.vehicles:
                result = await run(
                    factory, kind, vehicles, rate_hz=None, seconds=arguments.flood_seconds
                )
                print(result.row(), flush=True)
    finally:
        if broker is not None:
            await broker.astop()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kinds", nargs="+", default=["inprocess", "mqtt"],
                        choices=["inprocess", "mqtt"])  # fmt: skip
    parser.add_argument("--vehicles", nargs="+", type=int, default=[4, 16])
    parser.add_argument("--rate-hz", type=float, default=8.0)
    parser.add_argument("--seconds", type=float, default=10.0, help="paced run length")
    parser.add_argument("--flood-seconds", type=float, default=3.0)
    parser.add_argument("--quick", action="store_true", help="3 s paced, 1 s flood")
    args = parser.parse_args()
    if args.quick:
        args.seconds, args.flood_seconds = 3.0, 1.0
    asyncio.run(main(args))

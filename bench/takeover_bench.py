"""What a client-id takeover costs a vehicle on the bus. Prints figures; asserts nothing.

    python bench/takeover_bench.py                # 10 takeovers
    python bench/takeover_bench.py --takeovers 30

One vehicle bus client (with its last will, as a vehicle process has) publishes a StepMessage
every step (8 Hz); an observer subscribes to its steps and status. Every ``--every-s`` seconds
a stranger connects with the vehicle's client id and leaves at once: mosquitto drops the
vehicle and publishes its will, and the vehicle reconnects. Reported per takeover, from the
observer: the will's arrival after the stranger's connect call, the vehicle's restored status
after it, and the gap in its steps (the time between the last step before and the first after, and
the steps missing). Everything runs on loopback against a private anonymous mosquitto.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import aiomqtt  # noqa: E402

from mission_runner.bus import (  # noqa: E402
    BusError,
    BusKey,
    MqttBus,
    StepMessage,
    Topics,
    VehicleStatus,
    lost_vehicle_will,
)

TOPICS = Topics.for_mission("takeover-bench")
KEY = BusKey.generate("bench")
STEP_S = 0.125


async def fly(vehicle: MqttBus, stop: asyncio.Event, failed: list[int]) -> None:
    """Step messages on the step grid, as a controller sends them (dropped when they fail)."""
    loop = asyncio.get_running_loop()
    start_s, step = loop.time(), 0
    while not stop.is_set():
        message = StepMessage(2, step, time.time(), 0.0, 0.0, 0.0)
        try:
            await vehicle.publish_message(TOPICS.step(2), message, timeout=STEP_S / 2)
        except BusError:
            failed.append(step)
        step += 1
        await asyncio.sleep(max(start_s + step * STEP_S - loop.time(), 0.0))


async def main(arguments: argparse.Namespace) -> None:
    from tests.mosquitto import MosquittoBroker  # noqa: PLC0415 (needs mosquitto)

    broker = MosquittoBroker(Path(tempfile.mkdtemp(prefix="takeover-bench-")))
    await broker.astart()
    loop = asyncio.get_running_loop()
    arrivals: list[tuple[float, str, int]] = []  # (time, kind, step)
    will = lost_vehicle_will(TOPICS, 2, time_s=time.time())
    vehicle = MqttBus(broker.host, broker.port, key=KEY, client_id="bench-vehicle-2", will=will)
    observer = MqttBus(broker.host, broker.port, key=KEY, client_id="bench-observer")
    stop, failed, kicks = asyncio.Event(), [], []
    try:
        async with observer, observer.subscribe(f"{TOPICS.prefix}/vehicle/2/+") as heard:

            async def listen() -> None:
                async for topic, payload in heard:
                    now_s = loop.time()
                    if topic == TOPICS.step(2):
                        arrivals.append((now_s, "step", StepMessage.from_payload(payload).step))
                    else:
                        state = VehicleStatus.from_payload(payload).state
                        arrivals.append((now_s, "will" if state == "lost" else "status", 0))

            async with vehicle, asyncio.TaskGroup() as group:
                listening = group.create_task(listen())
                await vehicle.publish_message(
                    TOPICS.status(2), VehicleStatus(2, time.time(), "ready", 0, False, ""),
                    retain=True, timeout=2.0,
                )  # fmt: skip
                flying = group.create_task(fly(vehicle, stop, failed))
                for _ in range(arguments.takeovers):
                    await asyncio.sleep(arguments.every_s)  # the spacing of the attacks
                    # From the stranger's connect call: the will can reach the observer before
                    # the stranger has its CONNACK.
                    kicks.append(loop.time())
                    async with aiomqtt.Client(
                        broker.host, broker.port, identifier=vehicle.client_id
                    ):
                        pass
                await asyncio.sleep(arguments.every_s)
                stop.set()
                await flying
                listening.cancel()
    finally:
        await broker.astop()
    report(kicks, arrivals, failed, vehicle)


def report(kicks, arrivals, failed, vehicle) -> None:
    wills, restored, gaps, missing = [], [], [], []
    for kick_s in kicks:
        after = [a for a in arrivals if a[0] >= kick_s]
        before = [a for a in arrivals if a[0] < kick_s and a[1] == "step"]
        will = next((a[0] for a in after if a[1] == "will"), None)
        status = next((a[0] for a in after if a[1] == "status"), None)
        step = next((a for a in after if a[1] == "step"), None)
        if will is not None:
            wills.append(will - kick_s)
        if status is not None:
            restored.append(status - kick_s)
        if before and step is not None:
            gaps.append(step[0] - before[-1][0])
            missing.append(step[2] - before[-1][2] - 1)

    def ms(values: list[float]) -> str:
        if not values:
            return "none"
        return f"median {statistics.median(values) * 1e3:.0f} ms, max {max(values) * 1e3:.0f} ms"

    print(f"takeovers: {len(kicks)}; vehicle connections: {vehicle.connect_count}")
    print(f"will at the observer after the takeover: {ms(wills)} ({len(wills)} wills)")
    print(f"vehicle's status restored after the takeover: {ms(restored)}")
    print(f"gap in its steps at the observer: {ms(gaps)} (step period {STEP_S * 1e3:.0f} ms)")
    print(f"steps missing per takeover: {missing}; publishes that failed: {len(failed)}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--takeovers", type=int, default=10)
    parser.add_argument("--every-s", type=float, default=2.0)
    asyncio.run(main(parser.parse_args()))

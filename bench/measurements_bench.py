"""CPU of one step's measurements on a real bus: the range aid publishing them, the vehicles
receiving them. Prints figures; asserts nothing. Runs whatever ``mission_runner`` is on the path
(a range per message or a set per vehicle), so the same script measures an older tree:

    nice -n 5 python bench/measurements_bench.py                  # 300 steps at 20 Hz
    nice -n 5 python bench/measurements_bench.py --steps 100 --step-s 0.1

A private mosquitto on a free port (tests/mosquitto.py). Two processes, so that each one's CPU
(user + sys, all threads) is its own: the publisher draws each step's measurements for the four
vehicles of configs/paper_tracking_flyable.yaml (its UWB model; vehicle 1 senses the target) with
``step_measurements`` and hands them to one MqttBus signing as the range aid
(``publish_measurements``); the receiver holds four MqttBus clients, one per vehicle, each
subscribed to its own ranges and target topics as a controller is, and takes every message
through authentication and decoding. Reported per step: CPU to publish (measuring included)
and to receive (all four vehicles), messages and bytes on the wire.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

SCENARIO = Path(__file__).resolve().parent.parent / "configs" / "paper_tracking_flyable.yaml"
PREFIX = "enclosing/measurements-bench"


def cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def range_topic(topics: Any, vehicle_id: int) -> tuple[str, type]:
    """The vehicle's own ranges: one topic of sets, or a wildcard over one topic per peer."""
    from mission_runner import bus  # noqa: PLC0415 - whichever tree is on the path

    if hasattr(bus, "RangeSet"):
        return topics.ranges(vehicle_id), bus.RangeSet
    return topics.all_ranges(vehicle_id), bus.RangeMessage  # the tree before range sets


async def publish(port: int, steps: int, step_s: float) -> dict[str, float]:
    from mission_runner.bus import MqttBus, Sender, Topics  # noqa: PLC0415
    from mission_runner.checks import load_scenario  # noqa: PLC0415
    from mission_runner.sensors import UwbRanging  # noqa: PLC0415
    from mission_runner.world.world import publish_measurements, step_measurements  # noqa: PLC0415
    from tests.mosquitto import bus_test_key  # noqa: PLC0415

    scenario = load_scenario(SCENARIO)
    ids = [v.id for v in scenario.vehicles]
    topics = Topics(PREFIX)
    rng = np.random.default_rng(3)
    uwb = UwbRanging(scenario.sensors, len(ids), step_s)
    places = np.array([[*v.initial_position_m, -v.altitude_m] for v in scenario.vehicles])
    sensing = np.array([v.senses_target for v in scenario.vehicles])
    messages = payload_bytes = 0
    async with MqttBus("127.0.0.1", port, key=bus_test_key(), sender=Sender.ranges()) as bus:
        start_cpu, start_s = cpu_s(), time.monotonic()
        for k in range(steps):
            await asyncio.sleep(max(0.0, start_s + k * step_s - time.monotonic()))
            t_k = time.time()
            wobble = 0.5 * np.sin(0.1 * k + np.arange(len(ids)))[:, None]
            measured = step_measurements(
                k,
                t_k,
                ids=ids,
                topics=topics,
                positions_m=places + wobble,
                ranging=np.ones(len(ids), dtype=bool),
                tracking=sensing,
                target_m=[0.8 * k * step_s, 0.0],
                target_velocity_m_s=[0.8, 0.0],
                sensors=scenario.sensors,
                rng=rng,
                uwb=uwb,
            )
            await publish_measurements(bus, measured, timeout_s=1.0)
            messages += len(measured)
            payload_bytes += sum(len(message.to_payload()) for _, message in measured)
        cpu = cpu_s() - start_cpu
    return {"cpu_s": cpu, "messages": messages, "payload_bytes": payload_bytes}


async def receive(port: int) -> dict[str, float]:
    from mission_runner.bus import MqttBus, TargetObservation, Topics  # noqa: PLC0415
    from tests.mosquitto import bus_test_key  # noqa: PLC0415

    topics = Topics(PREFIX)
    received = {"messages": 0}

    async def drain(subscription: Any, message_type: type) -> None:
        async for _ in subscription.messages(message_type):
            received["messages"] += 1

    async with contextlib.AsyncExitStack() as stack:
        drains = []
        for vehicle_id in (1, 2, 3, 4):
            bus = await stack.enter_async_context(
                MqttBus("127.0.0.1", port, key=bus_test_key(), client_id=f"bench-{vehicle_id}")
            )
            for topic, message_type in (
                range_topic(topics, vehicle_id),
                (topics.target(vehicle_id), TargetObservation),
            ):
                subscription = await stack.enter_async_context(
                    bus.subscribe(topic, queue_size=100_000)
                )
                drains.append(asyncio.create_task(drain(subscription, message_type)))
        start_cpu = cpu_s()
        print("ready", flush=True)
        await asyncio.to_thread(sys.stdin.readline)  # the publisher is done
        await asyncio.sleep(1.0)  # the last step's messages on their way
        cpu = cpu_s() - start_cpu
        for task in drains:
            task.cancel()
        await asyncio.gather(*drains, return_exceptions=True)
    return {"cpu_s": cpu, "messages": received["messages"]}


def run(steps: int, step_s: float) -> None:
    from tests.mosquitto import MosquittoBroker  # noqa: PLC0415 - needs mosquitto

    with tempfile.TemporaryDirectory() as directory:
        broker = MosquittoBroker(Path(directory) / "mosquitto")
        broker.start()
        try:
            me = [sys.executable, __file__, "--port", str(broker.port)]
            receiver = subprocess.Popen(
                [*me, "--role", "receive"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
            )
            assert receiver.stdout is not None and receiver.stdin is not None
            assert receiver.stdout.readline().strip() == "ready"
            wall_s = time.monotonic()
            published = subprocess.run(
                [*me, "--role", "publish", "--steps", str(steps), "--step-s", str(step_s)],
                check=False,
                capture_output=True,
                text=True,
            )
            if published.returncode != 0:
                receiver.kill()
                raise SystemExit(f"the publisher failed:\n{published.stderr}")
            wall_s = time.monotonic() - wall_s
            out, _ = receiver.communicate("done\n", timeout=60)
        finally:
            broker.stop()
    sent = json.loads(published.stdout.splitlines()[-1])
    got = json.loads(out.splitlines()[-1])
    per_step_us = 1e6 / steps
    print(f"{steps} steps at {1 / step_s:g} Hz, 4 vehicles, {wall_s:.1f} s wall")
    print(
        f"publish: {sent['cpu_s'] * per_step_us:.0f} us CPU a step, "
        f"{sent['messages'] / steps:.1f} messages a step, "
        f"{sent['payload_bytes'] / steps:.0f} payload bytes a step (before signing)"
    )
    print(
        f"receive: {got['cpu_s'] * per_step_us:.0f} us CPU a step for the four vehicles "
        f"({got['cpu_s'] * per_step_us / 4:.0f} each), {got['messages']} of "
        f"{sent['messages']} messages received"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--step-s", type=float, default=0.05)
    parser.add_argument("--port", type=int)
    parser.add_argument("--role", choices=["publish", "receive"])
    args = parser.parse_args()
    if args.role == "publish":
        print(json.dumps(asyncio.run(publish(args.port, args.steps, args.step_s))))
    elif args.role == "receive":
        print(json.dumps(asyncio.run(receive(args.port))))
    else:
        if not math.isfinite(args.step_s) or args.step_s <= 0:
            parser.error("--step-s must be > 0")
        run(args.steps, args.step_s)


if __name__ == "__main__":
    main()

"""What flooding the control topic costs a swarm of processes. Prints figures; asserts nothing.

    python bench/flood_bench.py                          # none, big and flood, size-limited broker
    python bench/flood_bench.py --attacks big --no-limits

Each run flies ``configs/paper_tracking_flyable.yaml`` (``--steps`` steps) in process mode
(docs/flying.md): ``mission-runner emulate``, four ``mission-runner vehicle`` and ``mission-runner
ground`` on a private mosquitto that anyone may publish to (``--no-limits``: without
``broker-config``'s size limits). Once the ground shows a vehicle following, an outsider publishes
on the control topic: ``none``; ``big``, four 64 MiB payloads; ``flood``, 20,000 64-byte garbage
payloads and 20,000 empty ones. Per vehicle: steps by state, what its bus dropped by reason, and
the p99 of its step message's lateness after t_k; then the ground's line.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import csv
import json
import os
import re
import secrets
import sys
import tempfile
from pathlib import Path

import aiomqtt
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mission_runner.bus import AuthPolicy, Topics
from tests.mosquitto import MosquittoBroker
from tests.runner.flying import mqtt_scenario_file, swarm, wait_for

BIG_BYTES = 64 * 1024 * 1024
FLOOD = 20_000


async def outsider_attack(broker: MosquittoBroker, topic: str, kind: str) -> None:
    """The outsider's ``big`` or ``flood`` on ``topic`` (as tests/runner/test_bus_flood.py's)."""
    async with aiomqtt.Client(
        broker.host, broker.port, identifier="outsider", max_queued_outgoing_messages=0
    ) as client:
        if kind == "big":
            with contextlib.suppress(aiomqtt.MqttError):  # a size-limited broker disconnects
                for _ in range(4):
                    await client.publish(topic, os.urandom(BIG_BYTES), qos=1, timeout=30)
            return
        garbage = os.urandom(64)
        for n in range(FLOOD):
            await client.publish(topic, garbage, qos=0)
            await client.publish(topic, b"", qos=0)
            if n % 500 == 0:
                await asyncio.sleep(0)
        await client.publish(topic, garbage, qos=1, timeout=120)


def fly(attack: str, steps: int, limits: bool, directory: Path) -> None:
    broker = MosquittoBroker(directory / "mosquitto")
    if limits:
        from mission_runner.bus.broker import size_limits  # noqa: PLC0415

        with broker.config_path.open("a") as config:
            config.write("\n".join(size_limits(AuthPolicy().max_message_bytes)) + "\n")
    broker.start()
    try:
        scenario = mqtt_scenario_file(directory, broker, f"bench_{attack}", steps)
        data = yaml.safe_load(Path(scenario).read_text())
        with swarm(scenario, directory) as flying:
            seen: list[str] = []
            wait_for(flying.ground, r"vehicle \d: following", seen)
            if attack != "none":
                control = Topics.for_mission(data["name"]).control()
                asyncio.run(outsider_attack(broker, control, attack))
            rest, _ = flying.ground.communicate(timeout=600)
            for vehicle in flying.vehicles:
                vehicle.communicate(timeout=60)
    finally:
        broker.stop()
    print(f"{attack} ({'size-limited' if limits else 'unlimited'} broker), {steps} steps:")
    for number in range(1, 5):
        folder = directory / f"vehicle_{number}"
        rows = list(csv.DictReader((folder / "steps.csv").open()))
        states = dict(collections.Counter(row["state"] for row in rows))
        summary = json.loads((folder / "summary.json").read_text())
        dropped = {k: v for k, v in summary["bus_security"]["messages"].items() if v}
        late = summary["step_timing_after_t_k_s"]["message_sent"]
        print(f"  vehicle {number}: {states}; bus {dropped}; step message p99 {late['p99']:.3f} s")
    line = re.search(r"ground: mission \w+ over.*", "".join(seen) + rest)
    print(f"  {line.group(0) if line else 'ground: no result'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--attacks", nargs="+", default=["none", "big", "flood"])
    parser.add_argument("--steps", type=int, default=240)
    parser.add_argument("--no-limits", action="store_true")
    arguments = parser.parse_args()
    # Every process of the swarm signs with this bench's own key.
    os.environ.setdefault("MISSION_BUS_KEY", secrets.token_hex(32))
    for attack in arguments.attacks:
        with tempfile.TemporaryDirectory() as directory:
            fly(attack, arguments.steps, not arguments.no_limits, Path(directory))


if __name__ == "__main__":
    main()

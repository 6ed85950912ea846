"""The issue's two flooding attacks on a swarm of processes (``mission-runner emulate``, four
``vehicle`` processes and the ``ground`` station) over a real mosquitto that anyone may publish to,
with ``broker-config``'s size limits: an outsider publishes on the control topic, once the
formation is flying, either four 64 MiB payloads or 20,000 garbage and 20,000 empty messages.
Before, the first stalled the vehicles' odometry until they were declared lost, and the second
froze the formation for ~30 s while the ground said "4 done". Now every vehicle follows through
both, every process counts what it dropped, by reason, and the ground's verdict counts the steps
held on stale data. (The vehicles' own guard against oversized packets, for a broker without the
limits, is tests/bus/test_paho_reader.py's.)"""

import asyncio
import contextlib
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import aiomqtt
import pytest
import yaml

from mission_runner.bus import (
    AuthPolicy,
    BusAccess,
    MessageAuth,
    Sender,
    StepMessage,
    Topics,
    lost_vehicle_will,
    open_bus,
)
from mission_runner.bus.broker import size_limits, write_broker_config
from mission_runner.checks import load_scenario
from mission_runner.runner.process import flight_bus
from tests.mosquitto import MosquittoBroker, bus_test_key, free_loopback_port

from .flying import mqtt_scenario_file, swarm, wait_for

STEPS = 240  # 30 s of mission at T = 0.125 s
BIG_BYTES = 64 * 1024 * 1024
FLOOD = 20_000


async def attack(broker, topic, kind):
    """What the outsider publishes on ``topic``: ``big`` (four 64 MiB payloads) or ``flood``
    (``FLOOD`` 64-byte garbage payloads and as many empty ones, interleaved). Returns how many
    the broker took."""
    async with aiomqtt.Client(
        broker.host, broker.port, identifier="outsider", max_queued_outgoing_messages=0
    ) as client:
        if kind == "big":
            # The broker disconnects the sender at the first, before reading its payload: none
            # is acknowledged.
            acknowledged = 0
            with contextlib.suppress(aiomqtt.MqttError):
                for _ in range(4):
                    await client.publish(topic, os.urandom(BIG_BYTES), qos=1, timeout=10)
                    acknowledged += 1
            return acknowledged
        garbage = os.urandom(64)
        for n in range(FLOOD):
            await client.publish(topic, garbage, qos=0)
            await client.publish(topic, b"", qos=0)
            if n % 500 == 0:
                await asyncio.sleep(0)  # let paho write what is queued
        # A QoS 1 message after them all: acknowledged once the broker has taken every one.
        await client.publish(topic, garbage, qos=1, timeout=120)
        return 2 * FLOOD + 1


@pytest.fixture
def open_broker(tmp_path):
    """An anonymous mosquitto (anyone may publish, as on the issue's broker) with the size limits
    ``broker-config`` writes."""
    broker = MosquittoBroker(tmp_path / "mosquitto")
    with broker.config_path.open("a") as config:
        config.write("\n".join(size_limits(AuthPolicy().max_message_bytes)) + "\n")
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()


@pytest.mark.mavsdk
@pytest.mark.mqtt
@pytest.mark.slow
@pytest.mark.timeout(420)
@pytest.mark.parametrize("kind", ["big", "flood"])
def test_a_flood_on_the_control_topic_costs_the_formation_nothing(tmp_path, open_broker, kind):
    mosquitto = open_broker
    scenario = mqtt_scenario_file(tmp_path, mosquitto, f"flood_{kind}", STEPS)
    # The verdict bounds what the flood may cost: steps held or skipped on stale data.
    data = yaml.safe_load(Path(scenario).read_text())
    data["expect"]["steps_on_stale_data"] = {"max": 40}
    Path(scenario).write_text(yaml.safe_dump(data))
    control = Topics.for_mission(f"flood_{kind}").control()
    seen: list[str] = []
    with swarm(scenario, tmp_path) as flying:
        ground = flying.ground
        # Attack once the formation flies: the ground shows a vehicle following.
        wait_for(ground, r"vehicle \d: following", seen)
        taken = asyncio.run(attack(mosquitto, control, kind))
        rest, _ = ground.communicate(timeout=300)
        ground_out = "".join(seen) + rest
        outputs = [vehicle.communicate(timeout=60)[0] for vehicle in flying.vehicles]

    assert ground.returncode == 0, ground_out + flying.world_output
    assert re.search(r"4 vehicle\(s\) done, lost: none", ground_out), ground_out
    stale = re.search(r"held or skipped on stale or missing data: (\d+) of 960", ground_out)
    assert stale and int(stale.group(1)) <= 40, ground_out
    for number, (vehicle, output) in enumerate(zip(flying.vehicles, outputs, strict=True), 1):
        assert vehicle.returncode == 0, output
        following = re.search(rf"vehicle {number}: done, {STEPS} steps, (\d+) following", output)
        summary = json.loads((tmp_path / f"vehicle_{number}" / "summary.json").read_text())
        # What the other steps were (a target never observed is lost after 10 s: 81 following).
        assert following and int(following.group(1)) >= STEPS - 10, (
            f"{summary['steps_by_state']}\n{output}\n{ground_out}\n{flying.world_output}"
        )
        messages = summary["bus_security"]["messages"]
        if kind == "big":
            assert messages["oversized"] == 0, messages  # refused by the broker, unread
        else:
            # Counted by reason; mosquitto may drop some (QoS 0) for a client that falls behind.
            assert 0 < messages["malformed"] <= FLOOD + 1, messages
            assert 0 < messages["empty"] <= FLOOD, messages
            assert re.search(r"bus: dropped \d+ of \d+ messages \(.*malformed.*empty", output)
    assert taken == (0 if kind == "big" else 2 * FLOOD + 1)


# Another process: while it runs, the test's event loop (the vehicle's) reads nothing, so what it
# publishes waits at the broker and in the sockets, as behind a flood that arrives faster than it
# is read. Garbage on the control topic, then one genuine step message of vehicle 2.
OUTSIDER_AND_PEER = """
import sys
import paho.mqtt.client as mqtt
host, port, control, step_topic, count = sys.argv[1:6]
step = bytes.fromhex(sys.argv[6])
client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="outsider-and-peer")
client.max_queued_messages_set(0)
client.connect(host, int(port))
client.loop_start()
for _ in range(int(count)):
    client.publish(control, b"x" * 64, qos=0)
client.publish(step_topic, step, qos=1).wait_for_publish(timeout=60)
client.loop_stop()
client.disconnect()
"""


@pytest.mark.mqtt
@pytest.mark.asyncio
@pytest.mark.timeout(180)
async def test_a_step_message_is_not_held_back_behind_a_flood_on_the_control_topic(
    tmp_path, mosquitto
):
    """A vehicle process's connections as ``run_vehicle`` opens them: the control topic on one,
    the controller's topics on the other. A neighbour's step message sent after 20,000 garbage
    payloads on the control topic is read before (nearly) any of them: one connection would
    hand it over only after every one of them."""
    scenario = load_scenario(mqtt_scenario_file(tmp_path, mosquitto, "held_back", 16))
    topics = scenario.bus.topics(scenario.name)
    step = StepMessage(2, 0, 1.0, 0.0, 0.0, 0.0)
    sealed = MessageAuth(bus_test_key()).seal(Sender.vehicle(2), topics.step(2), step.to_payload())
    async with (
        open_bus(scenario.bus, sender=Sender.vehicle(1), client_id="v1-control") as bus,
        bus.subscribe(topics.control()),
        flight_bus(scenario, 1, bus) as flight,
        flight.subscribe(topics.step(2)) as steps,
    ):
        subprocess.run(
            [sys.executable, "-c", OUTSIDER_AND_PEER, mosquitto.host, str(mosquitto.port),
             topics.control(), topics.step(2), str(FLOOD), sealed.hex()],
            check=True,
            timeout=120,
        )  # fmt: skip
        _, got = await steps.receive_message(StepMessage, timeout=60)
        garbage_before_step = bus.auth_counters.malformed
    assert got == step
    assert garbage_before_step < FLOOD // 10, garbage_before_step


@pytest.mark.mqtt
@pytest.mark.asyncio
async def test_the_controllers_connection_logs_in_as_its_own_user(tmp_path):
    """On ``broker-config``'s broker, which binds client ids to logins (a login holds one
    connection): the controller's connection has its own login, so opening it does not take
    the vehicle's control connection (which would publish its last will: "lost")."""
    port = free_loopback_port()
    probe = MosquittoBroker(tmp_path / "probe", port=port)  # only for its host and the file
    scenario_file = mqtt_scenario_file(tmp_path, probe, "own_login", 16)
    scenario = load_scenario(scenario_file)
    topics = scenario.bus.topics(scenario.name)
    files = write_broker_config(
        tmp_path / "broker-config", topics, [1, 2, 3, 4], port=port, bind_address="127.0.0.1"
    )
    broker = MosquittoBroker(tmp_path / "broker", port=port, config_file=files.config)
    scenario = scenario.model_copy(
        update={"bus": scenario.bus.with_access(BusAccess(credentials_file=files.credentials))}
    )
    will = lost_vehicle_will(topics, 1, time_s=time.time())
    step = StepMessage(1, 0, 1.0, 0.0, 0.0, 0.0)
    await broker.astart()
    try:
        async with (
            open_bus(scenario.bus, sender=Sender.vehicle(2), client_id="v2") as peer,
            peer.subscribe(f"{topics.prefix}/vehicle/1/#") as vehicle_1,
            open_bus(scenario.bus, sender=Sender.vehicle(1), client_id="v1", will=will) as bus,
            flight_bus(scenario, 1, bus) as flight,
        ):
            await flight.publish_message(topics.step(1), step, timeout=5)
            topic, payload = await vehicle_1.receive(timeout=5)
    finally:
        await broker.astop()
    assert topic == topics.step(1), payload  # not vehicle 1's last will first
    assert StepMessage.from_payload(payload) == step

"""What the ground station concludes from a vehicle's last will, over a real mosquitto. The
vehicles here are bus clients that speak the handshake and report a status per step (as a
flying controller does) but fly nothing, so the ground's reading of wills is tested alone:
a vehicle whose client id someone took flies on and is not lost; one that died is, once it
has stayed silent for the ground's grace."""

import asyncio
import time

import aiomqtt
import pytest
import yaml

from mission_runner.bus import (
    ControlCommand,
    MqttBus,
    Sender,
    VehicleStatus,
    lost_vehicle_will,
)
from mission_runner.checks import load_scenario
from mission_runner.runner.handshake import next_command
from mission_runner.runner.process import run_ground
from tests.mosquitto import bus_test_key

from .flying import CONFIGS

pytestmark = pytest.mark.mqtt

STEPS = 6  # statuses each vehicle reports once the mission started


def scenario_on(broker, tmp_path):
    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["name"] = "wills"
    # Quick reconnects, so the grace after a will is short: 0.5 + 2 + 1 s.
    data["bus"] = {
        "kind": "mqtt",
        "mqtt": {
            "host": broker.host,
            "port": broker.port,
            "qos": 1,
            "reconnect_max_s": 0.5,
            "connect_timeout_s": 2.0,
        },
    }
    path = tmp_path / "wills.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_scenario(path)


class FakeVehicle:
    """A vehicle's bus client through the handshake: ready on the prepare, then one status per
    step after the start; ``at_step`` runs once at that step (the test's attack)."""

    def __init__(self, scenario, vehicle_id, bus):
        self.scenario, self.vehicle_id, self.bus = scenario, vehicle_id, bus
        self.topics = scenario.bus.topics(scenario.name)
        self.mission_id = None

    async def report(self, state, step=0, *, retain=False):
        status = VehicleStatus(
            self.vehicle_id, time.time(), state, step, state == "following", "",
            mission_id=self.mission_id, clock_rate=1.0,
        )  # fmt: skip
        topic = self.topics.status(self.vehicle_id)
        await self.bus.publish_message(topic, status, retain=retain, timeout=5.0)

    async def fly(self, at_step=None, steps=STEPS):
        async with self.bus.subscribe(self.topics.control()) as control:
            prepare = await next_command(control, {ControlCommand.PREPARE}, timeout_s=30)
            self.mission_id = prepare.mission_id
            await self.report("ready", retain=True)
            start = {ControlCommand.START}
            await next_command(control, start, mission_id=self.mission_id, timeout_s=30)
            for step in range(steps):
                if at_step is not None and step == at_step[0] and await at_step[1](self):
                    return  # it died
                await self.report("following", step)
            await self.report("done", steps, retain=True)


def vehicle_bus(scenario, vehicle_id, **overrides):
    topics = scenario.bus.topics(scenario.name)
    mqtt = scenario.bus.mqtt
    return MqttBus(
        mqtt.host,
        mqtt.port,
        key=bus_test_key(),
        sender=Sender.vehicle(vehicle_id),
        client_id=f"{scenario.name}-vehicle-{vehicle_id}",
        will=lost_vehicle_will(topics, vehicle_id, time_s=time.time()),
        **({"qos": 1, "reconnect_max_s": mqtt.reconnect_max_s} | overrides),
    )


async def take_over_its_client_id(vehicle):
    """A stranger (no login, no key) connects with the vehicle's client id and leaves: the broker
    drops the vehicle and publishes its will. The vehicle goes on once reconnected."""
    bus = vehicle.bus
    async with aiomqtt.Client(bus.host, bus.port, identifier=bus.client_id):
        pass
    await bus._wait_until(lambda: bus.connect_count == 2, 10.0, "the vehicle's reconnection")
    return False


async def die(vehicle):
    """The vehicle's socket closes without a goodbye (its process died): the broker publishes
    its will. Nothing of it is heard again (it publishes nothing more, and its bus's first
    reconnect would be a minute away)."""
    vehicle.bus._client._client._sock_close()
    return True


@pytest.mark.asyncio
@pytest.mark.timeout(120)
async def test_a_vehicle_whose_client_id_was_taken_is_not_lost_and_a_dead_one_is(
    mosquitto, tmp_path
):
    scenario = scenario_on(mosquitto, tmp_path)
    ids = [vehicle.id for vehicle in scenario.vehicles]
    assert ids == [1, 2, 3, 4]
    buses = {i: vehicle_bus(scenario, i) for i in (1, 2, 4)}
    buses[3] = vehicle_bus(scenario, 3, reconnect_initial_s=60.0, reconnect_max_s=60.0)
    attacks = {2: (2, take_over_its_client_id), 3: (2, die)}
    async with buses[1], buses[2], buses[3], buses[4], asyncio.TaskGroup() as group:
        ground = group.create_task(run_ground(scenario, start_delay_s=0.5, ready_timeout_s=30))
        for i in ids:
            group.create_task(FakeVehicle(scenario, i, buses[i]).fly(attacks.get(i)))
    outcome = ground.result()
    states = {i: status.state for i, status in outcome.statuses.items()}
    assert states == {1: "done", 2: "done", 3: "lost", 4: "done"}
    assert outcome.statuses[3].mission_id is None  # its will: the broker said it
    assert outcome.bus_drops == {2: 1}

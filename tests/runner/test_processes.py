"""A swarm as separate processes, as it flies for real: the emulator and its world
(``mission-runner emulate``), one ``mission-runner vehicle`` process per drone and a
``mission-runner ground`` station, talking only over a real mosquitto, each on its own clock
(UNIX time)."""

import asyncio
import re

import aiomqtt
import pytest

from mission_runner.bus import MqttBus, StepMessage, Topics
from tests.mosquitto import bus_test_key

from .flying import mqtt_scenario_file, swarm

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.slow]

STEPS = 320  # 40 s of mission at T = 0.125 s: converged with margin on a loaded machine


@pytest.mark.timeout(300)
def test_four_vehicle_processes_a_ground_station_and_the_emulator_over_mosquitto(
    tmp_path, mosquitto
):
    scenario = mqtt_scenario_file(tmp_path, mosquitto, "swarm_processes", STEPS)
    with swarm(scenario, tmp_path) as flying:
        ground, vehicles = flying.ground, flying.vehicles
        ground_out, _ = ground.communicate(timeout=260)
        outputs = [vehicle.communicate(timeout=60)[0] for vehicle in vehicles]
    sitl_out = flying.world_output

    assert ground.returncode == 0, ground_out
    assert re.search(r"mission \w+ over; 4 vehicle\(s\) done, lost: none", ground_out), ground_out
    for number, (vehicle, output) in enumerate(zip(vehicles, outputs, strict=True), start=1):
        assert vehicle.returncode == 0, output
        following = re.search(rf"vehicle {number}: done, {STEPS} steps, (\d+) following", output)
        assert following and int(following.group(1)) >= STEPS - 10, output
    error = re.search(r"formation centre ([0-9.]+) m from the target", sitl_out)
    assert error and float(error.group(1)) < 0.5, sitl_out


async def _take_over_client_id(broker, topics, vehicle_id, at_step):
    """Once vehicle ``vehicle_id`` flies step ``at_step``, connect to ``broker`` with no login and
    no bus key under that vehicle's client id, read from the broker's log (as someone watching the
    network would read it; it was ``<name>-vehicle-<id>`` to guess), and leave. Returns the id."""
    async with (
        MqttBus(broker.host, broker.port, key=bus_test_key(), client_id="test-watch") as watch,
        watch.subscribe(topics.step(vehicle_id)) as steps,
    ):
        while (await steps.receive_message(StepMessage, timeout=180))[1].step < at_step:
            pass
        connected = re.findall(r"New client connected from \S+ as (\S+) \(", broker.log_text())
        client_id = next(i for i in connected if f"-vehicle-{vehicle_id}" in i)
        async with aiomqtt.Client(broker.host, broker.port, identifier=client_id):
            pass
    return client_id


@pytest.mark.timeout(300)
def test_a_client_id_takeover_does_not_make_the_ground_declare_a_vehicle_lost(tmp_path, mosquitto):
    """The broker lets anyone in (a bench broker, no broker-config). Mid-flight, a stranger
    connects with vehicle 2's client id: mosquitto drops vehicle 2 and publishes its genuinely
    signed last will. Vehicle 2 reconnects and flies on, so the ground station reports every
    vehicle done (not vehicle 2 lost, exit 1), and counts the drop."""
    scenario = mqtt_scenario_file(tmp_path, mosquitto, "takeover", STEPS)
    topics = Topics.for_mission("takeover")
    with swarm(scenario, tmp_path) as flying:
        ground, vehicles = flying.ground, flying.vehicles
        stolen_id = asyncio.run(_take_over_client_id(mosquitto, topics, 2, at_step=80))
        ground_out, _ = ground.communicate(timeout=260)
        outputs = [vehicle.communicate(timeout=60)[0] for vehicle in vehicles]

    assert "closing old connection" in mosquitto.log_text()  # the takeover happened
    assert re.search(r"4 vehicle\(s\) done, lost: none", ground_out), ground_out
    assert "heard again, so not lost: 2 (1x)" in ground_out, ground_out
    assert ground.returncode == 0, ground_out
    assert re.search(rf"vehicle 2: done, {STEPS} steps", outputs[1]), outputs[1]
    assert re.fullmatch(r"takeover-vehicle-2-[0-9a-f]{16}", stolen_id)  # not to be guessed

"""A swarm as separate processes, as it flies for real: the emulator and its world
(``mission-runner emulate``), one ``mission-runner vehicle`` process per drone and a
``mission-runner ground`` station, talking only over a real mosquitto, each on its own clock
(UNIX time)."""

import re

import pytest

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

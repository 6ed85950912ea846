"""The operator's commands during a mission of vehicle processes (over a real mosquitto, against
the emulator): ``hold`` from ``mission-runner control``, then ``resume`` and ``land`` for one
vehicle typed into the ground station; and the ground station told to stop lands everyone."""

import re
import signal
import subprocess

import pytest

from .flying import mqtt_scenario_file, start, swarm, type_line, wait_for

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.slow]

STEPS = 400


def control(scenario, *arguments):
    operator = start("mission_runner.cli", "control", scenario, *arguments)
    output, _ = operator.communicate(timeout=30)
    assert operator.returncode == 0, output
    return output


@pytest.mark.timeout(300)
def test_hold_resume_and_landing_one_vehicle_from_the_operator(tmp_path, mosquitto):
    scenario = mqtt_scenario_file(tmp_path, mosquitto, "operator_control", STEPS)
    seen = []
    with swarm(
        scenario, tmp_path, ground_arguments=["--no-figures"], ground_stdin=subprocess.PIPE
    ) as flying:
        ground, vehicles = flying.ground, flying.vehicles
        wait_for(ground, r"vehicle 1: following", seen)
        assert "hold sent to every vehicle" in control(scenario, "hold", "--reason", "test")
        for number in range(1, 5):
            wait_for(ground, rf"vehicle {number}: held", seen)
        # The same commands typed into the ground station go out as control sends them.
        type_line(ground, "land 9")
        wait_for(ground, r"ground: error: vehicle 9 is not in the mission", seen)
        type_line(ground, "resume")
        wait_for(ground, r"ground: resume sent to every vehicle", seen)
        wait_for(ground, r"vehicle \d: following", seen)
        type_line(ground, "land 4")
        wait_for(ground, r"ground: land sent to vehicle 4", seen)
        wait_for(ground, r"vehicle 4: aborted", seen)
        rest, _ = ground.communicate(timeout=200)
        ground_out = "".join(seen) + rest
        outputs = [vehicle.communicate(timeout=60)[0] for vehicle in vehicles]

    assert re.search(r"3 vehicle\(s\) done, lost: 4 \(aborted: mission aborted", ground_out), (
        ground_out
    )
    for number, output in enumerate(outputs[:3], start=1):
        assert re.search(rf"vehicle {number}: done, {STEPS} steps", output), output
    assert vehicles[3].returncode != 0  # its mission did not finish: it was landed
    assert re.search(r"vehicle 4: aborted, .*\n  mission aborted by the ground station", outputs[3])


@pytest.mark.timeout(300)
def test_stopping_the_ground_station_lands_every_vehicle(tmp_path, mosquitto):
    scenario = mqtt_scenario_file(tmp_path, mosquitto, "operator_control", STEPS)
    with swarm(scenario, tmp_path, ground_arguments=["--no-figures"]) as flying:
        ground, vehicles = flying.ground, flying.vehicles
        wait_for(ground, r"vehicle 1: following", [])
        ground.send_signal(signal.SIGINT)
        ground.communicate(timeout=30)
        outputs = [vehicle.communicate(timeout=90)[0] for vehicle in vehicles]

    assert ground.returncode == 130
    for number, output in enumerate(outputs, start=1):
        assert re.search(
            rf"vehicle {number}: aborted, .*\n  mission aborted by the ground station: "
            "ground station stopped",
            output,
        ), output

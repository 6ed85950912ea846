"""The operator's commands during a mission of vehicle processes (over a real mosquitto, against
the emulator): ``hold`` then ``resume`` for the whole swarm, then ``land`` for one vehicle; and
the ground station told to stop lands everyone."""

import re
import signal

import pytest
import yaml

from tests.sitl.helpers import free_port_config

from .flying import CONFIGS, start

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.slow]

STEPS = 400


def scenario_file(tmp_path, broker):
    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["name"] = "operator_control"
    data["timing"]["steps"] = STEPS
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    path = tmp_path / "swarm.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def wait_for(process, pattern, seen):
    """Read ``process``'s output until a line matches ``pattern``; every line goes to ``seen``."""
    for line in process.stdout:
        seen.append(line)
        if re.search(pattern, line):
            return line
    raise AssertionError(f"no line matching {pattern!r}:\n{''.join(seen[-40:])}")


def control(scenario, *arguments):
    operator = start("mission_runner.cli", "control", scenario, *arguments)
    output, _ = operator.communicate(timeout=30)
    assert operator.returncode == 0, output
    return output


@pytest.mark.timeout(300)
def test_hold_resume_and_landing_one_vehicle_from_the_operator(tmp_path, mosquitto):
    scenario = str(scenario_file(tmp_path, mosquitto))
    ports = free_port_config(4, gcs=False)
    world = start(
        "mission_runner.cli",
        "emulate",
        scenario,
        "--no-gcs",
        "--api-port-base",
        str(ports.api_remote_base),
        "--api-local-port-base",
        str(ports.api_local_base),
    )
    processes, seen = [], []
    try:
        wait_for(world, "world on the mqtt bus", [])
        ground = start("mission_runner.cli", "ground", scenario, "--no-figures")
        vehicles = [
            start(
                "mission_runner.cli",
                "vehicle",
                scenario,
                "--id",
                str(i + 1),
                "--url",
                f"udpin://0.0.0.0:{ports.api_remote_base + i}",
                "--out",
                str(tmp_path / f"vehicle_{i + 1}"),
            )
            for i in range(4)
        ]
        processes = [ground, *vehicles]
        wait_for(ground, r"vehicle 1: following", seen)
        assert "hold sent to every vehicle" in control(scenario, "hold", "--reason", "test")
        for number in range(1, 5):
            wait_for(ground, rf"vehicle {number}: held", seen)
        control(scenario, "resume")
        wait_for(ground, r"vehicle \d: following", seen)
        assert "land sent to vehicle 4" in control(scenario, "land", "--vehicle", "4")
        wait_for(ground, r"vehicle 4: aborted", seen)
        rest, _ = ground.communicate(timeout=200)
        ground_out = "".join(seen) + rest
        outputs = [vehicle.communicate(timeout=60)[0] for vehicle in vehicles]
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
        world.send_signal(signal.SIGINT)
        world.communicate(timeout=30)

    assert re.search(r"3 vehicle\(s\) done, lost: 4 \(aborted: mission aborted", ground_out), (
        ground_out
    )
    for number, output in enumerate(outputs[:3], start=1):
        assert re.search(rf"vehicle {number}: done, {STEPS} steps", output), output
    assert vehicles[3].returncode != 0  # its mission did not finish: it was landed
    assert re.search(r"vehicle 4: aborted, .*\n  mission aborted by the ground station", outputs[3])


@pytest.mark.timeout(300)
def test_stopping_the_ground_station_lands_every_vehicle(tmp_path, mosquitto):
    scenario = str(scenario_file(tmp_path, mosquitto))
    ports = free_port_config(4, gcs=False)
    world = start(
        "mission_runner.cli",
        "emulate",
        scenario,
        "--no-gcs",
        "--api-port-base",
        str(ports.api_remote_base),
        "--api-local-port-base",
        str(ports.api_local_base),
    )
    processes, seen = [], []
    try:
        wait_for(world, "world on the mqtt bus", [])
        ground = start("mission_runner.cli", "ground", scenario, "--no-figures")
        vehicles = [
            start(
                "mission_runner.cli",
                "vehicle",
                scenario,
                "--id",
                str(i + 1),
                "--url",
                f"udpin://0.0.0.0:{ports.api_remote_base + i}",
                "--out",
                str(tmp_path / f"vehicle_{i + 1}"),
            )
            for i in range(4)
        ]
        processes = [ground, *vehicles]
        wait_for(ground, r"vehicle 1: following", seen)
        ground.send_signal(signal.SIGINT)
        ground.communicate(timeout=30)
        outputs = [vehicle.communicate(timeout=90)[0] for vehicle in vehicles]
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
        world.send_signal(signal.SIGINT)
        world.communicate(timeout=30)

    assert ground.returncode == 130
    for number, output in enumerate(outputs, start=1):
        assert re.search(
            rf"vehicle {number}: aborted, .*\n  mission aborted by the ground station: "
            "ground station stopped",
            output,
        ), output

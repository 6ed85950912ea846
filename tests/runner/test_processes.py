"""A swarm as separate processes, as it flies for real: the emulator and its world
(``mission-runner emulate``), one ``mission-runner vehicle`` process per drone and a
``mission-runner ground`` station, talking only over a real mosquitto, each on its own clock
(UNIX time)."""

import re
import signal

import pytest
import yaml

from tests.sitl.helpers import free_port_config

from .flying import CONFIGS, start

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.slow]

STEPS = 320  # 40 s of mission at T = 0.125 s: converged with margin on a loaded machine


def scenario_file(tmp_path, broker):
    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["name"] = "swarm_processes"
    data["timing"]["steps"] = STEPS
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    path = tmp_path / "swarm.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.timeout(300)
def test_four_vehicle_processes_a_ground_station_and_the_emulator_over_mosquitto(
    tmp_path, mosquitto
):
    scenario = str(scenario_file(tmp_path, mosquitto))
    ports = free_port_config(4, gcs=False)
    sitl = start(
        "mission_runner.cli",
        "emulate",
        scenario,
        "--no-gcs",
        "--api-port-base",
        str(ports.api_remote_base),
        "--api-local-port-base",
        str(ports.api_local_base),
    )
    processes = []
    try:
        for line in sitl.stdout:  # wait for the world to be up
            if "world on the mqtt bus" in line:
                break
        ground = start("mission_runner.cli", "ground", scenario)
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
        ground_out, _ = ground.communicate(timeout=260)
        outputs = [vehicle.communicate(timeout=60)[0] for vehicle in vehicles]
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
        sitl.send_signal(signal.SIGINT)
        sitl_out, _ = sitl.communicate(timeout=30)

    assert ground.returncode == 0, ground_out
    assert re.search(r"mission \w+ over; 4 vehicle\(s\) done, lost: none", ground_out), ground_out
    for number, (vehicle, output) in enumerate(zip(vehicles, outputs, strict=True), start=1):
        assert vehicle.returncode == 0, output
        following = re.search(rf"vehicle {number}: done, {STEPS} steps, (\d+) following", output)
        assert following and int(following.group(1)) >= STEPS - 10, output
    error = re.search(r"formation centre ([0-9.]+) m from the target", sitl_out)
    assert error and float(error.group(1)) < 0.5, sitl_out

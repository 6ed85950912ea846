"""``mission-runner emulate``: a mission's vehicles, target and UWB ranging for controllers in other
processes, over a real mosquitto, in UNIX time, started by a start command on the bus."""

import asyncio
import math
import os
import signal
import subprocess
import sys
import time

import pytest
import yaml

from mission_runner.bus import (
    MissionControl,
    MqttBus,
    RangeSet,
    TargetObservation,
    Topics,
)
from tests.mosquitto import bus_test_key
from tests.runner.flying import CONFIGS
from tests.sitl.helpers import free_port_config

pytestmark = [pytest.mark.mqtt, pytest.mark.asyncio]

STEP_S = 0.125


def scenario_file(tmp_path, broker):
    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["name"] = "world_process"
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    path = tmp_path / "scenario.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.timeout(60)
async def test_world_process_publishes_ranges_on_the_unix_step_grid_after_start(
    tmp_path, mosquitto
):
    ports = free_port_config(4, gcs=False)
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mission_runner.cli",
            "emulate",
            str(scenario_file(tmp_path, mosquitto)),
            "--api-port-base",
            str(ports.api_remote_base),
            "--api-local-port-base",
            str(ports.api_local_base),
            "--no-gcs",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    topics = Topics("enclosing/world_process")
    try:
        async with (
            MqttBus(
                mosquitto.host, mosquitto.port, key=bus_test_key(), client_id="test-ground"
            ) as bus,
            bus.subscribe(topics.all_ranges(), queue_size=10_000) as ranges,
            bus.subscribe(topics.all_targets(), queue_size=10_000) as targets,
        ):
            for _ in range(20):  # log lines come first; the banner says when the world is up
                line = await asyncio.to_thread(process.stdout.readline)
                if b"world on the mqtt bus" in line or not line:
                    break
            assert b"world on the mqtt bus" in line, line
            start_s = math.ceil((time.time() + 1.0) / STEP_S) * STEP_S
            await bus.publish_message(topics.control(), MissionControl("start", start_s), timeout=5)
            _, first = await ranges.receive_message(RangeSet, timeout=10)
            _, target = await targets.receive_message(TargetObservation, timeout=10)
    finally:
        process.send_signal(signal.SIGINT)
        output = await asyncio.to_thread(process.communicate, timeout=20)
    assert process.returncode == 0, output
    assert first.step is not None
    assert first.time_s == pytest.approx(start_s + first.step * STEP_S, abs=1e-6)
    assert abs(first.time_s - time.time()) < 5.0  # UNIX time, not simulated seconds
    assert target.vehicle_id == 1  # only vehicle 1 senses the target

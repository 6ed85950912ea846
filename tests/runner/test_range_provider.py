"""The GPS-based range provider (a simulation aid for vehicles without UWB) against emulated PX4
vehicles reached on their GCS link, publishing over a real mosquitto."""

import math
import time

import numpy as np
import pytest

from mission_runner.bus import MqttBus, RangeMessage, TargetObservation
from mission_runner.config import validate_scenario
from mission_runner.runner.ranges import run_range_provider
from sitl.config import ClockConfig, EmulatorConfig
from sitl.emulator import Emulator
from tests.sitl.helpers import free_port_config

from .flying import load

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.asyncio]

STEP_S = 0.125
PLACES = [(0.0, 0.0), (3.0, 4.0), (-6.0, 8.0)]


def scenario(broker):
    data = load("paper_tracking_flyable").model_dump(mode="json")
    data["vehicles"] = data["vehicles"][:3]
    for vehicle, (north, east) in zip(data["vehicles"], PLACES, strict=True):
        vehicle["initial_position_m"] = [north, east]
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    return validate_scenario(data)


@pytest.mark.timeout(60)
async def test_ranges_from_gps_match_the_true_distances_on_the_unix_step_grid(mosquitto):
    mission = scenario(mosquitto)
    ports = free_port_config(3, gcs=True)
    config = EmulatorConfig(
        vehicles=3,
        ports=ports,
        clock=ClockConfig(speed=1.0),
        placement={"positions": [{"north_m": n, "east_m": e} for n, e in PLACES]},
    )
    topics = mission.bus.topics(mission.name)
    async with (
        Emulator(config),
        MqttBus(mosquitto.host, mosquitto.port, client_id="listener") as bus,
        bus.subscribe(topics.all_ranges(), queue_size=10_000) as ranges,
        bus.subscribe(topics.all_targets(), queue_size=10_000) as targets,
    ):
        start_s = math.ceil((time.time() + 2.0) / STEP_S) * STEP_S
        done = await run_range_provider(
            mission, [f"udpin://0.0.0.0:{ports.gcs_remote_port}"], steps=8, start_s=start_s
        )
        assert done == 8
        measured = [m for _, m in ranges.drain_messages(RangeMessage)]
        observed = [m for _, m in targets.drain_messages(TargetObservation)]
    assert {m.step for m in measured} == set(range(8))
    for message in measured:
        assert message.time_s == pytest.approx(start_s + message.step * STEP_S)
        here, there = PLACES[message.vehicle_id - 1], PLACES[message.peer_id - 1]
        assert message.range_m == pytest.approx(math.dist(here, there), abs=0.05)
    assert observed and {m.vehicle_id for m in observed} == {1}
    # The virtual target starts at the scenario's origin and moves at 0.8 m/s north.
    first = observed[0]
    target_north = 0.8 * (first.time_s - start_s)
    assert first.range_m == pytest.approx(np.hypot(*PLACES[0]) + target_north, abs=0.05)
    assert first.velocity_north_m_s == pytest.approx(0.8, abs=1e-3)

"""The range aid (a simulation aid for vehicles without UWB) against emulated PX4 vehicles, from
their GPS on the GCS link or from their SIH-like ground-truth stream, publishing over a real
mosquitto once the ground station's start arrives."""

import math
import time

import numpy as np
import pytest

from mission_runner.bus import (
    ControlCommand,
    MissionControl,
    MqttBus,
    RangeMessage,
    TargetObservation,
)
from mission_runner.config import validate_scenario
from mission_runner.runner.ranges import run_range_provider
from sitl.config import ClockConfig, EmulatorConfig
from sitl.emulator import Emulator
from tests.mosquitto import bus_test_key
from tests.sitl.helpers import free_port_config, free_truth_stream

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


async def fly_aid(mosquitto, *, source, truth=False, truth_rate_hz=100.0):
    """Run the aid for 8 steps against three parked emulated vehicles; returns the start time,
    the aid's stats and what it published."""
    mission = scenario(mosquitto)
    ports = free_port_config(3, gcs=True)
    config = EmulatorConfig(
        vehicles=3,
        ports=ports,
        clock=ClockConfig(speed=1.0),
        placement={"positions": [{"north_m": n, "east_m": e} for n, e in PLACES]},
        truth_stream=free_truth_stream(3, ports) if truth else {},
    )
    topics = mission.bus.topics(mission.name)
    async with (
        Emulator(config),
        MqttBus(mosquitto.host, mosquitto.port, key=bus_test_key(), client_id="listener") as bus,
        bus.subscribe(topics.all_ranges(), queue_size=10_000) as ranges,
        bus.subscribe(topics.all_targets(), queue_size=10_000) as targets,
    ):
        start_s = math.ceil((time.time() + 2.0) / STEP_S) * STEP_S
        # Retained, as the aid may subscribe after the ground station spoke.
        start = MissionControl(ControlCommand.START, start_s, mission_id="m1")
        await bus.publish_message(topics.control(), start, retain=True, timeout=5.0)
        stats = await run_range_provider(
            mission,
            source=source,
            urls=[f"udpin://0.0.0.0:{ports.gcs_remote_port}"],
            truth_port_base=config.truth_stream.remote_base,
            truth_rate_hz=truth_rate_hz,
            steps=8,
        )
        await bus.publish(topics.control(), b"", retain=True, timeout=5.0)
        # The aid returns once it has published; the broker may still be delivering the last.
        measured = [
            (await ranges.receive_message(RangeMessage, timeout=5.0))[1]
            for _ in range(stats.ranges)
        ]
        observed = [m for _, m in targets.drain_messages(TargetObservation)]
    return start_s, stats, measured, observed


@pytest.mark.timeout(60)
@pytest.mark.parametrize("source", ["gps", "sih"])
async def test_ranges_match_the_true_distances_on_the_step_grid(mosquitto, source):
    start_s, stats, measured, observed = await fly_aid(
        mosquitto, source=source, truth=source == "sih"
    )
    assert stats.steps == 8
    assert stats.ranges == len(measured) == 8 * 6
    assert stats.missing_vehicles == 0
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
    # The truth recorded for scoring: every vehicle at its place at every step.
    assert [sample.step for sample in stats.truth] == list(range(8))
    for sample in stats.truth:
        assert sample.alive.all()
        assert sample.positions_m == pytest.approx(np.array(PLACES), abs=0.05)


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("asked_hz", "low_hz", "high_hz"), [(None, 15, 35), (100.0, 40, 130)])
async def test_the_aid_asks_the_simulator_for_ground_truth_fast_enough(
    mosquitto, asked_hz, low_hz, high_hz
):
    """SIH (and the emulator's truth stream, like it) sends 25 Hz of ground truth; each step's
    ranges wait for the first sample after t_k, so the aid asks for more (SET_MESSAGE_INTERVAL
    on the truth link) unless told not to. (The emulator streams at most at its physics rate,
    50 Hz here.)"""
    _, stats, measured, _ = await fly_aid(
        mosquitto, source="sih", truth=True, truth_rate_hz=asked_hz
    )
    assert stats.ranges == len(measured) == 8 * 6
    assert set(stats.position_rates_hz) == {1, 2, 3}
    for rate in stats.position_rates_hz.values():
        assert low_hz < rate < high_hz

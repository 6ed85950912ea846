"""The flyable tracking mission over a real mosquitto, with the broker killed mid-mission.

Every vehicle has its own MQTT client. While the broker is down the vehicles hear nobody: they
stop following the law and hold (no flyaway on stale data); when it is back the clients reconnect
with backoff, re-subscribe, and the formation converges again.
"""

import asyncio

import numpy as np
import pytest

from mission_runner.config import validate_scenario
from mission_runner.runner.mission import fly
from mission_runner.sim.metrics import run_metrics

from .flying import free_ports, load

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.slow]

KILL_AT, RESTART_AT, STEPS = 280, 300, 560


def mqtt_scenario(broker, steps):
    data = load("paper_tracking_flyable").model_dump(mode="json")
    data["timing"]["steps"] = steps
    data["bus"] = {
        "kind": "mqtt",
        "mqtt": {"host": broker.host, "port": broker.port, "reconnect_max_s": 0.5},
    }
    return validate_scenario(data)


@pytest.mark.asyncio
@pytest.mark.timeout(300)
async def test_broker_restart_mid_mission_holds_then_recovers(mosquitto):
    scenario = mqtt_scenario(mosquitto, STEPS)
    states, outage = {}, []

    def on_progress(progress):
        states[progress.step] = progress.states
        if progress.step == KILL_AT:
            outage.append(asyncio.get_running_loop().create_task(mosquitto.akill()))
        if progress.step == RESTART_AT:
            outage.append(asyncio.get_running_loop().create_task(mosquitto.astart()))

    outcome = await fly(scenario, emulator_overrides=free_ports(scenario), on_progress=on_progress)
    await asyncio.gather(*outage)
    metrics = {key: value[0] for key, value in run_metrics(outcome.result).items()}

    held = [k for k, by_vehicle in states.items() if "holding" in by_vehicle.values()]
    assert held and min(held) >= KILL_AT and max(held) < STEPS - 100, held
    # No flyaway: while holding, every vehicle stayed close to where the formation was.
    result = outcome.result
    positions = result.positions_m[0, KILL_AT : max(held) + 1]
    spread = np.linalg.norm(positions - result.target_m[KILL_AT : max(held) + 1, None], axis=-1)
    assert spread.max() < 2 * scenario.algorithm.radius_m + 3.0
    assert metrics["vehicles_in_formation_at_end"] == 4
    assert metrics["final_tracking_error_m"] < 0.1
    assert metrics["vehicles_disarmed_at_end"] == 4

"""The flyable tracking mission over a real mosquitto, with the broker killed mid-mission, in
lockstep and at real time (1x: the outage is 5 s of wall time while the vehicles fly on).

Every vehicle has its own MQTT client. While the broker is down the vehicles hear nobody: they
stop following the law and hold (no flyaway on stale data); when it is back the clients reconnect
with backoff, re-subscribe, and the formation converges again. No vehicle is declared lost.
"""

import asyncio

import numpy as np
import pytest

from mission_runner.checks import validate_scenario
from mission_runner.metrics import run_metrics
from mission_runner.runner.mission import fly

from .flying import free_ports, load

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.slow]

STEPS = 560
START_STEPS = 8  # the first second


def mqtt_scenario(broker, steps, clock="lockstep"):
    data = load("paper_tracking_flyable").model_dump(mode="json")
    data["timing"]["steps"] = steps
    data["flight"]["clock"] = clock
    data["bus"] = {
        "kind": "mqtt",
        "mqtt": {"host": broker.host, "port": broker.port, "reconnect_max_s": 0.5},
    }
    return validate_scenario(data)


@pytest.mark.asyncio
@pytest.mark.timeout(300)
# Killed once converged; at 1x the broker stays down 5 s (40 steps): the target moves on 4 m
# meanwhile, and the formation needs ~250 steps to close that gap and converge again.
# Converged again: lockstep is exact; at real time the final error also depends on how loaded
# the machine is (0.02 m idle; with two busy loops on both cores 0.04-0.12 m, 1.7 m before each
# step's measurements were published at once; 0.18 m on a loaded CI machine then).
@pytest.mark.parametrize(
    ("clock", "kill_at", "outage_steps", "final_error_m"),
    [("lockstep", 280, 20, 0.1), ("realtime", 200, 40, 0.25)],
)
async def test_broker_restart_mid_mission_holds_then_recovers(
    mosquitto, clock, kill_at, outage_steps, final_error_m
):
    scenario = mqtt_scenario(mosquitto, STEPS, clock)
    restart_at = kill_at + outage_steps
    states, outage = {}, []

    def on_progress(progress):
        states[progress.step] = progress.states
        # At real time a step can be skipped: act on the first step at or past each mark.
        if progress.step >= kill_at and not outage:
            outage.append(asyncio.get_running_loop().create_task(mosquitto.akill()))
        elif progress.step >= restart_at and len(outage) == 1:
            outage.append(asyncio.get_running_loop().create_task(mosquitto.astart()))

    outcome = await fly(scenario, emulator_overrides=free_ports(scenario), on_progress=on_progress)
    await asyncio.gather(*outage)
    metrics = {key: value[0] for key, value in run_metrics(outcome.result).items()}

    assert not [k for k, by_vehicle in states.items() if "lost" in by_vehicle.values()]
    held = [k for k, by_vehicle in states.items() if "holding" in by_vehicle.values()]
    # Before the outage a vehicle may hold only in the first second (steps 0-3 once on a loaded
    # CI machine: its first fresh inputs, or its OFFBOARD seen, not in yet).
    assert [k for k in held if k < kill_at] == [k for k in held if k < START_STEPS], held
    assert held and kill_at <= max(held) < STEPS - 100, held
    # No flyaway: while holding, every vehicle stayed close to where the formation was.
    result = outcome.result
    positions = result.positions_m[0, kill_at : max(held) + 1]
    spread = np.linalg.norm(positions - result.target_m[kill_at : max(held) + 1, None], axis=-1)
    assert spread.max() < 2 * scenario.algorithm.radius_m + 3.0
    assert metrics["vehicles_in_formation_at_end"] == 4
    assert metrics["final_tracking_error_m"] < final_error_m
    assert metrics["vehicles_disarmed_at_end"] == 4

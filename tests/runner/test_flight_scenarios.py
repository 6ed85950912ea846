"""Every bundled flight scenario, flown in lockstep through MAVSDK over UDP against the emulator,
must meet its own ``expect:`` block. The scenarios are data; this file only flies them."""

import pytest

from mission_runner.metrics import check_expectations, run_metrics
from mission_runner.runner.mission import fly

from .flying import flight_configs, free_ports, load

pytestmark = [pytest.mark.mavsdk, pytest.mark.slow]


def test_there_are_flight_scenarios():
    assert {"paper_tracking_flyable", "narrow_passage_flight", "link_lost_flight"} <= set(
        flight_configs()
    )


@pytest.mark.asyncio
@pytest.mark.timeout(240)
@pytest.mark.parametrize("name", flight_configs())
async def test_flight_scenario_meets_its_expectations(name):
    scenario = load(name)
    assert scenario.expect, f"{name} has no expect: block"
    outcome = await fly(scenario, emulator_overrides=free_ports(scenario))
    metrics = {key: value[0] for key, value in run_metrics(outcome.result).items()}
    assert check_expectations(scenario.expect, metrics) == [], metrics

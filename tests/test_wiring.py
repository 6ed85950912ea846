"""Scenario -> emulator settings: the physics rate a flight's emulator runs at; the pairs the
radios range under a sparse graph."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mission_runner.checks import load_scenario
from mission_runner.wiring import RangingGraph, emulator_config, neighbour_graph, physics_rate_hz

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize(
    ("step_s", "mode", "rate_hz"),
    [
        (0.125, "lockstep", 40.0),
        (0.125, "realtime", 200.0),
        (0.07, "lockstep", 3 / 0.07),  # 40 Hz does not divide 70 ms: 42.86 Hz does
        (0.0033, "realtime", 1 / 0.0033),  # never below one step per T
    ],
)
def test_the_physics_step_divides_t_at_the_clocks_lowest_rate(step_s, mode, rate_hz):
    assert physics_rate_hz(step_s, mode) == pytest.approx(rate_hz)


@pytest.mark.parametrize(("mode", "rate_hz"), [("lockstep", 40.0), ("realtime", 200.0)])
def test_a_flights_emulator_runs_at_its_clocks_rate_unless_the_scenario_sets_one(mode, rate_hz):
    scenario = load_scenario(CONFIGS / "paper_tracking_flyable.yaml")
    clock = {"mode": mode}
    assert emulator_config(scenario, clock=clock).physics.rate_hz == rate_hz
    chosen = emulator_config(scenario, clock=clock, physics={"rate_hz": 100.0})
    assert chosen.physics.rate_hz == 100.0


def test_a_ring_ranges_its_edges_and_the_one_that_closes_it_over_the_planned_loss():
    scenario = load_scenario(CONFIGS / "ring_enclosing.yaml")  # six on a ring, index 3 lost
    ranging = RangingGraph.of(scenario)
    assert ranging is not None and ranging.ring
    closing = np.zeros((6, 6), dtype=bool)
    closing[2, 4] = closing[4, 2] = True
    assert np.array_equal(ranging.frame, neighbour_graph(scenario) | closing)
    live = np.array([True, True, True, False, True, True])
    among = ranging.among(live)
    assert among[2, 4] and not among[3].any() and not among[:, 3].any()
    assert RangingGraph.of(load_scenario(CONFIGS / "paper_tracking.yaml")) is None

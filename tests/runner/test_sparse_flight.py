"""A ring graph flown through MAVSDK over UDP against the emulator in lockstep: the radios range
only ring edges, the controllers couple only with their ring neighbours, and after a vehicle is
killed its two neighbours notice it from what they hear (its step messages stop) and close the
ring over it. ``configs/ring_enclosing_flyable.yaml`` itself, in full, meets its ``expect:``
block in ``test_flight_scenarios.py``; here it is flown shortened, the loss brought forward."""

import math

import pytest
import yaml

from mission_runner.checks import parse_scenario
from mission_runner.runner.mission import fly

from .flying import CONFIGS, free_ports

pytestmark = [pytest.mark.mavsdk, pytest.mark.slow]

LOST_ID, LOST_AT = 4, 100


def shortened(steps=200):
    data = yaml.safe_load((CONFIGS / "ring_enclosing_flyable.yaml").read_text())
    data["timing"]["steps"] = steps
    data["events"] = [{"kind": "vehicle_lost", "vehicle": LOST_ID, "at_step": LOST_AT}]
    data.pop("expect")
    return parse_scenario(yaml.safe_dump(data), source="ring_shortened.yaml")


def ring_neighbours(ids):
    """Each id's two neighbours on the ring of ``ids`` in their order."""
    return {i: {ids[n - 1], ids[(n + 1) % len(ids)]} for n, i in enumerate(ids)}


@pytest.mark.asyncio
@pytest.mark.timeout(240)
async def test_a_ring_flies_ranging_its_edges_and_closes_over_a_lost_vehicle():
    scenario = shortened()
    ids = [vehicle.id for vehicle in scenario.vehicles]
    outcome = await fly(scenario, emulator_overrides=free_ports(scenario))
    before = ring_neighbours(ids)
    after = {LOST_ID: set(), **ring_neighbours([i for i in ids if i != LOST_ID])}
    timeout = scenario.flight.member_timeout_steps
    # Its last step message: killed at t_k, its odometry sample of t_k may or may not have left
    # first (the same instant), and without it there is no step-k message.
    last_sent = max(r.step for r in outcome.records[LOST_ID] if not math.isnan(r.odometry_m[0]))
    assert LOST_AT - 1 <= last_sent <= LOST_AT
    closing = {(3, 5), (5, 3)}
    ranged, used = set(), set()
    for vehicle_id, records in outcome.records.items():
        for record in records:
            peers = set(record.ranges_m) - {0}
            # Killed at t_k after its radio's round of that step: the ring's radios close at k + 1.
            allowed = before[vehicle_id] if record.step <= LOST_AT else after[vehicle_id]
            assert peers <= allowed, (vehicle_id, record.step, peers)
            ranged |= {(vehicle_id, peer, record.step) for peer in peers}
            neighbours = set(record.neighbours_used) - {0}
            # The controllers close the ring from what they hear: no step message from the lost
            # vehicle for member_timeout_steps. Until then they keep to the ring they had.
            heard_lost = record.step <= last_sent + timeout or vehicle_id == LOST_ID
            assert neighbours <= (before if heard_lost else after)[vehicle_id], (
                vehicle_id,
                record.step,
                neighbours,
            )
            used |= {(vehicle_id, peer, record.step) for peer in neighbours}
    assert {(i, j) for i, j, k in ranged if k > LOST_AT} >= closing
    closed_at = min(k for i, j, k in used if (i, j) in closing)
    assert last_sent + timeout < closed_at <= last_sent + timeout + 2
    survivors = {i: v for i, v in outcome.vehicles.items() if i != LOST_ID}
    assert all(v["state"] == "done" for v in survivors.values()), outcome.vehicles
    assert outcome.vehicles[LOST_ID]["state"] == "lost"

"""Shared ranges (``EnclosingParams.shared_ranges``): each pair estimated from both ends' ranges,
so that i's and j's estimates of it are exactly opposite whatever the noise."""

import dataclasses

import numpy as np
import pytest

from mission_runner.enclosing import NeighbourReport, SwarmEnclosing, TargetReport
from mission_runner.enclosing.step import pair_ranges

from .swarm_loop import PAPER, World, initial_positions
from .test_ekf import EKF, NOISY
from .test_step import OMEGA, PHASES, make_vehicles

SHARED = dataclasses.replace(PAPER, shared_ranges=True)
SHARED_EKF = dataclasses.replace(EKF, filter=NOISY, shared_ranges=True)


def test_a_pair_takes_the_mean_of_both_ends_or_the_one_there_is():
    nan = np.nan
    ranges, readings = pair_ranges(np.array([4.0, 4.0, nan, nan]), np.array([5.0, nan, 3.0, nan]))
    np.testing.assert_array_equal(ranges, [4.5, 4.0, 3.0, nan])
    np.testing.assert_array_equal(readings, [2, 1, 1, 0])


def noisy_ranges(world, rng, std_m=0.1):
    """The world's ranges with independent noise on i->j and j->i (and dropouts)."""
    ranges = world.ranges() + std_m * rng.normal(size=(4, 5))
    ranges[rng.uniform(size=ranges.shape) < 0.05] = np.nan
    return ranges


def swarm_run(params, steps=300, seed=3):
    rng = np.random.default_rng(seed)
    world = World(initial_positions())
    swarm = SwarmEnclosing(params, PHASES, np.full(4, OMEGA))
    for _ in range(steps):
        out = swarm.step(
            odometry_m=world.odometry(),
            range_m=noisy_ranges(world, rng),
            live=np.ones(4, dtype=bool),
            target_velocity_m_s=world.target_velocity,
            shape_now=np.eye(3),
            shape_next=np.eye(3),
        )
        world.advance(out.velocity_m_s)
    return world, out


@pytest.mark.parametrize("params", [SHARED, SHARED_EKF], ids=["rlse", "ekf"])
def test_with_shared_ranges_the_two_estimates_of_a_pair_are_exactly_opposite(params):
    _, out = swarm_run(params)
    vehicles = out.estimate_m[:, 1:]  # (N, N, 2): row i, vehicle j
    np.testing.assert_array_equal(vehicles, -np.swapaxes(vehicles, 0, 1))
    _, own = swarm_run(dataclasses.replace(params, shared_ranges=False))
    assert (
        np.nanmax(np.abs(own.estimate_m[:, 1:] + np.swapaxes(own.estimate_m[:, 1:], 0, 1))) > 1e-3
    )


def vehicle_commands(vehicles, world, ranges, shares):
    """Every vehicle's command from its own ranges (row of ``ranges``) and the ranges its
    neighbours measured to it, from those whose step message ``shares[j]`` came through."""
    ids = [vehicle.vehicle_id for vehicle in vehicles]
    odometry = world.odometry()
    phases = [vehicle.phase_rad for vehicle in vehicles]  # all at step k
    commands = []
    for row, vehicle in enumerate(vehicles):
        own = {peer: ranges[row, slot] for slot, peer in enumerate(ids, 1)}
        own[0] = ranges[row, 0]
        shared = {
            peer: ranges[slot - 1, row + 1] for slot, peer in enumerate(ids, 1) if shares[slot - 1]
        }
        commands.append(
            vehicle.step(
                own_odometry_m=odometry[row + 1],
                neighbours={
                    peer: NeighbourReport(phase, tuple(odometry[slot]))
                    for slot, (peer, phase) in enumerate(zip(ids, phases, strict=True), 1)
                    if peer != vehicle.vehicle_id
                },
                ranges_m={peer: d for peer, d in own.items() if np.isfinite(d)},
                target=TargetReport(tuple(odometry[0]), tuple(world.target_velocity)),
                members=ids,
                peer_ranges_m={
                    peer: d
                    for peer, d in shared.items()
                    if np.isfinite(d) and peer != vehicle.vehicle_id
                },
            )
        )
    return np.array([command.velocity_m_s for command in commands])


def test_vehicle_face_and_swarm_face_agree_with_shared_ranges():
    rng = np.random.default_rng(5)
    world = World(initial_positions())
    swarm = SwarmEnclosing(SHARED_EKF, PHASES, np.full(4, OMEGA))
    vehicles = make_vehicles(params=SHARED_EKF)
    for _ in range(200):
        ranges = noisy_ranges(world, rng)
        alone = vehicle_commands(vehicles, world, ranges, shares=np.ones(4, dtype=bool))
        together = swarm.step(
            odometry_m=world.odometry(),
            range_m=ranges,
            live=np.ones(4, dtype=bool),
            target_velocity_m_s=world.target_velocity,
            shape_now=np.eye(3),
            shape_next=np.eye(3),
        )
        np.testing.assert_allclose(alone, together.velocity_m_s, rtol=0, atol=1e-9)
        world.advance(together.velocity_m_s)
    error = np.linalg.norm(world.positions.mean(axis=0) - world.target())
    assert error < 0.1


def test_without_a_neighbours_message_a_vehicle_uses_its_own_range():
    """Shared ranges that never arrive leave exactly the paper's own-range estimator."""
    rng = np.random.default_rng(6)
    world = World(initial_positions())
    shared = make_vehicles(params=SHARED_EKF)
    alone = make_vehicles(params=dataclasses.replace(SHARED_EKF, shared_ranges=False))
    for _ in range(100):
        ranges = noisy_ranges(world, rng)
        silent = vehicle_commands(shared, world, ranges, shares=np.zeros(4, dtype=bool))
        own = vehicle_commands(alone, world, ranges, shares=np.ones(4, dtype=bool))
        np.testing.assert_array_equal(silent, own)
        world.advance(own)

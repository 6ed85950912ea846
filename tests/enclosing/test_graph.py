"""The neighbourhood graphs: each kind's adjacency, components, a ring closing over a loss, and
the step's masks (a sparse coupling equals the dense one over the same neighbours)."""

import numpy as np
import pytest

from mission_runner.enclosing import (
    IDENTITY,
    EnclosingError,
    NeighbourReport,
    SwarmEnclosing,
    TargetReport,
    VehicleEnclosing,
)
from mission_runner.enclosing.graph import (
    complete_graph,
    components,
    edge_graph,
    edge_problems,
    k_nearest_graph,
    live_adjacency,
    ring_graph,
    slot_mask,
)
from mission_runner.enclosing.oscillator import (
    _edge_coupling,
    _product_coupling,
    coupling_rate,
    harmonic_gains,
)

from .swarm_loop import PAPER, World, initial_positions


def edges_of(adjacency):
    return {(int(i), int(j)) for i, j in zip(*np.nonzero(np.triu(adjacency, 1)), strict=True)}


def assert_graph(adjacency):
    assert adjacency.dtype == bool
    assert np.array_equal(adjacency, adjacency.T)
    assert not adjacency.diagonal().any()


def test_complete_graph_links_every_pair():
    graph = complete_graph(4)
    assert_graph(graph)
    assert edges_of(graph) == {(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)}


def test_ring_links_each_vehicle_to_the_two_adjacent_in_order():
    graph = ring_graph(6)
    assert_graph(graph)
    assert edges_of(graph) == {(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 5)}
    assert np.all(graph.sum(axis=1) == 2)


def test_k_nearest_is_symmetric_and_keeps_each_vehicles_k_nearest():
    positions = np.array([[0.0, 0.0], [1.0, 0.0], [2.5, 0.0], [10.0, 0.0], [11.0, 0.0]])
    graph = k_nearest_graph(positions, 1)
    assert_graph(graph)
    # 0-1 mutual, 2's nearest is 1, 3-4 mutual: made symmetric, 1 gains 2.
    assert edges_of(graph) == {(0, 1), (1, 2), (3, 4)}
    assert np.array_equal(k_nearest_graph(positions, 4), complete_graph(5))
    with pytest.raises(EnclosingError, match="k must be >= 1"):
        k_nearest_graph(positions, 0)


def test_explicit_edges_are_undirected():
    graph = edge_graph(4, [[0, 1], [2, 1], [3, 2]])
    assert_graph(graph)
    assert edges_of(graph) == {(0, 1), (1, 2), (2, 3)}


def test_bad_edges_are_named_by_their_index():
    problems = dict(edge_problems(3, [[0, 1], [1, 1], [0, 3], [1, 0], [2]]))
    assert "self loop" in problems[1]
    assert "3 is not in 0..2" in problems[2]
    assert "repeats edges[0]" in problems[3]
    assert "two vehicle indices" in problems[4]
    assert 0 not in problems
    with pytest.raises(EnclosingError, match=r"edges\[1\]: self loop"):
        edge_graph(3, [[0, 1], [1, 1]])


def test_components_of_a_graph_and_of_its_live_vehicles():
    graph = edge_graph(5, [[0, 1], [1, 2], [3, 4]])
    assert components(graph) == [[0, 1, 2], [3, 4]]
    assert components(complete_graph(5)) == [[0, 1, 2, 3, 4]]
    live = np.array([True, False, True, True, True])
    assert components(graph, live) == [[0], [2], [3, 4]]
    path = edge_graph(4, [[0, 1], [1, 2], [2, 3]])
    assert components(path, np.array([True, True, False, True])) == [[0, 1], [3]]


def test_a_ring_closes_over_a_loss_and_other_graphs_only_lose_edges():
    live = np.array([True, True, False, True, True, True])
    closed = live_adjacency(ring_graph(6), live, ring=True)
    assert_graph(closed)
    assert edges_of(closed) == {(0, 1), (1, 3), (3, 4), (4, 5), (0, 5)}
    assert len(components(closed, live)) == 1
    cut = live_adjacency(ring_graph(6), live, ring=False)
    assert edges_of(cut) == {(0, 1), (3, 4), (4, 5), (0, 5)}
    # Two lost on a path: the rest falls apart.
    twice = np.array([True, False, True, False, True, True])
    assert len(components(live_adjacency(ring_graph(6), twice, ring=False), twice)) == 2
    assert len(components(live_adjacency(ring_graph(6), twice, ring=True), twice)) == 1


def test_slot_mask_puts_the_target_first_for_everyone():
    mask = slot_mask(ring_graph(4))
    assert mask.shape == (4, 5)
    assert mask[:, 0].all()
    assert np.array_equal(mask[:, 1:], ring_graph(4))


def random_phases(rng, runs, n):
    phase = np.concatenate([np.full((runs, 1), np.nan), rng.uniform(0, 40, (runs, n))], axis=-1)
    heard = np.isfinite(phase) & (rng.uniform(size=phase.shape) > 0.3)
    return np.where(heard, phase, np.nan), heard


def test_sparse_coupling_by_edges_equals_the_masked_matrix_product():
    rng = np.random.default_rng(3)
    n, runs = 30, 3
    phase, heard = random_phases(rng, runs, n)
    positions = rng.uniform(-20, 20, (n, 2))
    neighbours = slot_mask(k_nearest_graph(positions, 2))
    rows = np.arange(1, n + 1)
    gains = harmonic_gains(heard[:, 1:].sum(-1), n, 1.0, -1.0)
    finite = np.where(heard, phase, 0.0)
    by_edges = _edge_coupling(finite, rows, heard[..., None, :] & neighbours, gains)
    product = _product_coupling(finite, rows, heard, gains, neighbours=neighbours)
    np.testing.assert_allclose(by_edges, product, rtol=1e-9, atol=1e-9)
    # ...and differs from the complete graph's (the mask is used).
    dense = coupling_rate(phase, rows, heard, gains)
    assert np.abs(dense - product).max() > 1e-3


def test_a_complete_mask_gives_the_unmasked_coupling_bit_for_bit():
    rng = np.random.default_rng(4)
    n = 8
    phase, heard = random_phases(rng, 2, n)
    rows = np.arange(1, n + 1)
    gains = harmonic_gains(heard[:, 1:].sum(-1), n, 1.0, -1.0)
    masked = coupling_rate(phase, rows, heard, gains, neighbours=slot_mask(complete_graph(n)))
    assert np.array_equal(masked, coupling_rate(phase, rows, heard, gains))


def test_the_step_couples_estimates_and_agrees_over_graph_neighbours_only():
    # Every pair is ranged: the mask alone keeps vehicle 0 from vehicle 2 (opposite on the ring
    # 0-1-2-3; slot j + 1 is vehicle j).
    phases = np.array([0.0, 0.3, 0.9, 2.0])
    ring = SwarmEnclosing(PAPER, phases, np.full(4, 1.5))
    complete = SwarmEnclosing(PAPER, phases, np.full(4, 1.5))
    world = World(initial_positions())
    outputs = {}
    for swarm, mask in ((ring, slot_mask(ring_graph(4))), (complete, None)):
        for _ in range(3):
            outputs[swarm] = swarm.step(
                odometry_m=world.odometry(),
                range_m=world.ranges(),
                live=np.ones(4, dtype=bool),
                target_velocity_m_s=world.target_velocity,
                shape_now=IDENTITY,
                shape_next=IDENTITY,
                neighbours=mask,
            )
    masked, full = outputs[ring], outputs[complete]
    assert np.isnan(masked.estimate_north_m[0, 3]) and np.isnan(masked.estimate_north_m[2, 1])
    assert np.isfinite(full.estimate_north_m[0, 3])
    assert masked.consensus_weights[0, 3] == 0.0 and masked.consensus_weights[0, 2] > 0
    assert full.consensus_weights[0, 3] > 0
    # The coupling too: the phases part from the complete graph's.
    assert np.abs(ring.phase_rad - complete.phase_rad).max() > 1e-3


def test_a_flying_vehicle_with_the_graph_computes_its_row_of_the_swarm():
    # Every vehicle hears every message and ranges every pair: the graph alone keeps the
    # non-neighbours out, on the vehicle face as on the swarm face; vehicle 3 (index 2) is lost
    # at step 40 and the ring closes over it on both.
    ids = [1, 2, 3, 4, 5]
    angles = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    world = World(5.0 * np.stack([np.cos(angles), np.sin(angles)], axis=-1))
    phases, omega, graph = angles * 0.9, np.full(5, 1.5), ring_graph(5)
    swarm = SwarmEnclosing(PAPER, phases, omega)
    vehicles = [
        VehicleEnclosing(PAPER, i, ids, phases[n], 1.5, graph=graph, ring=True)
        for n, i in enumerate(ids)
    ]
    for k in range(80):
        live = np.array([k < 40 or i != 3 for i in ids])
        rows = np.where(live[:, None], live_adjacency(graph, live, ring=True), graph)
        together = swarm.step(
            odometry_m=world.odometry(),
            range_m=world.ranges(),
            live=live,
            target_velocity_m_s=world.target_velocity,
            shape_now=IDENTITY,
            shape_next=IDENTITY,
            neighbours=slot_mask(rows),
        )
        alone = vehicle_steps([v for v, up in zip(vehicles, live, strict=True) if up], world, live)
        velocities = np.array([command.velocity_m_s for command in alone])
        np.testing.assert_allclose(velocities, together.velocity_m_s[live], rtol=0, atol=1e-12)
        world.advance(np.where(live[:, None], together.velocity_m_s, 0.0))
    assert set(alone[1].neighbours_used) == {1, 4}  # vehicle 2: 1, and 4 across the lost 3


def vehicle_steps(vehicles, world, live):
    """Each live vehicle's step from every message and range (as test_step's, with losses)."""
    odometry, ranges = world.odometry(), world.ranges()
    ids = [i + 1 for i in range(len(live))]
    members = [i for i, up in zip(ids, live, strict=True) if up]
    phases = {v.vehicle_id: v.phase_rad for v in vehicles}
    commands = []
    for vehicle in vehicles:
        row = vehicle.vehicle_id - 1
        heard = {
            peer: NeighbourReport(phases[peer], tuple(odometry[peer]))
            for peer in members
            if peer != vehicle.vehicle_id
        }
        measured = {peer: ranges[row, peer] for peer in [0, *members]}
        measured = {peer: value for peer, value in measured.items() if np.isfinite(value)}
        commands.append(
            vehicle.step(
                own_odometry_m=odometry[row + 1],
                neighbours=heard,
                ranges_m=measured,
                target=TargetReport(tuple(odometry[0]), tuple(world.target_velocity)),
                members=members,
            )
        )
    return commands


def test_k_nearest_takes_the_lower_index_at_a_tie():
    # On a grid many distances tie: each vehicle's k are the first k of a stable sort.
    rng = np.random.default_rng(5)
    for _ in range(50):
        n, k = int(rng.integers(3, 30)), int(rng.integers(1, 6))
        positions = rng.integers(-3, 4, (n, 2)).astype(float)
        gaps = positions[:, None, :] - positions[None, :, :]
        distance = np.sqrt(np.sum(gaps * gaps, axis=-1))
        np.fill_diagonal(distance, np.inf)
        nearest = np.argsort(distance, axis=-1, kind="stable")[:, :k]
        expected = np.zeros((n, n), dtype=bool)
        expected[np.arange(n)[:, None], nearest] = k < n - 1
        expected = (expected | expected.T) if k < n - 1 else complete_graph(n)
        assert np.array_equal(k_nearest_graph(positions, k), expected)

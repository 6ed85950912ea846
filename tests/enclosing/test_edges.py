"""The swarm on a sparse graph kept per edge (:mod:`mission_runner.enclosing.edges`) flies as the
dense planes masked by the same graph: ranges, losses, joins, a ring closing over a loss (edges
born mid-run), shared ranges and the filter, batched."""

from dataclasses import replace

import numpy as np
import pytest

from mission_runner.enclosing import IDENTITY, SwarmEnclosing
from mission_runner.enclosing.edges import EdgeIndex
from mission_runner.enclosing.graph import k_nearest_graph, live_adjacency, ring_graph, slot_mask

from .swarm_loop import PAPER, World
from .test_ekf import NOISY


def test_the_edge_index_finds_reverse_edges_and_sums_by_row():
    mask = slot_mask(ring_graph(4))  # rows = vehicles 0..3 at slots 1..4
    mask[2, 2] = True  # a self entry is dropped
    index = EdgeIndex.of_mask(mask, np.arange(1, 5))
    assert index.size == 4 * 3  # each: the target and two ring neighbours
    assert list(index.row) == sorted(index.row)
    for e in range(index.size):
        back = index.reverse[e]
        if index.slot[e] == 0:
            assert back == -1
        else:
            assert index.slot[back] == index.row[e] + 1 and index.row[back] == index.slot[e] - 1
    values = np.arange(index.size, dtype=float)
    np.testing.assert_array_equal(index.row_sums(values), [3, 12, 21, 30])
    lonely = EdgeIndex.of_mask(np.array([[True, False], [False, False]]), np.array([1, 0]))
    np.testing.assert_array_equal(lonely.row_sums(np.array([5.0])), [5.0, 0.0])
    plane = index.scatter(values, np.nan)
    np.testing.assert_array_equal(index.gather(plane), values)


def ring_members(n, k):
    """Vehicle 5 joins at step 10, vehicle 8 is lost at step 40: the ring over the live ones
    loses edges 4-6 at the join and gains 7-9 at the loss."""
    live = np.ones(n, dtype=bool)
    live[5] = k >= 10
    live[8] = k < 40
    return live


def graph_masks(graph, steps, n, *, ring):
    """Each step's live mask ``(N,)`` and neighbour mask ``(N, N+1)``: a ring closes over the
    loss (a lost or not yet joined vehicle's row keeps its own edges, as in the simulator);
    other graphs keep every edge, so that the live vehicles' rows have neighbours they do not
    hear (no phase, no odometry)."""
    masks = []
    for k in range(steps):
        live = ring_members(n, k)
        rows = np.where(live[:, None], live_adjacency(graph, live, ring=True), graph)
        masks.append((live, slot_mask(rows if ring else graph)))
    return masks


def fly(swarm, masks, world, runs, *, per_edge, noise):
    """Fly ``swarm`` through ``masks`` on ``runs`` copies of ``world`` (the same positions, the
    same range noise); returns the positions after each step and the last outputs."""
    rng = np.random.default_rng(7)
    worlds = [World(world.positions.copy()) for _ in range(runs)]
    index = swarm.edge_index
    track = []
    for live, mask in masks:
        ranges = np.stack([w.ranges() for w in worlds])
        ranges = ranges + noise * rng.standard_normal(ranges.shape)
        odometry = np.stack([w.odometry() for w in worlds])
        odometry[:, 1:][:, ~live] = np.nan
        neighbours = np.broadcast_to(mask, ranges.shape)
        if per_edge:
            ranges, neighbours = index.gather(ranges), index.gather(neighbours)
        out = swarm.step(
            odometry_m=odometry,
            range_m=ranges,
            live=np.broadcast_to(live, (runs, live.size)),
            target_velocity_m_s=np.broadcast_to(worlds[0].target_velocity, (runs, 2)),
            shape_now=IDENTITY,
            shape_next=IDENTITY,
            neighbours=neighbours,
        )
        for run, w in enumerate(worlds):
            w.advance(np.where(live[:, None], out.velocity_m_s[run], 0.0))
        track.append(np.stack([w.positions for w in worlds]))
    return np.array(track), out


PARAMS = {
    "rlse": PAPER,
    "shared": replace(PAPER, shared_ranges=True),
    "ekf": replace(PAPER, estimator="ekf", filter=NOISY),
}


@pytest.mark.parametrize(
    ("kind", "estimator"), [("ring", "rlse"), ("k_nearest", "shared"), ("ring", "ekf")]
)
def test_per_edge_state_flies_as_the_masked_planes(kind, estimator):
    n, steps, runs = 12, 80, 2
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    positions = 6.0 * np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    graph = ring_graph(n) if kind == "ring" else k_nearest_graph(positions, 3)
    masks = graph_masks(graph, steps, n, ring=kind == "ring")
    union = np.any([mask for _, mask in masks], axis=0)
    params = PARAMS[estimator]
    noise = 0.05 if estimator == "ekf" else 0.01  # both ends' ranges differ
    phases = np.stack([angles * 0.9, angles * 0.8 + 0.1])
    dense = SwarmEnclosing(params, phases, np.full((runs, n), 1.5))
    sparse = SwarmEnclosing(params, phases, np.full((runs, n), 1.5), edges=union)
    world = World(positions)
    dense_track, dense_out = fly(dense, masks, world, runs, per_edge=False, noise=noise)
    sparse_track, sparse_out = fly(sparse, masks, world, runs, per_edge=True, noise=noise)
    assert sparse.edge_index is not None and sparse.edge_index.size < union.size / 2
    np.testing.assert_allclose(sparse_track, dense_track, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sparse.phase_rad, dense.phase_rad, rtol=0, atol=1e-12)
    index = sparse.edge_index
    for name in ("estimate_north_m", "estimate_east_m", "consensus_weights", "bearing_std_rad"):
        per_edge, plane = getattr(sparse_out, name), getattr(dense_out, name)
        np.testing.assert_allclose(per_edge, index.gather(plane), rtol=0, atol=1e-9)
    # Off the edges the planes hold nothing: not estimated, not weighted.
    off = ~np.broadcast_to(union, dense_out.estimate_north_m.shape)
    assert np.isnan(dense_out.estimate_north_m[off]).all()
    assert not dense_out.consensus_weights[off].any()
    assert (sparse_out.gated == index.gather(dense_out.gated)).all()
    # The ring's edge 7-9, born at the loss, was estimated from scratch and has converged.
    if kind == "ring":
        born = (index.row == 7) & (index.slot == 10)
        assert np.isfinite(sparse_out.estimate_north_m[:, born]).all()

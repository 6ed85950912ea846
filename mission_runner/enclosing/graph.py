"""Neighbourhood graphs: who couples, ranges and takes part in the consensus with whom.

The paper's analysis assumes every vehicle is a neighbour of every other (a complete graph,
Assumption 1). A scenario may pick a sparser graph (``algorithm.graph``): a ring in slot order,
the k nearest vehicles at the start, or an explicit list of undirected edges. One adjacency is
used by the oscillator coupling, the consensus law and the ranging schedule alike.

An adjacency is a boolean ``(N, N)`` matrix over the vehicles (indices 0..N-1 in the scenario's
order), symmetric, with no self loops. The step functions take a per-row mask over slots
``(R, S)`` (slot 0 the target, always a neighbour; slot j + 1 vehicle j): :func:`slot_mask`.

A lost vehicle drops out of the graph. A ring closes over the loss (its two live neighbours
become neighbours of each other, :func:`live_adjacency`): a ring that degraded to a path would
not space its phases evenly. Other graphs only lose the lost vehicle's edges, which may leave the
live vehicles disconnected (:func:`components`).
"""

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import EnclosingError

Adjacency = NDArray[np.bool_]


def complete_graph(n: int) -> Adjacency:
    """Every vehicle a neighbour of every other ``(n, n)``."""
    return ~np.eye(n, dtype=bool)


def ring_graph(n: int) -> Adjacency:
    """Each vehicle's neighbours are the two adjacent in index order, the last next to the first
    ``(n, n)``; for n <= 3 this is the complete graph."""
    return _ring_over(np.ones(n, dtype=bool))


def k_nearest_graph(positions_m: ArrayLike, k: int) -> Adjacency:
    """i and j neighbours if j is among i's ``k`` nearest or i among j's (made symmetric), by the
    positions ``(n, 2)`` [m]; ties go to the lower index. ``k`` >= n - 1: the complete graph."""
    positions = np.asarray(positions_m, dtype=float)
    n = positions.shape[0]
    if k < 1:
        raise EnclosingError(f"k must be >= 1, got {k}")
    if k >= n - 1:
        return complete_graph(n)
    north = positions[:, None, 0] - positions[None, :, 0]
    east = positions[:, None, 1] - positions[None, :, 1]
    distance = np.sqrt(north * north + east * east)
    np.fill_diagonal(distance, np.inf)
    # The first k of a stable sort of each row, without sorting it: everything nearer than the
    # k-th distance, then the lowest indices at it.
    kth = np.partition(distance, k - 1, axis=-1)[:, k - 1 : k]
    nearer = distance < kth
    tied = distance == kth
    room = k - np.sum(nearer, axis=-1, keepdims=True)
    adjacency: Adjacency = nearer | (tied & (np.cumsum(tied, axis=-1) <= room))
    return adjacency | adjacency.T


def edge_problems(n: int, edges: Sequence[Sequence[int]]) -> list[tuple[int, str]]:
    """What is wrong with an explicit edge list over ``n`` vehicles: ``(index in the list,
    problem)`` for self loops, indices out of 0..n-1 and duplicates (either direction)."""
    problems: list[tuple[int, str]] = []
    seen: dict[frozenset[int], int] = {}
    for index, edge in enumerate(edges):
        if len(edge) != 2:
            problems.append((index, f"an edge is two vehicle indices, got {list(edge)}"))
            continue
        i, j = int(edge[0]), int(edge[1])
        outside = [v for v in (i, j) if not 0 <= v < n]
        if outside:
            problems.append((index, f"vehicle index {outside[0]} is not in 0..{n - 1}"))
        elif i == j:
            problems.append((index, f"self loop [{i}, {j}]: a vehicle is not its own neighbour"))
        elif frozenset((i, j)) in seen:
            problems.append((index, f"[{i}, {j}] repeats edges[{seen[frozenset((i, j))]}]"))
        else:
            seen[frozenset((i, j))] = index
    return problems


def edge_graph(n: int, edges: Sequence[Sequence[int]]) -> Adjacency:
    """The undirected graph of ``edges`` (pairs of vehicle indices) over ``n`` vehicles."""
    problems = edge_problems(n, edges)
    if problems:
        raise EnclosingError("; ".join(f"edges[{i}]: {p}" for i, p in problems))
    adjacency = np.zeros((n, n), dtype=bool)
    for i, j in edges:
        adjacency[i, j] = adjacency[j, i] = True
    return adjacency


def components(adjacency: Adjacency, live: ArrayLike | None = None) -> list[list[int]]:
    """The connected components of the ``live`` vehicles ``(n,)`` bool (default: all), each a
    sorted list of vehicle indices, in order of their lowest index. One component (or none):
    connected."""
    n = adjacency.shape[0]
    alive = np.ones(n, dtype=bool) if live is None else np.asarray(live, dtype=bool)
    unseen = alive.copy()
    found: list[list[int]] = []
    for start in range(n):
        if not unseen[start]:
            continue
        reached = np.zeros(n, dtype=bool)
        reached[start] = True
        frontier = reached.copy()
        while frontier.any():  # breadth first, one matrix row-sum per level
            frontier = adjacency[frontier].any(axis=0) & alive & ~reached
            reached |= frontier
        unseen &= ~reached
        found.append([int(i) for i in np.flatnonzero(reached)])
    return found


def live_adjacency(adjacency: Adjacency, live: ArrayLike, *, ring: bool) -> Adjacency:
    """The graph among the ``live`` vehicles ``(n,)`` bool: the lost ones' edges removed; with
    ``ring``, the ring of the live vehicles in index order instead (it closes over losses)."""
    live = np.asarray(live, dtype=bool)
    if ring:
        return _ring_over(live)
    kept: Adjacency = adjacency & live[:, None] & live[None, :]
    return kept


def slot_mask(adjacency: Adjacency) -> NDArray[np.bool_]:
    """Each vehicle's neighbours over slots ``(n, n + 1)``: slot 0 the target (a neighbour of
    every vehicle that senses it), slot j + 1 vehicle j."""
    n = adjacency.shape[0]
    return np.concatenate([np.ones((n, 1), dtype=bool), adjacency], axis=-1)


def _ring_over(members: NDArray[np.bool_]) -> Adjacency:
    """The ring through the ``members`` ``(n,)`` in index order."""
    n = members.shape[0]
    order = np.flatnonzero(members)
    adjacency = np.zeros((n, n), dtype=bool)
    if order.size >= 2:
        following = np.roll(order, -1)
        adjacency[order, following] = adjacency[following, order] = True
    return adjacency

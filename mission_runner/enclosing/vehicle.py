"""The per-vehicle face of the algorithm: what one drone computes from its own measurements and its
neighbours' messages. The flying controller calls this; it is :func:`.step.enclosing_step` with a
single row, plus the bookkeeping from vehicle ids to slots.
"""

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import EnclosingError
from .graph import Adjacency, live_adjacency, slot_mask
from .shape import IDENTITY
from .step import TARGET_SLOT, EnclosingParams, EnclosingState, StepInputs, enclosing_step


@dataclass(frozen=True)
class NeighbourReport:
    """A neighbour's step-k message: its phase theta_j(k) [rad] and odometry o_j(k) ``(2,)`` [m]."""

    phase_rad: float
    odometry_m: tuple[float, float]


@dataclass(frozen=True)
class TargetReport:
    """The target's motion as the swarm knows it at step k (Assumption 2).

    odometry_m: ``(2,)`` the target's cumulative displacement [m] (needed by vehicles that range to
    it). velocity_m_s: ``(2,)`` u_0(k) [m/s].
    """

    odometry_m: tuple[float, float]
    velocity_m_s: tuple[float, float]


@dataclass(frozen=True)
class VehicleCommand:
    """Result of one vehicle step.

    velocity_m_s: ``(2,)`` north-east velocity setpoint u_i(k) [m/s], before vehicle limits.
    consensus_m_s: ``(2,)`` the saturated consensus term. estimates_m: phat_ij(k) per peer id
    (0 = target) for the edges estimated this step. neighbours_used: peer ids in this step's sum.
    gated: peer ids whose range the estimator rejected as an outlier this step.
    bearing_std_rad: per peer id in ``estimates_m``, how far the estimate's bearing may be off
    [rad] (see :class:`.step.StepOutputs`; NaN: not known).
    """

    velocity_m_s: NDArray[np.float64]
    consensus_m_s: NDArray[np.float64]
    estimates_m: dict[int, NDArray[np.float64]]
    neighbours_used: tuple[int, ...]
    gated: tuple[int, ...] = ()
    bearing_std_rad: dict[int, float] = field(default_factory=dict)


class VehicleEnclosing:
    """One vehicle's enclosing law.

    vehicle_ids: every vehicle id the swarm may contain (fixed at start; ids are > 0, 0 is the
    target). The vehicle's own phase at the current step is :attr:`phase_rad`: broadcast it with
    the odometry before calling :meth:`step`. graph: the neighbourhood graph ``(N, N)`` over
    ``vehicle_ids`` in their order (:mod:`.graph`), ``ring``: it closes over losses; None: every
    vehicle is a neighbour. Messages and ranges of vehicles that are not neighbours among the
    step's ``members`` are ignored, as the simulator's rows do.
    """

    def __init__(
        self,
        params: EnclosingParams,
        vehicle_id: int,
        vehicle_ids: Iterable[int],
        initial_phase_rad: float,
        omega_rad_s: float,
        *,
        graph: Adjacency | None = None,
        ring: bool = False,
    ) -> None:
        ids = list(vehicle_ids)
        if vehicle_id not in ids:
            raise EnclosingError(f"vehicle {vehicle_id} is not among the swarm's ids {ids}")
        if TARGET_SLOT in ids or len(set(ids)) != len(ids):
            raise EnclosingError(f"vehicle ids must be unique and non-zero, got {ids}")
        self.params = params
        self.vehicle_id = vehicle_id
        self._slot_of = {peer: slot for slot, peer in enumerate(ids, start=1)}
        self._slot_of[TARGET_SLOT] = TARGET_SLOT
        self._row = np.array([self._slot_of[vehicle_id]])
        self._n_slots = len(ids) + 1
        self._omega = np.array([float(omega_rad_s)])
        self.state = EnclosingState.initial(params, [initial_phase_rad], self._n_slots)
        if graph is not None and graph.shape != (len(ids), len(ids)):
            raise EnclosingError(f"graph is {graph.shape}, the swarm has {len(ids)} vehicles")
        self._graph, self._ring = graph, ring

    @property
    def phase_rad(self) -> float:
        """theta_i at the current step."""
        return float(self.state.phase_rad[0])

    @property
    def step_index(self) -> int:
        """k: how many steps this vehicle has taken."""
        return self.state.step

    def step(
        self,
        *,
        own_odometry_m: ArrayLike,
        neighbours: Mapping[int, NeighbourReport],
        ranges_m: Mapping[int, float],
        target: TargetReport | None,
        members: Iterable[int],
        shape_now: ArrayLike = IDENTITY,
        shape_next: ArrayLike = IDENTITY,
        peer_ranges_m: Mapping[int, float] | None = None,
    ) -> VehicleCommand:
        """Advance from step k to k+1 and return the command for step k.

        own_odometry_m: ``(2,)`` own cumulative displacement at k [m]. neighbours: the step-k
        messages heard from other vehicles, by id. ranges_m: d_ij(k) by peer id (0 = target).
        target: the target's motion at k, or None if unknown. members: ids of the vehicles counted
        as live (including this one). shape_now/shape_next: affine shape at k and k+1.
        peer_ranges_m: d_ji(k) by peer id, the range each neighbour measured to this vehicle and
        shared in its step-k message (used with ``params.shared_ranges``).
        """
        n = self._n_slots
        odometry = np.full((n, 2), np.nan)
        phase = np.full(n, np.nan)
        ranges = np.full((1, n), np.nan)
        member = np.zeros(n, dtype=bool)
        odometry[self._row[0]] = own_odometry_m
        for peer, report in neighbours.items():
            slot = self._slot(peer)
            odometry[slot] = report.odometry_m
            phase[slot] = report.phase_rad
        for peer, distance in ranges_m.items():
            ranges[0, self._slot(peer)] = distance
        reverse = None
        if peer_ranges_m is not None:
            reverse = np.full((1, n), np.nan)
            for peer, distance in peer_ranges_m.items():
                if peer != TARGET_SLOT:
                    reverse[0, self._slot(peer)] = distance
        for peer in members:
            member[self._slot(peer)] = True
        velocity = np.full(2, np.nan)
        if target is not None:
            odometry[TARGET_SLOT] = target.odometry_m
            velocity = np.asarray(target.velocity_m_s, dtype=float)
        inputs = StepInputs(
            odometry_m=odometry,
            phase_rad=phase,
            range_m=ranges,
            member=member,
            target_velocity_m_s=velocity,
            shape_now=np.asarray(shape_now, dtype=float),
            shape_next=np.asarray(shape_next, dtype=float),
            omega_rad_s=self._omega,
            reverse_range_m=reverse,
            neighbours=self._neighbours(member),
        )
        self.state, out = enclosing_step(self.params, self._row, self.state, inputs)
        peers = {slot: peer for peer, slot in self._slot_of.items()}
        used = np.flatnonzero(out.consensus_weights[0] > 0).tolist()
        estimated = np.flatnonzero(np.isfinite(out.estimate_north_m[0])).tolist()
        estimate = out.estimate_m[0]
        return VehicleCommand(
            velocity_m_s=out.velocity_m_s[0],
            consensus_m_s=out.consensus_m_s[0],
            estimates_m={peers[s]: estimate[s] for s in estimated},
            neighbours_used=tuple(peers[s] for s in used),
            gated=tuple(peers[s] for s in np.flatnonzero(out.gated[0]).tolist()),
            bearing_std_rad={peers[s]: float(out.bearing_std_rad[0, s]) for s in estimated},
        )

    def _neighbours(self, member: NDArray[np.bool_]) -> NDArray[np.bool_] | None:
        """This vehicle's neighbours over slots ``(1, S)`` among the live ``member`` ``(S,)``
        (its own row of the simulator's mask); None without a graph."""
        if self._graph is None:
            return None
        live = member[1:]
        own = self._row[0] - 1
        if live[own]:
            row = live_adjacency(self._graph, live, ring=self._ring)[own]
        else:  # not counted live: its own neighbours, as a lost row in the simulator
            row = self._graph[own]
        mask: NDArray[np.bool_] = slot_mask(row[None, :])
        return mask

    def _slot(self, peer: int) -> int:
        try:
            return self._slot_of[peer]
        except KeyError:
            known = sorted(self._slot_of)
            raise EnclosingError(f"unknown vehicle id {peer}; known: {known}") from None

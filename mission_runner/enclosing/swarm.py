"""The whole-swarm face of the algorithm, for the numeric simulator: every vehicle is a row of
one :func:`.step.enclosing_step` call, with optional leading batch axes (many runs at once).
On a sparse graph it keeps the step's state and outputs per directed edge (:mod:`.edges`).
"""

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .edges import EdgeIndex
from .step import EnclosingParams, EnclosingState, StepInputs, StepOutputs, enclosing_step


class SwarmEnclosing:
    """All N vehicles of a swarm (slots 1..N; slot 0 the target), batched over leading axes.

    initial_phase_rad, omega_rad_s: ``(..., N)``. edges: ``(N, N+1)`` bool, every (vehicle,
    slot) pair the graph may have over the run (a ring's closing edges too): the state, ranges,
    masks and outputs are then kept per edge of it (:attr:`edge_index`), O(E) instead of
    O(N^2); None: on ``(..., N, N+1)`` planes.
    """

    def __init__(
        self,
        params: EnclosingParams,
        initial_phase_rad: ArrayLike,
        omega_rad_s: ArrayLike,
        *,
        edges: NDArray[np.bool_] | None = None,
    ) -> None:
        self.params = params
        self.omega_rad_s = np.asarray(omega_rad_s, dtype=float)
        phase = np.asarray(initial_phase_rad, dtype=float)
        self.n_vehicles = phase.shape[-1]
        self.rows = np.arange(1, self.n_vehicles + 1)
        self.edge_index = None if edges is None else EdgeIndex.of_mask(edges, self.rows)
        n_edges = None if self.edge_index is None else self.edge_index.size
        self.state = EnclosingState.initial(params, phase, self.n_vehicles + 1, n_edges)

    @property
    def phase_rad(self) -> NDArray[np.float64]:
        """``(..., N)`` theta_i(k) of every vehicle."""
        return self.state.phase_rad

    def step(
        self,
        *,
        odometry_m: NDArray[np.float64],
        range_m: NDArray[np.float64],
        live: ArrayLike,
        target_velocity_m_s: NDArray[np.float64],
        shape_now: NDArray[np.float64],
        shape_next: NDArray[np.float64],
        neighbours: NDArray[np.bool_] | None = None,
    ) -> StepOutputs:
        """One step for every vehicle.

        odometry_m: ``(..., N+1, 2)`` slot 0 the target; NaN for lost vehicles.
        range_m: ``(..., N, N+1)``. live: ``(..., N)`` bool. Lost vehicles' phases are not heard.
        With ``params.shared_ranges`` every vehicle hears every other's ranges to it (the
        transpose of the vehicle columns). neighbours: ``(..., N, N+1)`` bool, each vehicle's
        graph neighbours over slots (:func:`.graph.slot_mask`); None: all. Returns
        :class:`.step.StepOutputs` with R = N. With ``edges``, ``range_m``, ``neighbours`` and
        the outputs' planes are ``(..., E)``, per edge of :attr:`edge_index`.
        """
        live = np.asarray(live, dtype=bool)
        member = np.concatenate([np.zeros((*live.shape[:-1], 1), dtype=bool), live], axis=-1)
        phase = np.concatenate(
            [np.full((*live.shape[:-1], 1), np.nan), np.where(live, self.phase_rad, np.nan)],
            axis=-1,
        )
        inputs = StepInputs(
            odometry_m=odometry_m,
            phase_rad=phase,
            range_m=range_m,
            member=member,
            target_velocity_m_s=target_velocity_m_s,
            shape_now=shape_now,
            shape_next=shape_next,
            omega_rad_s=self.omega_rad_s,
            reverse_range_m=self._reverse(range_m) if self.params.shared_ranges else None,
            neighbours=neighbours,
        )
        self.state, outputs = enclosing_step(
            self.params, self.rows, self.state, inputs, edge_index=self.edge_index
        )
        return outputs

    def _reverse(self, range_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """d_ji in the layout of d_ij (NaN for the target, which ranges to nobody)."""
        if self.edge_index is None:
            return _transposed(range_m)
        return self.edge_index.reversed(range_m)


def _transposed(range_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(..., N, N+1)`` d_ij by row i and slot j -> d_ji in the same layout (NaN for the target,
    which ranges to nobody)."""
    vehicles = np.swapaxes(range_m[..., 1:], -1, -2)
    return np.concatenate([np.full((*range_m.shape[:-1], 1), np.nan), vehicles], axis=-1)

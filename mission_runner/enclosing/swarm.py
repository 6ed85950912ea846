"""The whole-swarm face of the algorithm, for the numeric simulator: every vehicle is a row of
one :func:`.step.enclosing_step` call, with optional leading batch axes (many runs at once).
"""

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .step import EnclosingParams, EnclosingState, StepInputs, StepOutputs, enclosing_step


class SwarmEnclosing:
    """All N vehicles of a swarm (slots 1..N; slot 0 the target), batched over leading axes.

    initial_phase_rad, omega_rad_s: ``(..., N)``.
    """

    def __init__(
        self, params: EnclosingParams, initial_phase_rad: ArrayLike, omega_rad_s: ArrayLike
    ) -> None:
        self.params = params
        self.omega_rad_s = np.asarray(omega_rad_s, dtype=float)
        phase = np.asarray(initial_phase_rad, dtype=float)
        self.n_vehicles = phase.shape[-1]
        self.rows = np.arange(1, self.n_vehicles + 1)
        self.state = EnclosingState.initial(params, phase, self.n_vehicles + 1)

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
        :class:`.step.StepOutputs` with R = N.
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
            reverse_range_m=_transposed(range_m) if self.params.shared_ranges else None,
            neighbours=neighbours,
        )
        self.state, outputs = enclosing_step(self.params, self.rows, self.state, inputs)
        return outputs


def _transposed(range_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(..., N, N+1)`` d_ij by row i and slot j -> d_ji in the same layout (NaN for the target,
    which ranges to nobody)."""
    vehicles = np.swapaxes(range_m[..., 1:], -1, -2)
    return np.concatenate([np.full((*range_m.shape[:-1], 1), np.nan), vehicles], axis=-1)

"""Saturated consensus tracking law, eq. ``formationtrackingcontrol``.

ubar_i = -beta sum_j abar_ij (phat_ij - r_ij),  u_i = sat_Ubar(ubar_i) + delta_r_i / T + u_0

Only relative quantities enter ubar and delta_r is a difference, so the command does not depend on
any common origin (the paper's remark after the law); vehicles share orientation only.
"""

import numpy as np
from numpy.typing import NDArray


def saturate(
    velocity_m_s: NDArray[np.float64], limit_m_s: float | NDArray[np.float64]
) -> NDArray[np.float64]:
    """sat_U(u) = u U / max(U, |u|) over the last axis. ``velocity_m_s``: ``(..., 2)``;
    ``limit_m_s``: U > 0, or one per vehicle broadcast against ``(..., 1)``. The law's
    saturation, and the speed limit of the simulator and of a flying controller alike."""
    norm = np.sqrt(np.sum(velocity_m_s * velocity_m_s, axis=-1, keepdims=True))
    return velocity_m_s * (limit_m_s / np.maximum(limit_m_s, norm))


def consensus_velocity(
    error_north_m: NDArray[np.float64],
    error_east_m: NDArray[np.float64],
    weights: NDArray[np.float64],
    beta: float,
) -> NDArray[np.float64]:
    """ubar_i = -beta sum_j abar_ij (phat_ij - r_ij).

    error_north_m, error_east_m: ``(..., R, S)`` phat_ij - r_ij [m], may be NaN where the weight
    is 0. weights: ``(..., R, S)`` abar_ij, rows summing to 1 (or all 0 for an isolated vehicle).
    Returns ``(..., R, 2)`` [m/s].
    """
    unused = ~(weights > 0)
    sums = []
    for error_m in (error_north_m, error_east_m):
        weighted = weights * error_m
        np.copyto(weighted, 0.0, where=unused)  # NaN errors of zero weights, in place
        sums.append(np.sum(weighted, axis=-1))
    return -beta * np.stack(sums, axis=-1)


def row_normalised(mask: NDArray[np.bool_]) -> NDArray[np.float64]:
    """abar_ij = 1 / |N_i| over the True entries of each row of ``mask`` ``(..., R, S)``."""
    count = mask.sum(axis=-1, keepdims=True)
    return np.where(mask, 1.0 / np.maximum(count, 1), 0.0)

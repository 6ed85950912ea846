"""Saturated consensus tracking law, eq. ``formationtrackingcontrol``.

ubar_i = -beta sum_j abar_ij (phat_ij - r_ij),  u_i = sat_Ubar(ubar_i) + delta_r_i / T + u_0

Only relative quantities enter ubar and delta_r is a difference, so the command does not depend on
any common origin (the paper's remark after the law); vehicles share orientation only.
"""

import numpy as np


def saturate(velocity_m_s, limit_m_s):
    """sat_U(u) = u U / max(U, |u|) over the last axis. ``velocity_m_s``: ``(..., 2)``."""
    norm = np.sqrt(np.sum(velocity_m_s * velocity_m_s, axis=-1, keepdims=True))
    return velocity_m_s * (limit_m_s / np.maximum(limit_m_s, norm))


def consensus_velocity(estimate_m, desired_relative_m, weights, beta):
    """ubar_i = -beta sum_j abar_ij (phat_ij - r_ij).

    estimate_m, desired_relative_m: ``(..., R, S, 2)`` [m], may be NaN where the weight is 0.
    weights: ``(..., R, S)`` abar_ij, rows summing to 1 (or all 0 for an isolated vehicle).
    Returns ``(..., R, 2)`` [m/s].
    """
    error = np.where(weights[..., None] > 0, estimate_m - desired_relative_m, 0.0)
    return -beta * np.sum(weights[..., None] * error, axis=-2)


def row_normalised(mask):
    """abar_ij = 1 / |N_i| over the True entries of each row of ``mask`` ``(..., R, S)``."""
    count = mask.sum(axis=-1, keepdims=True)
    return np.where(mask, 1.0 / np.maximum(count, 1), 0.0)

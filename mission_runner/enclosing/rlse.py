"""Relative localization by RLSE with forgetting, eqs. ``cosinelaw`` and ``estimator``.

For an edge (i, j), with v the relative displacement p_ij(b) - p_ij(a) over an interval a -> b:

    zeta = (d(b)^2 - d(a)^2 - |v|^2) / 2          (cosine law: zeta = v . p_ij(a))
    eps  = zeta - v . phat(a)
    Gamma(b) = (Gamma(a) - Gamma v v^T Gamma / (beta_f + v^T Gamma v)) / beta_f
    phat(b)  = phat(a) + v + Gamma(b) v eps

The paper uses one step as the interval. Here each edge keeps an *anchor*: the last instant at which
its range and both odometries were known, with the estimate at that instant. Displacements come
from odometry (cumulative displacement in each vehicle's own north-east frame), so when a range or
a neighbour's message is missing the next update simply spans the longer interval: nothing is
guessed and nothing is corrupted. With every measurement present it is exactly the paper's update.

Arrays: ``(..., R, S)`` edges from R computing vehicles to S slots (slot 0 is the target),
vectors ``(..., R, S, 2)`` [m], gains ``(..., R, S, 2, 2)`` [1/m^2 scale].
"""

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class EdgeEstimates:
    """Per-edge estimator state at each edge's anchor instant.

    estimate_m: ``(..., R, S, 2)`` phat_ij at the anchor [m].
    gain: ``(..., R, S, 2, 2)`` Gamma_ij at the anchor.
    anchor_range_m: ``(..., R, S)`` d_ij at the anchor [m]; NaN where the edge has no anchor yet.
    anchor_odometry_m: ``(..., R, S, 2)`` relative odometry o_i - o_j at the anchor [m].
    """

    estimate_m: np.ndarray
    gain: np.ndarray
    anchor_range_m: np.ndarray
    anchor_odometry_m: np.ndarray

    @classmethod
    def initial(cls, shape, initial_gain=1.0):
        """The paper's phat = 0, Gamma = initial_gain * I; no anchor. ``shape``: ``(..., R, S)``."""
        return cls(
            estimate_m=np.zeros((*shape, 2)),
            gain=np.broadcast_to(np.eye(2) * initial_gain, (*shape, 2, 2)).copy(),
            anchor_range_m=np.full(shape, np.nan),
            anchor_odometry_m=np.zeros((*shape, 2)),
        )

    @property
    def anchored(self):
        """``(..., R, S)`` bool: the edge has had at least one range with both odometries."""
        return np.isfinite(self.anchor_range_m)

    def current(self, relative_odometry_m):
        """phat now: the anchor estimate carried forward by the odometry since the anchor.

        relative_odometry_m: ``(..., R, S, 2)`` o_i - o_j now (NaN where unknown).
        Returns ``(..., R, S, 2)``; NaN where the edge is unanchored or its odometry unknown.
        """
        moved = relative_odometry_m - self.anchor_odometry_m
        return np.where(self.anchored[..., None], self.estimate_m + moved, np.nan)


def rlse_update(estimates, range_m, relative_odometry_m, forgetting_factor):
    """One estimator update for every edge whose range and relative odometry are known now.

    range_m: ``(..., R, S)`` d_ij now [m], NaN where not measured (or not an edge).
    relative_odometry_m: ``(..., R, S, 2)`` o_i - o_j now [m], NaN where unknown.
    Unanchored edges with a measurement get their first anchor (phat and Gamma keep their initial
    values, as at the paper's k = 0); edges without a measurement keep their anchor.
    Returns the new :class:`EdgeEstimates`.
    """
    measured = np.isfinite(range_m) & np.isfinite(relative_odometry_m).all(axis=-1)
    update = measured & estimates.anchored

    v = np.where(update[..., None], relative_odometry_m - estimates.anchor_odometry_m, 0.0)
    range_now = np.where(update, range_m, 0.0)
    range_then = np.where(update, estimates.anchor_range_m, 0.0)
    v_n, v_e = v[..., 0], v[..., 1]
    zeta = 0.5 * (range_now**2 - range_then**2 - (v_n * v_n + v_e * v_e))

    # The 2x2 algebra written out per component: einsum on tiny matrices costs more than it saves.
    g = estimates.gain
    g00, g01, g10, g11 = g[..., 0, 0], g[..., 0, 1], g[..., 1, 0], g[..., 1, 1]
    p = estimates.estimate_m
    eps = zeta - (v_n * p[..., 0] + v_e * p[..., 1])
    gv_n = g00 * v_n + g01 * v_e
    gv_e = g10 * v_n + g11 * v_e
    vg_n = v_n * g00 + v_e * g10
    vg_e = v_n * g01 + v_e * g11
    denominator = forgetting_factor + v_n * gv_n + v_e * gv_e
    new_gain = np.empty_like(g)
    new_gain[..., 0, 0] = (g00 - gv_n * vg_n / denominator) / forgetting_factor
    new_gain[..., 0, 1] = (g01 - gv_n * vg_e / denominator) / forgetting_factor
    new_gain[..., 1, 0] = (g10 - gv_e * vg_n / denominator) / forgetting_factor
    new_gain[..., 1, 1] = (g11 - gv_e * vg_e / denominator) / forgetting_factor
    correction_n = new_gain[..., 0, 0] * v_n + new_gain[..., 0, 1] * v_e
    correction_e = new_gain[..., 1, 0] * v_n + new_gain[..., 1, 1] * v_e
    new_estimate = np.stack(
        [p[..., 0] + v_n + correction_n * eps, p[..., 1] + v_e + correction_e * eps], axis=-1
    )

    return EdgeEstimates(
        estimate_m=np.where(update[..., None], new_estimate, p),
        gain=np.where(update[..., None, None], new_gain, g),
        anchor_range_m=np.where(measured, range_m, estimates.anchor_range_m),
        anchor_odometry_m=np.where(
            measured[..., None], relative_odometry_m, estimates.anchor_odometry_m
        ),
    )

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

Every array is ``(..., R, S)``: edges from R computing vehicles to S slots (slot 0 is the target);
the update is elementwise, so a sparse swarm keeps the same state per edge, ``(..., E)``
(:mod:`.edges`).
Planar quantities are stored as separate north and east arrays and Gamma (symmetric) as its three
distinct entries: contiguous planes are several times faster than ``(..., 2)`` and ``(..., 2, 2)``
trailing axes for the large swarms the simulator runs.
"""

import functools
from dataclasses import dataclass
from typing import Self

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class EdgeEstimates:
    """Per-edge estimator state at each edge's anchor instant, all ``(..., R, S)``.

    estimate_north_m, estimate_east_m: phat_ij at the anchor [m].
    gain_nn, gain_ne, gain_ee: Gamma_ij at the anchor ([[nn, ne], [ne, ee]]).
    anchor_range_m: d_ij at the anchor [m]; NaN where the edge has no anchor yet.
    anchor_north_m, anchor_east_m: relative odometry o_i - o_j at the anchor [m].
    error_nn, error_ne, error_ee: a covariance bound of phat's error at the anchor [m^2], kept
    only when :func:`rlse_update` is given the range noise (None otherwise; NaN unanchored).
    """

    estimate_north_m: NDArray[np.float64]
    estimate_east_m: NDArray[np.float64]
    gain_nn: NDArray[np.float64]
    gain_ne: NDArray[np.float64]
    gain_ee: NDArray[np.float64]
    anchor_range_m: NDArray[np.float64]
    anchor_north_m: NDArray[np.float64]
    anchor_east_m: NDArray[np.float64]
    error_nn: NDArray[np.float64] | None = None
    error_ne: NDArray[np.float64] | None = None
    error_ee: NDArray[np.float64] | None = None

    @classmethod
    def initial(cls, shape: tuple[int, ...], initial_gain: float = 1.0) -> Self:
        """The paper's phat = 0, Gamma = initial_gain * I; no anchor. ``shape``: ``(..., R, S)``."""
        return cls(
            estimate_north_m=np.zeros(shape),
            estimate_east_m=np.zeros(shape),
            gain_nn=np.full(shape, float(initial_gain)),
            gain_ne=np.zeros(shape),
            gain_ee=np.full(shape, float(initial_gain)),
            anchor_range_m=np.full(shape, np.nan),
            anchor_north_m=np.zeros(shape),
            anchor_east_m=np.zeros(shape),
        )

    @functools.cached_property
    def anchored(self) -> NDArray[np.bool_]:
        """``(..., R, S)`` bool: the edge has had at least one range with both odometries.
        Worked out once (a step asks four times; the arrays are never written in place)."""
        return np.isfinite(self.anchor_range_m)

    @property
    def estimate_m(self) -> NDArray[np.float64]:
        """phat at the anchor as ``(..., R, S, 2)``."""
        return np.stack([self.estimate_north_m, self.estimate_east_m], axis=-1)

    @property
    def gain(self) -> NDArray[np.float64]:
        """Gamma at the anchor as ``(..., R, S, 2, 2)``."""
        rows = [[self.gain_nn, self.gain_ne], [self.gain_ne, self.gain_ee]]
        return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)

    @property
    def bearing_std_rad(self) -> NDArray[np.float64]:
        """``(..., R, S)`` how far phat's bearing may be off [rad]: the worst-direction std of
        its error over the range at the anchor. NaN where no error bound is kept."""
        if self.error_nn is None or self.error_ne is None or self.error_ee is None:
            return np.full(self.anchor_range_m.shape, np.nan)
        nn, ne, ee = self.error_nn, self.error_ne, self.error_ee
        largest = 0.5 * (nn + ee) + np.sqrt(0.25 * (nn - ee) ** 2 + ne * ne)
        return np.sqrt(np.maximum(largest, 0.0)) / self.anchor_range_m

    def current(
        self, relative_north_m: NDArray[np.float64], relative_east_m: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """phat now: the anchor estimate carried forward by the odometry since the anchor.

        relative_north_m, relative_east_m: ``(..., R, S)`` o_i - o_j now (NaN where unknown).
        Returns ``(north, east)``; NaN where the edge is unanchored or its odometry unknown.
        """
        unanchored = ~self.anchored
        north = _sum_into(relative_north_m - self.anchor_north_m, self.estimate_north_m)
        east = _sum_into(relative_east_m - self.anchor_east_m, self.estimate_east_m)
        np.copyto(north, np.nan, where=unanchored)
        np.copyto(east, np.nan, where=unanchored)
        return north, east


def rlse_update(
    estimates: EdgeEstimates,
    range_m: NDArray[np.float64],
    relative_north_m: NDArray[np.float64],
    relative_east_m: NDArray[np.float64],
    forgetting_factor: float,
    *,
    range_noise_std_m: float | None = None,
    min_displacement_m: float = 0.0,
) -> EdgeEstimates:
    """One estimator update for every edge whose range and relative odometry are known now.

    range_m: ``(..., R, S)`` d_ij now [m], NaN where not measured (or not an edge).
    relative_north_m, relative_east_m: ``(..., R, S)`` o_i - o_j now [m], NaN where unknown.
    Unanchored edges with a measurement get their first anchor (phat and Gamma keep their initial
    values, as at the paper's k = 0); edges without a measurement keep their anchor.
    range_noise_std_m: sigma_r, to keep a bound of each estimate's error covariance (see
    :func:`_error_update`); None: none is kept. min_displacement_m: a range whose relative
    displacement since the anchor is shorter than this is not used (the anchor stays and the
    next update spans the longer interval, as for a range not measured): with noisy ranges such
    an update moves phat by about sigma_r d / |v| across what it knows, and with forgetting the
    regression starves to garbage while a pair barely moves. 0: every range is used (the paper).
    Returns the new :class:`EdgeEstimates`.
    """
    anchored = estimates.anchored
    if min_displacement_m > 0:
        moved_n = relative_north_m - estimates.anchor_north_m
        moved_e = relative_east_m - estimates.anchor_east_m
        short = moved_n * moved_n + moved_e * moved_e < min_displacement_m * min_displacement_m
        range_m = np.where(anchored & short, np.nan, range_m)
    measured = np.isfinite(range_m) & np.isfinite(relative_north_m) & np.isfinite(relative_east_m)
    update = measured & anchored
    # Edges that do not update compute NaN or stale values here; _where keeps their old state.
    v_n = relative_north_m - estimates.anchor_north_m
    v_e = relative_east_m - estimates.anchor_east_m
    anchor_range = estimates.anchor_range_m
    eps = _innovation(range_m, anchor_range, (v_n, v_e), estimates)
    new_nn, new_ne, new_ee = _gain_update(estimates, (v_n, v_e), forgetting_factor, update)
    k_n, k_e = new_nn * v_n, new_ne * v_n  # phat += v + k eps
    k_n += new_ne * v_e
    k_e += new_ee * v_e
    error = None
    if range_noise_std_m is not None:
        zeta_variance = range_noise_std_m**2 * (range_m * range_m + anchor_range * anchor_range)
        error = _error_update(estimates, (k_n, k_e), (v_n, v_e), zeta_variance, update=update)
        first = measured & ~anchored  # phat is the paper's 0: off by d, any way
        start = range_m * range_m
        error = (
            np.where(first, start, error[0]),
            np.where(first, 0.0, error[1]),
            np.where(first, start, error[2]),
        )
    p_n, p_e = estimates.estimate_north_m, estimates.estimate_east_m
    k_n *= eps
    k_e *= eps
    return EdgeEstimates(
        estimate_north_m=_where(update, _sum_into(p_n + v_n, k_n), p_n),
        estimate_east_m=_where(update, _sum_into(p_e + v_e, k_e), p_e),
        gain_nn=new_nn,
        gain_ne=new_ne,
        gain_ee=new_ee,
        anchor_range_m=np.where(measured, range_m, anchor_range),
        anchor_north_m=np.where(measured, relative_north_m, estimates.anchor_north_m),
        anchor_east_m=np.where(measured, relative_east_m, estimates.anchor_east_m),
        error_nn=None if error is None else error[0],
        error_ne=None if error is None else error[1],
        error_ee=None if error is None else error[2],
    )


def _error_update(
    estimates: EdgeEstimates,
    gain: tuple[NDArray[np.float64], NDArray[np.float64]],
    displacement: tuple[NDArray[np.float64], NDArray[np.float64]],
    zeta_variance: NDArray[np.float64],
    *,
    update: NDArray[np.bool_],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The error covariance bound C after an update: the error e = phat - p moves as
    e(b) = (I - k v^T) e(a) + k n, where n is zeta's noise (variance sigma_r^2 (d_a^2 + d_b^2);
    the noise shared by consecutive updates is neglected), so C(b) = A C A^T + k k^T var(n).
    Odometry carries phat and p alike, so C does not grow between updates; nor does it with the
    forgetting that inflates Gamma (forgetting weights data, it adds no error). At an edge's
    first anchor phat is the paper's 0, off by the range d in an unknown direction: C = d^2 I.
    With exact ranges C is then exact: |e| <= sqrt(lambda_max(C))."""
    k_n, k_e = gain
    v_n, v_e = displacement
    shape = update.shape
    c_nn = estimates.error_nn if estimates.error_nn is not None else np.full(shape, np.nan)
    c_ne = estimates.error_ne if estimates.error_ne is not None else np.full(shape, np.nan)
    c_ee = estimates.error_ee if estimates.error_ee is not None else np.full(shape, np.nan)
    a_nn, a_ne, a_en, a_ee = 1.0 - k_n * v_n, -k_n * v_e, -k_e * v_n, 1.0 - k_e * v_e
    # A C, then (A C) A^T, each 2 x 2 written out on the planes.
    ac_nn, ac_ne = a_nn * c_nn + a_ne * c_ne, a_nn * c_ne + a_ne * c_ee
    ac_en, ac_ee = a_en * c_nn + a_ee * c_ne, a_en * c_ne + a_ee * c_ee
    new_nn = ac_nn * a_nn + ac_ne * a_ne + k_n * k_n * zeta_variance
    new_ne = ac_nn * a_en + ac_ne * a_ee + k_n * k_e * zeta_variance
    new_ee = ac_en * a_en + ac_ee * a_ee + k_e * k_e * zeta_variance
    return (
        np.where(update, new_nn, c_nn),
        np.where(update, new_ne, c_ne),
        np.where(update, new_ee, c_ee),
    )


# The update runs on every edge of the simulator's swarms (65 280 for 256 vehicles) every step;
# the helpers below compute in place, in the order of the formulas, to spare temporaries.


def _innovation(
    range_m: NDArray[np.float64],
    anchor_range_m: NDArray[np.float64],
    displacement: tuple[NDArray[np.float64], NDArray[np.float64]],
    estimates: EdgeEstimates,
) -> NDArray[np.float64]:
    """eps = zeta - v . phat(a), zeta = (d(b)^2 - d(a)^2 - |v|^2) / 2, ``(..., R, S)``."""
    v_n, v_e = displacement
    zeta = range_m - anchor_range_m
    zeta *= range_m + anchor_range_m
    zeta -= _sum_into(v_n * v_n, v_e * v_e)
    zeta *= 0.5
    zeta -= _sum_into(v_n * estimates.estimate_north_m, v_e * estimates.estimate_east_m)
    return zeta


def _gain_update(
    estimates: EdgeEstimates,
    displacement: tuple[NDArray[np.float64], NDArray[np.float64]],
    forgetting_factor: float,
    update: NDArray[np.bool_],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Gamma(b) = (Gamma - Gamma v v^T Gamma / (beta_f + v^T Gamma v)) / beta_f, as (nn, ne, ee),
    where ``update``; Gamma(a) elsewhere."""
    v_n, v_e = displacement
    g_nn, g_ne, g_ee = estimates.gain_nn, estimates.gain_ne, estimates.gain_ee
    gv_n = _sum_into(g_nn * v_n, g_ne * v_e)
    gv_e = _sum_into(g_ne * v_n, g_ee * v_e)
    scale = v_n * gv_n
    scale += forgetting_factor
    scale += v_e * gv_e
    np.divide(1.0, scale, out=scale)
    forget = 1.0 / forgetting_factor
    new = []
    for gain, left, right in ((g_nn, gv_n, gv_n), (g_ne, gv_n, gv_e), (g_ee, gv_e, gv_e)):
        term = left * right
        term *= scale
        np.subtract(gain, term, out=term)
        term *= forget
        new.append(_where(update, term, gain))
    return new[0], new[1], new[2]


def _sum_into(total: NDArray[np.float64], term: NDArray[np.float64]) -> NDArray[np.float64]:
    """``total + term``, written into ``total`` (a temporary of the caller's)."""
    total += term
    return total


def _where(
    update: NDArray[np.bool_], new: NDArray[np.float64], old: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``np.where(update, new, old)``, written into ``new`` (a temporary of the caller's)."""
    np.copyto(new, old, where=~update)
    return new

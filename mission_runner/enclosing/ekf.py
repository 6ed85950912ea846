"""Relative localization by a per-edge extended Kalman filter on range, with outlier gating.

The state of edge (i, j) is p_ij = p_i - p_j (north, east). Between two instants a -> b it is
predicted by the relative odometry, exactly as the RLSE carries its estimate forward:

    p(b|a) = p(a) + v,            P(b|a) = P(a) + q (b - a) I

where v = (o_i - o_j)(b) - (o_i - o_j)(a) and q = 2 sigma_v^2 per step (each end's displacement
has per-axis noise sigma_v). The range d(b) = |p(b)| + n, n ~ N(0, sigma_r^2), updates it:

    H = p(b|a)^T / |p(b|a)|,  y = d(b) - |p(b|a)|,  s = H P(b|a) H^T + sigma_r^2,
    K = P(b|a) H^T / s,       p(b) = p(b|a) + K y,  P(b) = P(b|a) - s K K^T

Unlike the RLSE's cosine-law regressor (which squares the range, so its noise grows with the
distance and each range enters two consecutive regressors), this weighs each range by its own
variance and the odometry by its own, which is what brings the error down to what the sensors
allow.

A range whose normalised innovation y^2 / s exceeds ``gate_chi2`` is an outlier (NLOS: UWB reads
long through an obstacle): it is counted and treated as not measured, so the edge's anchor stays
and the next update spans the longer interval, as a missing range does for the RLSE.

Range-only filters need a starting point away from the symmetric ambiguity; each edge therefore
first runs the paper's cosine-law RLSE (:func:`.rlse.rlse_update`, with its own forgetting factor)
and hands over to the filter once that regression is well conditioned: enough updates, a
covariance bound small enough (:func:`_regression_covariance`), and what is left of its start no
more than its error from the sensors' noise (so with exact sensors never: the regression is then
exact, and better than a filter with floored noise). Until then the edge's estimate is the
regression's. An edge that gates ``gate_patience`` ranges in a row has lost track (or the world
changed under it); it returns to its regression, which has kept running on the accepted ranges.

Arrays follow :mod:`.rlse`: every field is ``(..., R, S)``, planar quantities as north/east planes
and the symmetric 2x2 covariance as its three distinct entries.
"""

from dataclasses import dataclass
from typing import Self

import numpy as np
from numpy.typing import NDArray

from .errors import EnclosingError
from .rlse import EdgeEstimates, rlse_update

#: Noise figures below these are taken as these [m]: a filter told that ranges and odometry are
#: perfect has no gain to compute. Their ratio sets how many steps a noise-free filter remembers
#: (about sqrt(range^2 / q) = 2.4): enough to see the line of sight turn, which is what resolves
#: the direction across it, and short enough to forget its start quickly (measured on a circling
#: edge: 1e-5 m of displacement floor takes 78 steps to 1e-6 m, 3e-5 m 67, 7e-5 m 71).
RANGE_FLOOR_M = 1e-4
DISPLACEMENT_FLOOR_M = 3e-5


@dataclass(frozen=True)
class FilterSettings:
    """Noise model, hand-over and gate of the per-edge filter.

    range_noise_std_m: sigma_r, std of one range [m]. displacement_noise_std_m: sigma_v, per-axis
    std of one vehicle's displacement over one step [m] (white; a drift is folded in by the
    caller). gate_chi2: a range is rejected when y^2 / s exceeds this (chi-square, 1 degree of
    freedom; 10.83 rejects 0.1 % of good ranges); None: no gate. gate_patience: ranges rejected in
    a row after which the edge restarts from its regression. initial_forgetting_factor: beta_f of
    the regression that starts each edge. handover_updates: regression updates before the hand-over.
    handover_std_m: the hand-over waits until the regression's covariance bound is below this
    (1 sigma, along its worst direction) [m]. range_common_std_m: the part of sigma_r that both
    ends of a pair read alike (the pair's bias and multipath; all of it when one exchange serves
    both ends), which averaging both ends' ranges does not remove [m]. gate_long_only: only
    ranges longer than predicted are gated (NLOS reads long, never short: a range far too short
    says the estimate is too long, and the filter takes it rather than coast on the error).
    """

    range_noise_std_m: float
    displacement_noise_std_m: float
    gate_chi2: float | None
    gate_patience: int
    initial_forgetting_factor: float
    handover_updates: int
    handover_std_m: float
    range_common_std_m: float
    gate_long_only: bool

    def __post_init__(self) -> None:
        rules = [
            (self.range_noise_std_m >= 0, "range_noise_std_m must be >= 0"),
            (self.displacement_noise_std_m >= 0, "displacement_noise_std_m must be >= 0"),
            (self.gate_chi2 is None or self.gate_chi2 > 0, "gate_chi2 must be > 0"),
            (self.gate_patience >= 1, "gate_patience must be >= 1"),
            (
                0 < self.initial_forgetting_factor <= 1,
                "initial_forgetting_factor must be in (0, 1]",
            ),
            (self.handover_updates >= 1, "handover_updates must be >= 1"),
            (self.handover_std_m > 0, "handover_std_m must be > 0"),
            (self.range_common_std_m >= 0, "range_common_std_m must be >= 0"),
        ]
        broken = [message for ok, message in rules if not ok]
        if broken:
            raise EnclosingError("; ".join(broken))

    @property
    def range_variance_m2(self) -> float:
        """sigma_r^2, floored [m^2]."""
        return max(self.range_noise_std_m, RANGE_FLOOR_M) ** 2

    @property
    def process_variance_m2(self) -> float:
        """q: per-axis variance the relative odometry adds per step (both ends) [m^2]."""
        return 2.0 * max(self.displacement_noise_std_m, DISPLACEMENT_FLOOR_M) ** 2


@dataclass(frozen=True)
class FilterEdges:
    """Per-edge state of the filter estimator, all ``(..., R, S)``.

    filter: p_ij and its covariance P (in the gain fields) at the filter's anchor.
    regression: the cosine-law RLSE that starts the edge (and restarts it).
    engaged: the filter has taken over from the regression.
    anchor_step: the step of the filter's anchor (process noise grows with the steps since).
    regression_updates: updates the regression has made. rejected_in_row: ranges gated in a row.
    start_range_m: the edge's first range (how far the paper's phat = 0 start was off) [m].
    """

    filter: EdgeEstimates
    regression: EdgeEstimates
    engaged: NDArray[np.bool_]
    anchor_step: NDArray[np.float64]
    regression_updates: NDArray[np.float64]
    rejected_in_row: NDArray[np.float64]
    start_range_m: NDArray[np.float64]

    @classmethod
    def initial(cls, shape: tuple[int, ...], initial_gain: float = 1.0) -> Self:
        """Nothing anchored; the regression starts as the paper's RLSE does (phat = 0, Gamma =
        initial_gain * I). ``shape``: ``(..., R, S)``."""
        return cls(
            filter=EdgeEstimates.initial(shape, initial_gain),
            regression=EdgeEstimates.initial(shape, initial_gain),
            engaged=np.zeros(shape, dtype=bool),
            anchor_step=np.zeros(shape),
            regression_updates=np.zeros(shape),
            rejected_in_row=np.zeros(shape),
            start_range_m=np.full(shape, np.nan),
        )

    @property
    def anchored(self) -> NDArray[np.bool_]:
        """``(..., R, S)`` bool: the edge has had at least one range with both odometries."""
        return self.regression.anchored

    def current(
        self, relative_north_m: NDArray[np.float64], relative_east_m: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """p_ij now: the filter's (or, before the hand-over, the regression's) anchor estimate
        carried forward by the odometry since. Arguments and result as
        :meth:`.rlse.EdgeEstimates.current`."""
        filter_north, filter_east = self.filter.current(relative_north_m, relative_east_m)
        north, east = self.regression.current(relative_north_m, relative_east_m)
        return (
            np.where(self.engaged, filter_north, north),
            np.where(self.engaged, filter_east, east),
        )


def filter_update(
    edges: FilterEdges,
    range_m: NDArray[np.float64],
    relative_north_m: NDArray[np.float64],
    relative_east_m: NDArray[np.float64],
    *,
    step: int,
    settings: FilterSettings,
    initial_gain: float = 1.0,
    readings: NDArray[np.float64] | None = None,
) -> tuple[FilterEdges, NDArray[np.bool_]]:
    """One update of every edge whose range and relative odometry are known at ``step``.

    Arguments as :func:`.rlse.rlse_update`; ``initial_gain``: the regression's Gamma(0) scale, as
    given to :meth:`FilterEdges.initial`. readings: ``(..., R, S)`` how many independent ranges
    each ``range_m`` averages (both ends of a pair: 2, the variance of what is not common to
    both ends is halved, ``settings.range_common_std_m`` stays); None: one each.
    Returns the new state and the ``(..., R, S)`` mask of ranges rejected by the gate at this step.
    """
    measured = np.isfinite(range_m) & np.isfinite(relative_north_m) & np.isfinite(relative_east_m)
    # Predict the engaged edges to now and test their ranges (NaN or stale values elsewhere are
    # discarded by np.where below).
    prediction = _predict(
        edges,
        range_m,
        relative_north_m,
        relative_east_m,
        step=step,
        settings=settings,
        readings=readings,
    )
    tested = measured & edges.engaged
    gated = tested & _outlying(prediction, settings)
    accepted = tested & ~gated
    rejected_in_row = np.where(gated, edges.rejected_in_row + 1, 0.0)
    rejected_in_row = np.where(tested, rejected_in_row, edges.rejected_in_row)
    lost = rejected_in_row >= settings.gate_patience
    filtered = _corrected(
        edges.filter, prediction, accepted, range_m, relative_north_m, relative_east_m
    )
    anchor_step = np.where(accepted, float(step), edges.anchor_step)

    regression, updated, updates, start_range = _regression_step(
        edges, range_m, relative_north_m, relative_east_m, gated=gated, lost=lost, settings=settings
    )

    # Hand over where the regression is ready (it was updated now, so its anchor is now).
    variance, bias = _regression_covariance(
        regression, updates, settings, start_range, initial_gain
    )
    ready = updated & _regression_ready(regression, updates, variance, bias, settings)
    handover = ready & (~edges.engaged | lost)
    state = FilterEdges(
        filter=_handed_over(filtered, regression, variance, handover),
        regression=regression,
        engaged=(edges.engaged & ~lost) | handover,
        anchor_step=np.where(handover, float(step), anchor_step),
        regression_updates=updates,
        rejected_in_row=np.where(handover | lost, 0.0, rejected_in_row),
        start_range_m=start_range,
    )
    return state, gated


@dataclass(frozen=True)
class _Prediction:
    """The filter's anchors carried to now, every field ``(..., R, S)``: p(b|a) (``north_m``,
    ``east_m``), P(b|a) (``nn``, ``ne``, ``ee``), P(b|a) H^T (``ph_north``, ``ph_east``), the
    innovation y and its variance s."""

    north_m: NDArray[np.float64]
    east_m: NDArray[np.float64]
    nn: NDArray[np.float64]
    ne: NDArray[np.float64]
    ee: NDArray[np.float64]
    ph_north: NDArray[np.float64]
    ph_east: NDArray[np.float64]
    innovation: NDArray[np.float64]
    innovation_variance: NDArray[np.float64]


def _predict(
    edges: FilterEdges,
    range_m: NDArray[np.float64],
    relative_north_m: NDArray[np.float64],
    relative_east_m: NDArray[np.float64],
    *,
    step: int,
    settings: FilterSettings,
    readings: NDArray[np.float64] | None,
) -> _Prediction:
    """Every edge's filter predicted to ``step`` and its range's innovation (meaningful where
    the edge is engaged and measured; arguments as :func:`filter_update`)."""
    old = edges.filter
    v_n = relative_north_m - old.anchor_north_m
    v_e = relative_east_m - old.anchor_east_m
    p_n, p_e = old.estimate_north_m + v_n, old.estimate_east_m + v_e
    spread = settings.process_variance_m2 * (step - edges.anchor_step)
    c_nn, c_ne, c_ee = old.gain_nn + spread, old.gain_ne, old.gain_ee + spread
    predicted = np.sqrt(p_n * p_n + p_e * p_e)
    h_n = p_n / np.maximum(predicted, 1e-12)
    h_e = p_e / np.maximum(predicted, 1e-12)
    ph_n = c_nn * h_n + c_ne * h_e
    ph_e = c_ne * h_n + c_ee * h_e
    # Second-order terms of the range (its Hessian is (I - H^T H) / |p|): the curvature lengthens
    # the expected range by P_perp / 2|p| and adds (P_perp / |p|)^2 / 2 of variance, P_perp being
    # the variance across the line of sight. Without them a start that is good to decimetres
    # looks, to a filter fed exact ranges, like evidence against every range after the first.
    along = h_n * ph_n + h_e * ph_e
    across = np.maximum(c_nn + c_ee - along, 0.0) / np.maximum(predicted, 1e-12)
    range_variance: float | NDArray[np.float64] = settings.range_variance_m2
    if readings is not None:
        common = min(settings.range_common_std_m**2, settings.range_variance_m2)
        range_variance = (range_variance - common) / np.maximum(readings, 1.0) + common
    return _Prediction(
        north_m=p_n,
        east_m=p_e,
        nn=c_nn,
        ne=c_ne,
        ee=c_ee,
        ph_north=ph_n,
        ph_east=ph_e,
        innovation=range_m - (predicted + 0.5 * across),
        innovation_variance=along + range_variance + 0.5 * across * across,
    )


def _outlying(prediction: _Prediction, settings: FilterSettings) -> NDArray[np.bool_]:
    """``(..., R, S)``: the ranges the gate rejects (none without a gate)."""
    innovation = prediction.innovation
    if settings.gate_chi2 is None:
        return np.zeros(innovation.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        outlying = innovation * innovation > settings.gate_chi2 * prediction.innovation_variance
        if settings.gate_long_only:
            outlying &= innovation > 0
    return outlying


def _corrected(  # noqa: PLR0917 - the update's pieces, each named
    old: EdgeEstimates,
    prediction: _Prediction,
    accepted: NDArray[np.bool_],
    range_m: NDArray[np.float64],
    relative_north_m: NDArray[np.float64],
    relative_east_m: NDArray[np.float64],
) -> EdgeEstimates:
    """The filter after its ``accepted`` ranges (the Kalman update, anchored now); the other
    edges keep ``old``."""
    s = prediction.innovation_variance
    k_n, k_e = prediction.ph_north / s, prediction.ph_east / s
    innovation = prediction.innovation
    return EdgeEstimates(
        estimate_north_m=np.where(
            accepted, prediction.north_m + k_n * innovation, old.estimate_north_m
        ),
        estimate_east_m=np.where(
            accepted, prediction.east_m + k_e * innovation, old.estimate_east_m
        ),
        gain_nn=np.where(accepted, prediction.nn - s * k_n * k_n, old.gain_nn),
        gain_ne=np.where(accepted, prediction.ne - s * k_n * k_e, old.gain_ne),
        gain_ee=np.where(accepted, prediction.ee - s * k_e * k_e, old.gain_ee),
        anchor_range_m=np.where(accepted, range_m, old.anchor_range_m),
        anchor_north_m=np.where(accepted, relative_north_m, old.anchor_north_m),
        anchor_east_m=np.where(accepted, relative_east_m, old.anchor_east_m),
    )


def _regression_step(
    edges: FilterEdges,
    range_m: NDArray[np.float64],
    relative_north_m: NDArray[np.float64],
    relative_east_m: NDArray[np.float64],
    *,
    gated: NDArray[np.bool_],
    lost: NDArray[np.bool_],
    settings: FilterSettings,
) -> tuple[EdgeEstimates, NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """The edges' regressions after this step's ranges less the ``gated`` ones: the new
    regression, where it was updated, its update count (afresh where the filter ``lost`` track)
    and each edge's first range, all ``(..., R, S)``."""
    measured = np.isfinite(range_m) & np.isfinite(relative_north_m) & np.isfinite(relative_east_m)
    # The regression sees every range the gate let through (all of them before the hand-over).
    regression = rlse_update(
        edges.regression,
        np.where(gated, np.nan, range_m),
        relative_north_m,
        relative_east_m,
        settings.initial_forgetting_factor,
    )
    updated = measured & ~gated & edges.regression.anchored
    # An edge that lost track has its regression earn the hand-over afresh: the regression was
    # held back by the same gate, and what it learnt before may be what went wrong.
    updates = np.where(lost, 0.0, edges.regression_updates) + updated
    start_range = np.where(regression.anchored, edges.start_range_m, np.nan)
    start_range = np.where(np.isnan(start_range), regression.anchor_range_m, start_range)
    return regression, updated, updates, start_range


def _regression_ready(
    regression: EdgeEstimates,
    updates: NDArray[np.float64],
    variance: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
    bias: NDArray[np.float64],
    settings: FilterSettings,
) -> NDArray[np.bool_]:
    """``(..., R, S)``: the regression has earned the hand-over (updates, covariance bound
    ``variance`` and what is left of its start, ``bias``, from :func:`_regression_covariance`)."""
    worst = _largest_eigenvalue(*variance)
    # The filter is the better estimator on noise, the regression on exact data (the cosine law
    # is then exact and linear in p): hand over once what is left of the start (bias) is no more
    # than the regression's error from the noise the sensors are said to have, unfloored. With
    # noisy sensors that is soon; with nearly exact ones the regression first converges to their
    # noise; with exact ones it keeps the edge. (Handed an edge decimetres off, a filter whose
    # noise is floored at 0.1 mm trusts its linearisation too much: measured, one run in 100
    # gated exact ranges and restarted, and on a conservative covariance the second-order range
    # term holds it microns off for tens of steps.)
    forgotten = bias <= _regression_noise(regression, settings) - bias
    return (
        (updates >= settings.handover_updates) & (worst <= settings.handover_std_m**2) & forgotten
    )


def _handed_over(
    filtered: EdgeEstimates,
    regression: EdgeEstimates,
    variance: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]],
    handover: NDArray[np.bool_],
) -> EdgeEstimates:
    """The filter restarted from the regression (its estimate, anchor and covariance bound
    ``variance``) where ``handover``; ``filtered`` elsewhere."""
    variance_nn, variance_ne, variance_ee = variance
    return EdgeEstimates(
        estimate_north_m=np.where(handover, regression.estimate_north_m, filtered.estimate_north_m),
        estimate_east_m=np.where(handover, regression.estimate_east_m, filtered.estimate_east_m),
        gain_nn=np.where(handover, variance_nn, filtered.gain_nn),
        gain_ne=np.where(handover, variance_ne, filtered.gain_ne),
        gain_ee=np.where(handover, variance_ee, filtered.gain_ee),
        anchor_range_m=np.where(handover, regression.anchor_range_m, filtered.anchor_range_m),
        anchor_north_m=np.where(handover, regression.anchor_north_m, filtered.anchor_north_m),
        anchor_east_m=np.where(handover, regression.anchor_east_m, filtered.anchor_east_m),
    )


def _regression_noise(regression: EdgeEstimates, settings: FilterSettings) -> NDArray[np.float64]:
    """The regression's error variance from the sensors' noise as given (no floors), along its
    worst direction ``(..., R, S)``: see :func:`_regression_covariance`."""
    distance = regression.anchor_range_m
    given = 2.0 * settings.range_noise_std_m**2 + 2.0 * settings.displacement_noise_std_m**2
    g = _largest_eigenvalue(regression.gain_nn, regression.gain_ne, regression.gain_ee)
    return distance * distance * given * g


def _largest_eigenvalue(
    nn: NDArray[np.float64], ne: NDArray[np.float64], ee: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Largest eigenvalue of the symmetric 2x2 ``[[nn, ne], [ne, ee]]``, all ``(..., R, S)``."""
    return 0.5 * (nn + ee) + np.sqrt(0.25 * (nn - ee) ** 2 + ne * ne)


def _regression_covariance(
    regression: EdgeEstimates,
    updates: NDArray[np.float64],
    settings: FilterSettings,
    start_range_m: NDArray[np.float64],
    initial_gain: float,
) -> tuple[
    tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]
]:
    """A covariance bound of the regression's estimate ``(nn, ne, ee)``, each ``(..., R, S)``,
    and the part of it (on the diagonal) that is the start's bias.

    Noise: the cosine law's residual zeta - v.p carries d(b) n(b) - d(a) n(a) from the ranges and
    p.dv from the odometry, about d^2 (2 sigma_r^2 + q) for a range d; the regression's Gamma is
    its covariance per unit of that variance. Bias: the paper's start phat = 0, Gamma = Gamma(0)
    leaves beta_f^n Gamma(0)^-1 of prior weight after n updates, which keeps Gamma beta_f^n
    Gamma(0)^-1 of the start's error p(0), |p(0)| = the first range; added (twice over) as a
    variance so that the filter starts no more sure of itself than the regression has earned.
    """
    distance = regression.anchor_range_m
    noise = distance * distance * (2.0 * settings.range_variance_m2 + settings.process_variance_m2)
    g_nn, g_ne, g_ee = regression.gain_nn, regression.gain_ne, regression.gain_ee
    largest = _largest_eigenvalue(g_nn, g_ne, g_ee)
    pull = settings.initial_forgetting_factor**updates / initial_gain
    bias = (2.0 * largest * pull * start_range_m) ** 2
    return (noise * g_nn + bias, noise * g_ne, noise * g_ee + bias), bias

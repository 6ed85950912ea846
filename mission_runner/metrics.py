"""A run's result and its scoring, the same for a simulated and a flown run: the result's time
series (:class:`SimulationResult`), the headline metrics, their distribution over a batch, and the
scenario's pass/fail expectations.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .config import FLIGHT_METRICS, Expectation, MetricName, Scenario
from .enclosing import splay_spacing_error
from .enclosing.target import LOST

#: One run's value of a metric (a Python or numpy number; None where there is none).
MetricValue = float | np.floating[Any] | np.integer[Any] | None


def converged_step(error: NDArray[np.float64], tolerance: float) -> NDArray[np.int_]:
    """First step from which ``error`` ``(B, K)`` stays <= tolerance; -1 where it never does."""
    above = ~(error <= tolerance)  # NaN counts as not converged
    last_above = np.where(
        above.any(axis=-1), error.shape[-1] - 1 - np.argmax(above[..., ::-1], axis=-1), -1
    )
    step = last_above + 1
    return np.where(step >= error.shape[-1], -1, step)


def first_step(flag: NDArray[np.bool_]) -> NDArray[np.int_]:
    """First step at which ``flag`` ``(B, K)`` holds; -1 where it never does."""
    return np.where(flag.any(axis=-1), np.argmax(flag, axis=-1), -1)


def max_after_first(error: NDArray[np.float64], tolerance: float) -> NDArray[np.float64]:
    """Largest ``error`` ``(B, K)`` from the first step it is <= tolerance on (how far a run that
    had converged strays later: an occlusion, a hand-over); NaN where it never gets there."""
    reached = error <= tolerance
    first = np.where(reached.any(axis=-1), np.argmax(reached, axis=-1), error.shape[-1])
    after = np.arange(error.shape[-1]) >= first[..., None]
    worst = np.where(after, error, -np.inf).max(axis=-1)
    return np.where(reached.any(axis=-1), worst, np.nan)


#: Metrics whose -1 means "never", which no bound accepts.
NEVER_IS_NO_VALUE = (
    "tracking_converged_step",
    "localization_converged_step",
    "phase_converged_step",
    "target_lost_step",
    "graph_disconnected_step",
)


def run_metrics(result: SimulationResult) -> dict[str, NDArray[Any]]:
    """Headline metrics of every run: ``{name: (B,) array}``, names as in ``config.METRICS``."""
    tolerances = result.scenario.metrics
    commands = result.commands_m_s
    speed = np.sqrt(np.sum(commands * commands, axis=-1)).max(axis=(-1, -2))
    # With noise the final sample is a lottery; the last quarter of the run is a steadier figure.
    tail = max(1, result.tracking_error_m.shape[-1] // 4)
    metrics = {
        "final_tracking_error_m": result.tracking_error_m[:, -1],
        "tail_tracking_error_rms_m": np.sqrt(np.mean(result.tracking_error_m[:, -tail:] ** 2, -1)),
        "tail_localization_error_median_m": np.median(result.localization_error_m[:, -tail:], -1),
        "tail_localization_error_rms_m": np.sqrt(
            np.mean(result.localization_rms_m[:, -tail:] ** 2, -1)
        ),
        "final_localization_error_m": result.localization_error_m[:, -1],
        "final_phase_spacing_error_rad": result.phase_spacing_error_rad[:, -1],
        "tracking_converged_step": converged_step(
            result.tracking_error_m, tolerances.tracking_tolerance_m
        ),
        "localization_converged_step": converged_step(
            result.localization_error_m, tolerances.localization_tolerance_m
        ),
        "phase_converged_step": converged_step(
            result.phase_spacing_error_rad, tolerances.phase_tolerance_rad
        ),
        "max_consensus_speed_m_s": result.consensus_speed_m_s.max(axis=-1),
        "max_speed_m_s": speed,
        "min_separation_m": result.separation_m.min(axis=-1),
        "final_live_vehicles": result.live[:, -1].sum(axis=-1),
        "gated_ranges": result.gated_ranges.sum(axis=-1),
        "target_lost_step": first_step(result.target_status == LOST),
        "max_tracking_error_after_convergence_m": max_after_first(
            result.tracking_error_m, tolerances.tracking_tolerance_m
        ),
    }
    if result.graph_disconnected_step is not None:  # a sparse graph's (a complete one stays whole)
        metrics["graph_disconnected_step"] = result.graph_disconnected_step
    # Flight-only metrics (e.g. vehicles disarmed at the end) come with the result; a simulated
    # run has none, and an expectation on them then fails with "no value".
    for name in FLIGHT_METRICS:
        if name in result.extra_metrics:
            metrics[name] = np.asarray(result.extra_metrics[name])
    return metrics


LOWER_IS_WORSE = {"min_separation_m", "final_live_vehicles"}


def distribution(values: ArrayLike, name: str) -> dict[str, float | int | None]:
    """Median, p95 and worst of one metric over runs. Convergence steps of -1 count as never;
    runs where it is not a finite number (diverged, or not measured) are counted as
    ``not_finite``, and the statistics they would make meaningless are None."""
    values = np.asarray(values, dtype=float)
    if name in NEVER_IS_NO_VALUE:
        never = int(np.sum(values < 0))
        finite = values[values >= 0]
        if finite.size == 0:
            return {"median": None, "p95": None, "worst": None, "never_converged": never}
        worst = None if never else float(finite.max())
        return {
            "median": float(np.median(np.where(values < 0, np.inf, values)))
            if never * 2 < values.size
            else None,
            "p95": float(np.percentile(finite, 95)) if never == 0 else None,
            "worst": worst,
            "never_converged": never,
        }
    tail = "p5" if name in LOWER_IS_WORSE else "p95"
    not_finite = int(np.sum(~np.isfinite(values)))
    if not_finite:  # diverged (inf, NaN) or not measured in some runs: no number stands for them
        # Fewer than half: the median is still a number, with NaN counted as the worst.
        ranked = np.where(np.isnan(values), -np.inf if tail == "p5" else np.inf, values)
        median = float(np.median(ranked)) if not_finite * 2 < values.size else None
        return {"median": median, tail: None, "worst": None, "not_finite": not_finite}
    if name in LOWER_IS_WORSE:
        return {
            "median": float(np.median(values)),
            "p5": float(np.percentile(values, 5)),
            "worst": float(values.min()),
        }
    return {
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
        "worst": float(values.max()),
    }


def check_expectations(
    expect: Mapping[MetricName, Expectation], metrics: Mapping[str, MetricValue]
) -> list[str]:
    """Failed expectations as readable strings (empty when the run passes).

    expect: the scenario's ``expect`` mapping; metrics: ``{name: scalar}`` of one run. A
    convergence step of -1 (never) fails any bound on it. A run that lost its target
    (``target_lost_step`` >= 0) fails unless ``expect`` bounds ``target_lost_step``: losing the
    target is a failure of the mission unless the scenario sets out to show it. So does a run
    whose losses disconnected a sparse neighbourhood graph (``graph_disconnected_step``).
    """
    failures = []
    lost_at = metrics.get("target_lost_step")
    if "target_lost_step" not in expect and lost_at is not None and lost_at >= 0:
        failures.append(
            f"target lost at step {int(lost_at)} (bound target_lost_step in expect: to accept it)"
        )
    cut_at = metrics.get("graph_disconnected_step")
    if "graph_disconnected_step" not in expect and cut_at is not None and cut_at >= 0:
        failures.append(
            f"neighbourhood graph disconnected at step {int(cut_at)} "
            "(bound graph_disconnected_step in expect: to accept it)"
        )
    for name, bound in expect.items():
        value = metrics.get(name)
        if value is None:
            if name not in FLIGHT_METRICS:
                failures.append(f"{name}: not measured")
            continue  # a flight-only bound does not apply to a simulated run
        never = name in NEVER_IS_NO_VALUE and value < 0
        if value is None or never or not np.isfinite(value):
            failures.append(f"{name} = {'never' if never else value}: no value to compare")
            continue
        if bound.max is not None and value > bound.max:
            failures.append(f"{name} = {value:.6g} > max {bound.max:g}")
        if bound.min is not None and value < bound.min:
            failures.append(f"{name} = {value:.6g} < min {bound.min:g}")
    return failures


def formation_centre(
    positions_m: NDArray[np.float64], live: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """Centroid of the live vehicles: positions_m ``(..., n, 2)``, live ``(..., n)`` -> ``(..., 2)``
    (the origin where none is live)."""
    total = np.sum(np.where(live[..., None], positions_m, 0.0), axis=-2)
    return total / np.maximum(live.sum(axis=-1, keepdims=True), 1)


def tracking_error(
    positions_m: NDArray[np.float64], live: NDArray[np.bool_], target_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance [m] from the formation's centre to the target: positions_m ``(..., n, 2)``, live
    ``(..., n)``, target_m ``(..., 2)`` -> ``(...)``."""
    gap = formation_centre(positions_m, live) - target_m
    return np.sqrt(np.sum(gap * gap, axis=-1))


def edge_rms(error_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """RMS over edges of |phat_ij - p_ij|: error_m ``(..., R, S)`` (NaN: not estimated, which does
    not count; inf: diverged, which does) -> ``(...)`` (0 where no edge is estimated)."""
    uncounted = np.isnan(error_m)
    square = error_m * error_m
    np.copyto(square, 0.0, where=uncounted)  # in place: a 256-vehicle swarm's plane is 0.5 MB
    counted = (~uncounted).sum(axis=(-1, -2))
    return np.sqrt(square.sum(axis=(-1, -2)) / np.maximum(counted, 1))


def closest_pair(distance_m: NDArray[np.float64], live: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Smallest distance between two live vehicles: distance_m ``(..., n, n)``, live ``(..., n)``
    -> ``(...)`` (inf with fewer than two)."""
    pair = live[..., :, None] & live[..., None, :] & ~np.eye(live.shape[-1], dtype=bool)
    return np.where(pair, distance_m, np.inf).min(axis=(-1, -2))


def closest_live_pair(
    position_m: NDArray[np.float64], live: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """:func:`closest_pair` from the positions ``(..., n, 2)`` without the ``(n, n)`` distances:
    the live vehicles sorted by north, the pairs d places apart for d = 1, 2, ... until every
    such pair is further apart in north alone than the closest pair so far. Each distance is
    computed as in the matrix (``sqrt(dn^2 + de^2)`` of ``p_i - p_j``), so the result is the
    same bit for bit; O(n d) for the d that ends the search (a few dozen for 1000 vehicles)."""
    north = np.where(live, position_m[..., 0], np.inf)  # the lost ones sort last
    order = np.argsort(north, axis=-1, kind="stable")
    ordered = np.take_along_axis(position_m, order[..., None], axis=-2)
    ordered_live = np.take_along_axis(live, order, axis=-1)
    closest = np.full(live.shape[:-1], np.inf)
    for apart in range(1, live.shape[-1]):
        first, second = ordered[..., :-apart, :], ordered[..., apart:, :]
        both = ordered_live[..., :-apart] & ordered_live[..., apart:]
        north_gap = first[..., 0] - second[..., 0]
        east_gap = first[..., 1] - second[..., 1]
        distance = np.sqrt(north_gap * north_gap + east_gap * east_gap)
        closest = np.minimum(closest, np.where(both, distance, np.inf).min(axis=-1))
        # Sorted: pairs further apart in the order are at least this far apart in north.
        if np.all(np.where(both, -north_gap, np.inf).min(axis=-1) >= closest):
            break
    return closest


@dataclass(frozen=True)
class SimulationResult:
    """Time series of a (batched) run; B runs, K steps, N vehicles.

    times_s ``(K+1,)``; target_m ``(K+1, 2)``; positions_m ``(B, K+1, N, 2)``;
    phases_rad ``(B, K+1, N)``; commands_m_s ``(B, K, N, 2)`` (after the speed bound);
    live ``(B, K+1, N)``; tracking_error_m ``(B, K+1)``; localization_error_m ``(B, K)`` (max over
    estimated edges at step k); localization_rms_m ``(B, K)`` (RMS over the estimated edges at
    step k); gated_ranges ``(B, K)`` (ranges the estimators rejected as outliers at step k);
    phase_spacing_error_rad ``(B, K+1)``; consensus_speed_m_s ``(B, K)`` (max over vehicles of
    |sat(ubar)|); separation_m ``(B, K+1)`` (closest live pair); target_status ``(B, K)`` (what
    the formation knew of the target at step k: ``enclosing.target`` OBSERVED, PREDICTED or LOST;
    a flight's worst over its vehicles); estimates_m ``(K, N, N+1, 2)``
    run 0's phat_ij(k) [north, east] (slot 0 the target; NaN where not estimated), or None
    (flights carry theirs in the controllers' step records; a swarm whose estimates would exceed
    ``ESTIMATES_LIMIT_BYTES`` does not keep them).
    """

    scenario: Scenario
    times_s: NDArray[np.float64]
    target_m: NDArray[np.float64]
    positions_m: NDArray[np.float64]
    phases_rad: NDArray[np.float64]
    commands_m_s: NDArray[np.float64]
    live: NDArray[np.bool_]
    tracking_error_m: NDArray[np.float64]
    localization_error_m: NDArray[np.float64]
    localization_rms_m: NDArray[np.float64]
    gated_ranges: NDArray[np.int_]
    phase_spacing_error_rad: NDArray[np.float64]
    consensus_speed_m_s: NDArray[np.float64]
    separation_m: NDArray[np.float64]
    target_status: NDArray[np.int8]
    #: Simulated only, ``(B, K)``: ranges between vehicles read in an NLOS burst at step k, and
    #: ranges the estimators gated that were not (the gate's false rejections).
    nlos_ranges: NDArray[np.int_] | None = None
    false_rejections: NDArray[np.int_] | None = None
    #: Flight-only metrics, ``{name: (B,) array}`` (see ``config.FLIGHT_METRICS``).
    extra_metrics: dict[str, NDArray[Any]] = field(default_factory=dict)
    estimates_m: NDArray[np.float64] | None = None
    #: Simulated with a sparse ``algorithm.graph`` only, ``(B,)``: the first step at which the
    #: live vehicles' graph is disconnected (a loss cut it), -1 if never.
    graph_disconnected_step: NDArray[np.int_] | None = None

    @property
    def runs(self) -> int:
        return self.tracking_error_m.shape[0]


def score(
    scenario: Scenario,
    times: NDArray[np.float64],
    target: NDArray[np.float64],
    out: Mapping[str, NDArray[Any]],
    extra_metrics: dict[str, NDArray[Any]] | None = None,
) -> SimulationResult:
    """A :class:`SimulationResult` from recorded series (simulated or flown): adds the tracking
    error (centroid of live vehicles to target) and the phase-spacing error.

    times ``(K+1,)``, target ``(K+1, 2)``; ``out`` the series named as the result's fields
    (positions_m, phases_rad, commands_m_s, live, localization_error_m, localization_rms_m,
    gated_ranges, consensus_speed_m_s, separation_m; optionally estimates_m), shaped as
    documented there."""
    positions, live = out["positions_m"], out["live"]
    tracking = tracking_error(positions, live, target)
    spacing = splay_spacing_error(out["phases_rad"], live)
    return SimulationResult(
        scenario=scenario,
        times_s=times,
        target_m=target,
        tracking_error_m=tracking,
        phase_spacing_error_rad=spacing,
        extra_metrics=extra_metrics or {},
        **out,
    )


@dataclass(frozen=True)
class SweepPoint:
    """One combination: its values (by path) and every metric over its runs, ``{name: (B,)}``."""

    values: dict[str, Any]
    metrics: dict[str, NDArray[Any]]

"""The sensor models: true positions in, what a UWB radio, a target tracker and an odometry
source would report out (numpy only).

One model for every place that synthesises measurements: the numeric simulator
(:mod:`.sim.simulator`, batched), the emulated world (:mod:`.world`) and the range aid for real
autopilots (:mod:`.runner.ranges`) all call these functions with the scenario's ``sensors:``
settings, so a noise, dropout or range limit means the same everywhere.

``rng`` is a numpy ``Generator`` or anything with its ``normal(scale=, size=)`` and
``uniform(size=)`` (the simulator's batch streams).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from .config import SensorConfig


class Rng(Protocol):
    """What the models draw from: a numpy ``Generator``, or the simulator's batch streams (called
    with keywords only)."""

    def normal(self, *, scale: float, size: Any) -> Any: ...

    def uniform(self, *, low: float = ..., high: float = ..., size: Any) -> Any: ...


def measure_ranges(
    from_m: ArrayLike,
    sensors: SensorConfig,
    rng: Rng,
    *,
    to_m: ArrayLike | None = None,
    measured: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """Ranges from every point of ``from_m`` to every point of ``to_m``, through
    :func:`range_readings`.

    from_m: ``(..., n, d)`` true positions [m] (NaN rows: not measured this time).
    to_m: ``(..., m, d)``; default ``from_m`` (then a point is never ranged to itself).
    measured: ``(..., n, m)`` bool, the pairs that are ranged at all (default: every pair).
    Returns ``(..., n, m)`` ranges [m], NaN where nothing is measured.
    """
    points = np.asarray(from_m, dtype=float)
    others = points if to_m is None else np.asarray(to_m, dtype=float)
    gaps = points[..., :, None, :] - others[..., None, :, :]
    distances = np.sqrt(np.sum(gaps * gaps, axis=-1))
    if others is points:
        not_self = ~np.eye(distances.shape[-1], dtype=bool)
        measured = not_self if measured is None else measured & not_self
    return range_readings(distances, sensors, rng, measured=measured)


def range_readings(
    true_m: NDArray[np.float64],
    sensors: SensorConfig,
    rng: Rng,
    *,
    measured: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """What a UWB radio reads for true distances ``true_m`` (any shape, NaN: no line): Gaussian
    noise (``range_noise_std_m``, reported as its absolute value), random dropouts
    (``range_dropout_probability``), NLOS outliers (``range_outlier_probability``: longer by a
    bias uniform in ``range_outlier_bias_m``) and a maximum range (``range_max_m``); NaN where
    nothing is read, or where ``measured`` (same shape, bool) is False. Noise, dropout and
    outliers are drawn for every entry, read or not, so that one pair's fate does not shift
    another's draws.
    """
    kept = np.isfinite(true_m)
    if measured is not None:
        kept &= measured
    readings = true_m
    if sensors.range_noise_std_m > 0:
        readings = readings + rng.normal(scale=sensors.range_noise_std_m, size=true_m.shape)
    if sensors.range_dropout_probability > 0:
        kept &= rng.uniform(size=true_m.shape) >= sensors.range_dropout_probability
    if sensors.range_outlier_probability > 0:
        outlier = rng.uniform(size=true_m.shape) < sensors.range_outlier_probability
        low, high = sensors.range_outlier_bias_m
        bias = rng.uniform(low=low, high=high, size=true_m.shape)
        readings = readings + np.where(outlier, bias, 0.0)
    if sensors.range_max_m is not None:
        kept &= readings <= sensors.range_max_m
    return np.where(kept, np.abs(readings), np.nan)


def target_seen(
    distance_m: NDArray[np.float64],
    sensors: SensorConfig,
    rng: Rng,
    *,
    looking: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """Which trackers see the target: those ``looking`` (``(..., n)`` bool: a tracker that is
    there, works and is not occluded) whose horizontal distance ``distance_m`` ``(..., n)`` [m]
    is within ``target_sensing_range_m``, less random misses (``target_dropout_probability``,
    drawn for every entry, only when set, so that scenarios without it draw as before)."""
    seen = looking & np.isfinite(distance_m)
    if sensors.target_sensing_range_m is not None:
        seen &= distance_m <= sensors.target_sensing_range_m
    if sensors.target_dropout_probability > 0:
        seen &= rng.uniform(size=distance_m.shape) >= sensors.target_dropout_probability
    return seen


def odometry_drift(sensors: SensorConfig, rng: Rng, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """A constant drift velocity [m/s] per vehicle, ``shape + (2,)``: ``displacement_drift_m_s``
    in a random direction (zeros without drift)."""
    if sensors.displacement_drift_m_s <= 0:
        return np.zeros((*shape, 2))
    angle = rng.uniform(low=0, high=2 * np.pi, size=shape)
    return sensors.displacement_drift_m_s * np.stack([np.cos(angle), np.sin(angle)], -1)


def odometry_error_step(
    sensors: SensorConfig, rng: Rng, error_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The odometry error after one more step: a random walk of ``displacement_noise_std_m`` per
    step. error_m: ``(..., 2)`` [m], returned unchanged without noise."""
    if sensors.displacement_noise_std_m <= 0:
        return error_m
    return error_m + rng.normal(scale=sensors.displacement_noise_std_m, size=error_m.shape)

"""The UWB-like range sensor model: true positions in, measured ranges out (numpy only).

One model for every place that synthesises ranges (the range aid of :mod:`.runner.ranges`; the
simulator and the emulator's world draw from the same settings, ``scenario.sensors``): Gaussian
noise, random dropouts and a maximum range.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from .config import SensorConfig


def measure_ranges(
    positions_m: ArrayLike, sensors: SensorConfig, rng: np.random.Generator
) -> NDArray[np.float64]:
    """Ranges between every pair of vehicles.

    positions_m: ``(n, d)`` true positions (NaN rows: vehicles not measured this time).
    sensors: a :class:`mission_runner.config.SensorConfig`. rng: a numpy ``Generator``.
    Returns ``(n, n)`` ranges [m], NaN where no range is measured (the diagonal, a missing
    vehicle, a dropout, beyond ``range_max_m``).
    """
    positions_m = np.asarray(positions_m, dtype=float)
    n = len(positions_m)
    gaps = positions_m[:, None, :] - positions_m[None, :, :]
    ranges = np.sqrt(np.sum(gaps * gaps, axis=-1))
    if sensors.range_noise_std_m > 0:
        ranges = np.abs(ranges + rng.normal(scale=sensors.range_noise_std_m, size=ranges.shape))
    kept = ~np.eye(n, dtype=bool) & np.isfinite(ranges)
    if sensors.range_dropout_probability > 0:
        kept &= rng.uniform(size=ranges.shape) >= sensors.range_dropout_probability
    if sensors.range_max_m is not None:
        kept &= ranges <= sensors.range_max_m
    return np.where(kept, ranges, np.nan)

"""A vehicle's own odometry, sampled at the exact instants the algorithm asks for.

Telemetry arrives at its own rate (LOCAL_POSITION_NED at 30-50 Hz) with the autopilot's
timestamp; step k needs the odometry at t_k = start + kT on every vehicle. :class:`OdometryTrack`
keeps the recent samples on the mission clock and interpolates linearly between the two that
bracket t_k, so every vehicle's o_i(t_k) refers to the same instant whatever the telemetry phase.
"""

import bisect
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class OdometrySample:
    """One LOCAL_POSITION_NED sample on the mission clock: time [s], north/east/down [m]."""

    time_s: float
    north_m: float
    east_m: float
    down_m: float


class OdometryTrack:
    """The last ``capacity`` samples, in time order (late or repeated samples are dropped)."""

    def __init__(self, capacity: int = 256) -> None:
        self._samples: deque[OdometrySample] = deque(maxlen=capacity)
        self._times: deque[float] = deque(maxlen=capacity)

    def add(self, sample: OdometrySample) -> bool:
        """Record a sample; returns False (and ignores it) if it is not newer than the last."""
        if self._times and sample.time_s <= self._times[-1]:
            return False
        self._samples.append(sample)
        self._times.append(sample.time_s)
        return True

    @property
    def latest(self) -> OdometrySample | None:
        """The newest sample, or None."""
        return self._samples[-1] if self._samples else None

    def at(self, time_s: float) -> tuple[float, float, float] | None:
        """``(north_m, east_m, down_m)`` at ``time_s``, or None if no two samples bracket it.

        A sample exactly at ``time_s`` is returned as is.
        """
        index = bisect.bisect_left(self._times, time_s)
        if index < len(self._times) and self._times[index] == time_s:
            sample = self._samples[index]
            return sample.north_m, sample.east_m, sample.down_m
        if index == 0 or index == len(self._times):
            return None
        before, after = self._samples[index - 1], self._samples[index]
        weight = (time_s - before.time_s) / (after.time_s - before.time_s)

        def between(a: float, b: float) -> float:
            return a + weight * (b - a)

        return (
            between(before.north_m, after.north_m),
            between(before.east_m, after.east_m),
            between(before.down_m, after.down_m),
        )

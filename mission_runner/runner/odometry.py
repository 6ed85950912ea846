"""A vehicle's own odometry, sampled at the exact instants the algorithm asks for.

Telemetry arrives at its own rate (LOCAL_POSITION_NED at 30-50 Hz) with the autopilot's
timestamp; step k needs the odometry at t_k = start + kT on every vehicle. :class:`OdometryTrack`
keeps the recent samples and interpolates linearly between the two that bracket t_k, so every
vehicle's o_i(t_k) refers to the same instant whatever the telemetry phase; asked to, it
extrapolates a little past the newest sample at that sample's velocity rather than wait for the
next one.
"""

import bisect
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

#: LOCAL_POSITION_NED asked of the autopilot [Hz]. The controller needs the odometry at t_k,
#: 8 times a second, and takes it between the two samples around t_k or up to two periods past
#: the newest at its velocity (a 1 m/s^2 turn moves 3 mm off that line in 80 ms, far below the
#: ranges' noise). Each sample costs a vehicle process about 0.04 % of a core (MAVSDK's
#: raw-message plugin: a JSON encode in its thread, a Python callback, thread wake-ups): on PX4
#: SIH, 50 Hz asked gave 39 samples/s for 2.0 % of a core, 25 Hz 18/s for 1.1 %, none 0.5 %
#: (``python bench/link_bench.py``).
ODOMETRY_RATE_HZ = 25.0
ODOMETRY_PERIOD_S = 1.0 / ODOMETRY_RATE_HZ


@dataclass(frozen=True, slots=True)
class OdometrySample:
    """One LOCAL_POSITION_NED sample: time [s], north/east/down [m] and, where the source gives
    it, the velocity [m per second of the same clock] (NaN: none)."""

    time_s: float
    north_m: float
    east_m: float
    down_m: float
    north_m_s: float = math.nan
    east_m_s: float = math.nan
    down_m_s: float = math.nan


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

    def highest_since(self, time_s: float) -> float | None:
        """The least ``down_m`` (the highest point) of the samples from ``time_s`` on, or None
        if there are none."""
        index = bisect.bisect_left(self._times, time_s)
        downs = [self._samples[i].down_m for i in range(index, len(self._samples))]
        return min(downs, default=None)

    def at(self, time_s: float, *, extrapolate_s: float = 0.0) -> tuple[float, float, float] | None:
        """``(north_m, east_m, down_m)`` at ``time_s``, or None if no two samples bracket it.

        A sample exactly at ``time_s`` is returned as is. With ``extrapolate_s`` > 0, a time
        after the newest sample by no more than that is extrapolated from it at its velocity
        (when it has one) instead of waiting for the next: at 50 Hz, the wait was 10 ms on
        average, a quarter of what a step's command took to go out, and an autopilot's velocity
        over 20 ms moves the estimate by under a millimetre.
        """
        index = bisect.bisect_left(self._times, time_s)
        if index < len(self._times) and self._times[index] == time_s:
            sample = self._samples[index]
            return sample.north_m, sample.east_m, sample.down_m
        if index == len(self._times) and index > 0:
            return self._extrapolated(self._samples[-1], time_s, extrapolate_s)
        if index == 0:
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

    @staticmethod
    def _extrapolated(
        sample: OdometrySample, time_s: float, extrapolate_s: float
    ) -> tuple[float, float, float] | None:
        ahead_s = time_s - sample.time_s
        velocity = (sample.north_m_s, sample.east_m_s, sample.down_m_s)
        if ahead_s > extrapolate_s or not all(map(math.isfinite, velocity)):
            return None
        return (
            sample.north_m + velocity[0] * ahead_s,
            sample.east_m + velocity[1] * ahead_s,
            sample.down_m + velocity[2] * ahead_s,
        )


class FedTrack(OdometryTrack):
    """An :class:`OdometryTrack` fed from another thread: MAVSDK's receive thread hands each
    sample over with :meth:`feed` (a deque append, safe across threads), and the owner's thread
    files what came in whenever it reads. A sample through MAVSDK's asyncio stream cost a
    thread hop, an event-loop wake-up and a queue per message: 6 % of a core for
    LOCAL_POSITION_NED alone at 100 Hz, most of a vehicle process's MAVLink work.

    ``on_feed`` (if set) is called in the feeding thread after each sample, e.g. to wake a
    waiter on the owner's event loop."""

    def __init__(self, capacity: int = 256) -> None:
        super().__init__(capacity)
        # Bounded like the track: a track nobody reads (before a mission) keeps only the newest.
        self._pending: deque[OdometrySample] = deque(maxlen=capacity)
        self.on_feed: Callable[[], None] | None = None

    def feed(self, sample: OdometrySample) -> None:
        """Hand over a sample, from any thread."""
        self._pending.append(sample)
        on_feed = self.on_feed
        if on_feed is not None:
            on_feed()

    @property
    def fed(self) -> bool:
        """Whether samples are waiting to be filed."""
        return bool(self._pending)

    def _file(self) -> None:
        pending = self._pending
        while pending:
            super().add(pending.popleft())

    def add(self, sample: OdometrySample) -> bool:
        self._file()
        return super().add(sample)

    @property
    def latest(self) -> OdometrySample | None:
        self._file()
        return super().latest

    def at(self, time_s: float, *, extrapolate_s: float = 0.0) -> tuple[float, float, float] | None:
        self._file()
        return super().at(time_s, extrapolate_s=extrapolate_s)

    def highest_since(self, time_s: float) -> float | None:
        self._file()
        return super().highest_since(time_s)

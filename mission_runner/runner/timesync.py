"""Time that holds on real autopilots: an autopilot's boot clock mapped onto the mission clock.

Every timestamp an autopilot sends (LOCAL_POSITION_NED's and GLOBAL_POSITION_INT's
``time_boot_ms``) is on its *boot clock*. The mission clock is shared by every vehicle process (UNIX
time on time-synchronised companion computers, possibly scaled, see :class:`MissionTime`). The two
are related by SYSTEM_TIME, which carries both clocks read at the same instant on the autopilot, so
the link's latency does not enter the pair.

The relation is not a constant offset: PX4 SITL's simulated boot clock runs at 0.986x the host's
clock at speed factor 1 and ~1.93x at 2, and even a hardware crystal drifts by tens of ppm. An
offset estimated once drifts ~14 ms per second on SIH. :class:`ClockMapping` therefore fits
``unix = offset + rate * boot`` by least squares over a sliding window of pairs, continuously, and
survives a jump of the autopilot's UNIX clock (GPS time arriving, NTP stepping) by refitting.
"""

from __future__ import annotations

import bisect
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from .errors import RunnerError

#: Rates outside this band are not a clock, they are a bug or a hostile message.
MIN_RATE, MAX_RATE = 0.01, 100.0


class ClockMappingError(RunnerError):
    """The mapping cannot answer yet (no pair) or was given an impossible pair."""


@dataclass(frozen=True, slots=True)
class ClockFit:
    """``unix_s = reference_unix_s + rate * (boot_s - reference_boot_s)``; ``residual_s`` is the
    RMS misfit of the pairs in the window, ``pairs`` how many there were."""

    reference_boot_s: float
    reference_unix_s: float
    rate: float
    residual_s: float
    pairs: int

    @property
    def boot_rate(self) -> float:
        """Boot-clock seconds per UNIX second (0.986 for PX4 SIH at speed factor 1)."""
        return 1.0 / self.rate

    def unix_s(self, boot_s: float) -> float:
        return self.reference_unix_s + self.rate * (boot_s - self.reference_boot_s)

    def boot_s(self, unix_s: float) -> float:
        return self.reference_boot_s + (unix_s - self.reference_unix_s) / self.rate


#: Running sums are recomputed from the window (and re-originated) after this many updates, so
#: rounding never accumulates over a long mission.
_RESUM_EVERY = 256


class _Sums:
    """Sums of the pairs in a window, taken from ``origin`` (the first pair added since they were
    last recomputed: UNIX times of 1.7e9 s would leave no digits for milliseconds once squared)."""

    __slots__ = ("boot", "boot_boot", "boot_unix", "origin", "unix", "unix_unix", "updates")

    def __init__(self) -> None:
        self.origin: tuple[float, float] | None = None
        self.boot = self.unix = self.boot_boot = self.boot_unix = self.unix_unix = 0.0
        self.updates = 0

    @classmethod
    def of(cls, pairs: deque[tuple[float, float]]) -> _Sums:
        sums = cls()
        for boot_s, unix_s in pairs:
            sums.add(boot_s, unix_s, 1.0)
        sums.updates = 0
        return sums

    def add(self, boot_s: float, unix_s: float, sign: float) -> None:
        """Add (``sign`` 1) or remove (-1) one pair."""
        if self.origin is None:
            self.origin = (boot_s, unix_s)
        b, u = boot_s - self.origin[0], unix_s - self.origin[1]
        self.boot += sign * b
        self.unix += sign * u
        self.boot_boot += sign * b * b
        self.boot_unix += sign * b * u
        self.unix_unix += sign * u * u
        self.updates += 1


class ClockMapping:
    """Boot clock -> UNIX clock of one autopilot, from (boot_s, unix_s) pairs.

    window_s: boot seconds of pairs kept for the fit (long enough to average the millisecond
    quantisation, short enough to follow a rate that wanders; times between pairs are interpolated
    between them, not read off the line). jump_s: a pair this far from the
    current fit is an outlier; ``jumps_to_refit`` outliers in a row mean the autopilot's clock was
    stepped, and the fit restarts from them. Until the pairs span ``min_span_s`` the rate is
    taken as ``nominal_rate`` and no pair is judged an outlier (the rate may be far from 1).
    """

    def __init__(
        self,
        *,
        window_s: float = 20.0,
        jump_s: float = 0.5,
        jumps_to_refit: int = 3,
        min_span_s: float = 1.5,
        nominal_rate: float = 1.0,
    ) -> None:
        self.window_s = window_s
        self.jump_s = jump_s
        self.jumps_to_refit = jumps_to_refit
        self.min_span_s = min_span_s
        self.nominal_rate = nominal_rate
        self._pairs: deque[tuple[float, float]] = deque()
        self._sums = _Sums()
        self._outliers: list[tuple[float, float]] = []
        self._fit: ClockFit | None = None
        self._rate_measured = False  # until then a pair cannot be judged an outlier
        self.rejected = 0
        self.refits = 0

    @property
    def ready(self) -> bool:
        return self._fit is not None

    @property
    def fit(self) -> ClockFit:
        if self._fit is None:
            raise ClockMappingError("no SYSTEM_TIME pair yet: the autopilot's clock is unknown")
        return self._fit

    def add(self, boot_s: float, unix_s: float) -> bool:
        """Add a pair read at one instant; returns False if it was rejected as an outlier or a
        repeat (a pair not newer than the last one)."""
        if not (math.isfinite(boot_s) and math.isfinite(unix_s)) or unix_s <= 0 or boot_s < 0:
            self.rejected += 1
            return False
        if self._pairs and boot_s <= self._pairs[-1][0]:
            if boot_s < self._pairs[-1][0] - self.window_s:  # the autopilot rebooted
                self._restart([(boot_s, unix_s)])
                return True
            return False
        if self._rate_measured and abs(self.fit.unix_s(boot_s) - unix_s) > self.jump_s:
            self._outliers.append((boot_s, unix_s))
            if len(self._outliers) < self.jumps_to_refit:
                self.rejected += 1
                return False
            self._restart(self._outliers)
            return True
        self._outliers.clear()
        self._pairs.append((boot_s, unix_s))
        self._sums.add(boot_s, unix_s, 1.0)
        while self._pairs and self._pairs[-1][0] - self._pairs[0][0] > self.window_s:
            self._sums.add(*self._pairs.popleft(), -1.0)
        if self._sums.updates >= _RESUM_EVERY:
            self._sums = _Sums.of(self._pairs)
        self._refit()
        return True

    def _restart(self, pairs: list[tuple[float, float]]) -> None:
        self.refits += 1
        self._pairs = deque(pairs)
        self._sums = _Sums.of(self._pairs)
        self._outliers = []
        self._refit()

    def _refit(self) -> None:
        """The least-squares line through the window's pairs, from running sums (a refit at
        every SYSTEM_TIME must not cost the whole window: at 10 Hz of a clock at 2x, 200 pairs
        summed five times over, 20 times a second, in every vehicle process)."""
        sums = self._sums
        count = len(self._pairs)
        mean_boot, mean_unix = sums.boot / count, sums.unix / count
        sxx = max(sums.boot_boot - sums.boot * mean_boot, 0.0)
        sxy = sums.boot_unix - sums.boot * mean_unix
        syy = max(sums.unix_unix - sums.unix * mean_unix, 0.0)
        rate = self.nominal_rate
        self._rate_measured = self._pairs[-1][0] - self._pairs[0][0] >= self.min_span_s
        if self._rate_measured and sxx > 0.0:
            fitted = sxy / sxx
            if MIN_RATE <= fitted <= MAX_RATE:
                rate = fitted
        misfit = syy - 2.0 * rate * sxy + rate * rate * sxx
        assert sums.origin is not None  # a window is never empty here
        origin_boot, origin_unix = sums.origin
        self._fit = ClockFit(
            origin_boot + mean_boot,
            origin_unix + mean_unix,
            rate,
            math.sqrt(max(misfit, 0.0) / count),
            count,
        )

    def unix_s(self, boot_s: float) -> float:
        """UNIX time of boot time ``boot_s``: interpolated between the pairs that bracket it
        (they follow a simulated clock's jitter, which a line does not: PX4 SIH on a loaded
        machine strays 10-30 ms RMS from its linear fit), extrapolated from the nearest pair at
        the fitted rate outside them."""
        fit = self.fit
        return self._map(boot_s, 0, fit.rate)

    def boot_s(self, unix_s: float) -> float:
        """Boot time of UNIX time ``unix_s`` (the inverse of :meth:`unix_s`)."""
        fit = self.fit
        return self._map(unix_s, 1, 1.0 / fit.rate)

    def _map(self, value: float, axis: int, rate: float) -> float:
        pairs = self._pairs
        other = 1 - axis
        index = bisect.bisect_left(pairs, value, key=lambda pair: pair[axis])
        if 0 < index < len(pairs):
            before, after = pairs[index - 1], pairs[index]
            weight = (value - before[axis]) / (after[axis] - before[axis])
            return before[other] + weight * (after[other] - before[other])
        anchor = pairs[-1] if index >= len(pairs) else pairs[0]
        return anchor[other] + rate * (value - anchor[axis])


class MissionTime:
    """The mission clock of vehicle processes: UNIX time, optionally scaled to follow autopilots
    whose simulated time does not run at wall speed (PX4 SITL's speed factor).

    ``mission_s = reference_s + rate * (unix_s - reference_s)``: at ``reference_s`` both clocks
    read the same. The ground station chooses ``rate`` (the autopilots' measured boot-clock rate,
    or exactly 1 where that is within ``UNITY_BAND`` of 1, as for hardware) and sends it with the
    start command, so that every process runs the same clock; ``started`` says :meth:`set` has
    taken it (before, the clock is plain UNIX time). ``unix`` is injectable for tests.
    """

    UNITY_BAND = 0.002

    def __init__(
        self,
        rate: float = 1.0,
        reference_s: float = 0.0,
        *,
        unix: Callable[[], float] = time.time,
    ) -> None:
        self._unix = unix
        self._apply(rate, reference_s)
        self.started = False

    def set(self, rate: float, reference_s: float) -> None:
        """Run at the mission's ``rate`` around ``reference_s`` from now on (the start)."""
        self._apply(rate, reference_s)
        self.started = True

    def _apply(self, rate: float, reference_s: float) -> None:
        if not (math.isfinite(rate) and MIN_RATE <= rate <= MAX_RATE):
            raise ClockMappingError(f"mission clock rate must be in [{MIN_RATE}, {MAX_RATE}]")
        self.rate = float(rate)
        self.reference_s = float(reference_s)

    @classmethod
    def rate_for(cls, autopilot_rates: list[float]) -> float:
        """The mission clock rate for autopilots whose boot clocks run at ``autopilot_rates``
        (boot seconds per UNIX second, :attr:`ClockFit.boot_rate`): their median, or exactly 1
        when that is within ``UNITY_BAND`` of 1."""
        rates = sorted(r for r in autopilot_rates if math.isfinite(r) and r > 0)
        if not rates:
            return 1.0
        middle = len(rates) // 2
        median = rates[middle] if len(rates) % 2 else 0.5 * (rates[middle - 1] + rates[middle])
        return 1.0 if abs(median - 1.0) <= cls.UNITY_BAND else median

    def from_unix(self, unix_s: float) -> float:
        return self.reference_s + self.rate * (unix_s - self.reference_s)

    def to_unix(self, mission_s: float) -> float:
        return self.reference_s + (mission_s - self.reference_s) / self.rate

    def now_s(self) -> float:
        return self.from_unix(self._unix())

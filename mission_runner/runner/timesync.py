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
import itertools
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .errors import RunnerError

#: Rates outside this band are not a clock, they are a bug or a hostile message.
MIN_RATE, MAX_RATE = 0.01, 100.0


class ClockMappingError(RunnerError):
    """The mapping cannot answer yet (no pair) or was given an impossible pair."""


def _check_rate(rate: float) -> None:
    if not (math.isfinite(rate) and MIN_RATE <= rate <= MAX_RATE):
        raise ClockMappingError(f"mission clock rate must be in [{MIN_RATE}, {MAX_RATE}]")


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

    def recent_boot_rate(self, span_s: float = 5.0) -> float:
        """Boot-clock seconds per UNIX second over the pairs of the last ``span_s`` boot seconds
        (least squares; the whole window's :attr:`ClockFit.boot_rate` until they span
        ``min_span_s``). Follows a simulated clock that changes pace (PX4 SITL starved of CPU,
        then not) within seconds, where the window's fit takes ``window_s`` to."""
        pairs = self._pairs
        if not pairs:
            return self.fit.boot_rate
        newest_boot_s = pairs[-1][0]
        recent = [
            p
            for p in itertools.takewhile(lambda p: p[0] >= newest_boot_s - span_s, reversed(pairs))
        ]
        if len(recent) < 3 or newest_boot_s - recent[-1][0] < self.min_span_s:
            return self.fit.boot_rate
        boot0, unix0 = recent[-1]
        mean_boot = sum(b - boot0 for b, _ in recent) / len(recent)
        mean_unix = sum(u - unix0 for _, u in recent) / len(recent)
        sxx = sum((b - boot0 - mean_boot) ** 2 for b, _ in recent)
        sxy = sum((b - boot0 - mean_boot) * (u - unix0 - mean_unix) for b, u in recent)
        if sxx <= 0.0 or not MIN_RATE <= sxy / sxx <= MAX_RATE:
            return self.fit.boot_rate
        return sxx / sxy

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


class FedClockMapping(ClockMapping):
    """A :class:`ClockMapping` fed from another thread (MAVSDK's, as SYSTEM_TIME arrives):
    :meth:`feed` only queues the pair; the pairs queued are added, in order, on the thread that
    reads the mapping, when it next reads it. Nobody waits for a pair the mapping is not read
    for, and the event loop is not woken for each one (at 10 Hz, a third of a vehicle process's
    event-loop turns in flight went to it)."""

    def __init__(self, **settings: Any) -> None:
        super().__init__(**settings)
        self._fed: deque[tuple[float, float]] = deque()  # appended and popped thread-safely
        self._taking = False

    def feed(self, boot_s: float, unix_s: float) -> None:
        """Queue a pair read at one instant (from any thread); :meth:`add` judges it later."""
        self._fed.append((boot_s, unix_s))

    @property
    def fitted(self) -> bool:
        """Whether the mapping had a fit when last read (for the feeding thread: it takes
        nothing queued)."""
        return self._fit is not None

    def _take_fed(self) -> None:
        if self._taking:  # add() reads the fit: the pairs go in one by one, in order
            return
        self._taking, fed = True, self._fed
        try:
            while fed:
                super().add(*fed.popleft())
        finally:
            self._taking = False

    def add(self, boot_s: float, unix_s: float) -> bool:
        self._take_fed()
        return super().add(boot_s, unix_s)

    @property
    def ready(self) -> bool:
        self._take_fed()
        return self._fit is not None

    @property
    def fit(self) -> ClockFit:
        self._take_fed()
        return super().fit

    def recent_boot_rate(self, span_s: float = 5.0) -> float:
        self._take_fed()
        return super().recent_boot_rate(span_s)


class MissionTime:
    """The mission clock of vehicle processes: UNIX time, optionally scaled to follow autopilots
    whose simulated time does not run at wall speed (PX4 SITL's speed factor).

    ``mission_s = reference_s + rate * (unix_s - reference_s)``: at ``reference_s`` both clocks
    read the same. The ground station chooses ``rate`` (the autopilots' measured boot-clock rate,
    or exactly 1 where that is within ``UNITY_BAND`` of 1, as for hardware) and sends it with the
    start command, so that every process runs the same clock; ``started`` says :meth:`set` has
    taken it (before, the clock is plain UNIX time). ``unix`` is injectable for tests.

    The rate may change during the mission (:meth:`change`, the ground's ``clock`` command when
    simulated autopilots speed up or slow down: PX4 SITL starved of CPU runs its clock at 0.5-0.7x
    for a while): the clock then runs on at the new rate from a given UNIX instant, continuous
    there, so every process that takes the same change keeps the same clock.
    """

    UNITY_BAND = 0.002
    #: Rate changes remembered, so that a mission time of the last minutes still maps back.
    KEPT_SEGMENTS = 16

    def __init__(
        self,
        rate: float = 1.0,
        reference_s: float = 0.0,
        *,
        unix: Callable[[], float] = time.time,
    ) -> None:
        self._unix = unix
        #: (unix_s, mission_s, rate) from which the clock runs at ``rate``, oldest first.
        self._segments: list[tuple[float, float, float]] = []
        self._apply(rate, reference_s)
        self.started = False

    def set(self, rate: float, reference_s: float) -> None:
        """Run at the mission's ``rate`` around ``reference_s`` from now on (the start)."""
        self._apply(rate, reference_s)
        self.started = True

    def _apply(self, rate: float, reference_s: float) -> None:
        _check_rate(rate)
        self._segments = [(float(reference_s), float(reference_s), float(rate))]

    def change(self, rate: float, at_unix_s: float, mission_s: float) -> None:
        """From UNIX time ``at_unix_s`` on, run at ``rate``, reading ``mission_s`` then (the
        ground's clock there: one that missed an earlier change takes this one's word for it).
        A change at or before an earlier one's instant replaces it."""
        _check_rate(rate)
        if not (math.isfinite(at_unix_s) and math.isfinite(mission_s)):
            raise ClockMappingError("a clock change needs a finite instant and mission time")
        kept = [s for s in self._segments if s[0] < at_unix_s]
        kept.append((float(at_unix_s), float(mission_s), float(rate)))
        self._segments = kept[-self.KEPT_SEGMENTS :]

    @property
    def rate(self) -> float:
        """Mission seconds per UNIX second now."""
        return self._segment(self._unix(), 0)[2]

    @property
    def latest_rate(self) -> float:
        """The rate of the newest change, even if it is still to come."""
        return self._segments[-1][2]

    @property
    def reference_s(self) -> float:
        """UNIX time (= mission time) of the start's reference."""
        return self._segments[0][0]

    def _segment(self, value: float, axis: int) -> tuple[float, float, float]:
        for segment in reversed(self._segments):
            if segment[axis] <= value:
                return segment
        return self._segments[0]

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
        start_unix_s, start_mission_s, rate = self._segment(unix_s, 0)
        return start_mission_s + rate * (unix_s - start_unix_s)

    def to_unix(self, mission_s: float) -> float:
        start_unix_s, start_mission_s, rate = self._segment(mission_s, 1)
        return start_unix_s + (mission_s - start_mission_s) / rate

    def now_s(self) -> float:
        return self.from_unix(self._unix())

    def unix_now_s(self) -> float:
        """The UNIX clock this mission clock runs on, now."""
        return self._unix()


@dataclass(frozen=True, slots=True)
class ClockChange:
    """Run the mission clock at ``rate`` from UNIX time ``at_unix_s``, reading ``mission_s``."""

    rate: float
    at_unix_s: float
    mission_s: float


class ClockFollower:
    """The ground's mission clock, following the autopilots' clocks through the mission.

    At the start the ground sets the rate to the autopilots' (:meth:`MissionTime.rate_for`). A
    simulated autopilot does not keep its pace: PX4 SITL sharing two cores with the mission ran
    its clock at 0.63x while everything started, 1x a minute later (and the other way round when
    the machine got busy mid-flight). Vehicles then had to fly 1.4-1.6x faster or slower than the
    law asked on their autopilot's clock, which velocity setpoints cannot do (bounded at
    :data:`~mission_runner.runner.links.MAX_VELOCITY_SCALE`), and the formation ended metres off.
    So the vehicles report their autopilots' recent rates (statuses, every second) and once their
    median has been more than ``band`` off the mission clock's rate for ``hold_s``, the ground
    changes the clock (:meth:`due`) ``lead_s`` ahead, for every process alike. Rates are only
    those heard within ``fresh_s``; hardware (rates within ``UNITY_BAND`` of 1) never changes.
    """

    def __init__(
        self,
        time: MissionTime,
        *,
        band: float = 0.03,
        hold_s: float = 2.0,
        lead_s: float = 0.5,
        fresh_s: float = 5.0,
    ) -> None:
        self.time = time
        self.band, self.hold_s, self.lead_s, self.fresh_s = band, hold_s, lead_s, fresh_s
        self._rates: dict[int, tuple[float, float]] = {}  # vehicle -> (boot rate, heard at)
        self._off_since_s: float | None = None
        self.changes = 0

    def heard(self, vehicle_id: int, boot_rate: float | None, unix_s: float) -> None:
        """Vehicle ``vehicle_id`` reported its autopilot's recent boot-clock rate."""
        if boot_rate is not None and math.isfinite(boot_rate) and MIN_RATE <= boot_rate <= MAX_RATE:
            self._rates[vehicle_id] = (boot_rate, unix_s)

    def due(self, unix_s: float) -> ClockChange | None:
        """The change to send now, if one is due (it is then taken by :attr:`time`)."""
        rates = [r for r, heard_s in self._rates.values() if unix_s - heard_s <= self.fresh_s]
        if not rates:
            return None
        wanted = MissionTime.rate_for(rates)
        if abs(wanted / self.time.latest_rate - 1.0) <= self.band:
            self._off_since_s = None
            return None
        if self._off_since_s is None:
            self._off_since_s = unix_s
        if unix_s - self._off_since_s < self.hold_s:
            return None
        at_unix_s = unix_s + self.lead_s
        change = ClockChange(wanted, at_unix_s, self.time.from_unix(at_unix_s))
        self.time.change(change.rate, change.at_unix_s, change.mission_s)
        self._off_since_s = None
        self.changes += 1
        return change

"""Detects silence on the bus, so a controller holds instead of flying on stale data.

A vehicle controller feeds a ``SilenceWatchdog`` with every message it receives (keyed by
sender) and asks it once per step whether data is fresh. When nothing has arrived for more
than ``timeout_s`` the controller stops following the algorithm and holds position; when
one neighbour goes silent it can drop that neighbour (the oscillators then re-balance to
the live vehicles). The watchdog only reads time; it never sleeps.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Hashable


class SilenceWatchdog:
    """Tracks the last arrival time overall and per source, on an injected clock.

    ``now`` returns seconds (monotonic); a test passes ``ManualClock().now``. Before the
    first arrival, silence is measured from construction (or ``reset``), so a bus that
    never delivers anything is reported silent after ``timeout_s`` too.
    """

    def __init__(self, timeout_s: float, *, now: Callable[[], float] = time.monotonic) -> None:
        if not math.isfinite(timeout_s) or timeout_s <= 0.0:
            raise ValueError(f"timeout_s must be finite and > 0, got {timeout_s!r}")
        self.timeout_s = timeout_s
        self._now = now
        self._started_s = now()
        self._last_arrival_s: float | None = None
        self._last_by_source: dict[Hashable, float] = {}

    def reset(self) -> None:
        """Forget every arrival; silence is measured from now."""
        self._started_s = self._now()
        self._last_arrival_s = None
        self._last_by_source.clear()

    def feed(self, source: Hashable | None = None, *, at_s: float | None = None) -> None:
        """Record an arrival (now, or at ``at_s``) from ``source`` (e.g. a vehicle id)."""
        arrival_s = self._now() if at_s is None else at_s
        if self._last_arrival_s is None or arrival_s > self._last_arrival_s:
            self._last_arrival_s = arrival_s
        if source is not None:
            previous_s = self._last_by_source.get(source)
            if previous_s is None or arrival_s > previous_s:
                self._last_by_source[source] = arrival_s

    def forget(self, source: Hashable) -> None:
        """Stop tracking ``source`` (e.g. a vehicle declared lost)."""
        self._last_by_source.pop(source, None)

    @property
    def last_arrival_s(self) -> float | None:
        """Time of the latest arrival from any source, None if nothing arrived yet."""
        return self._last_arrival_s

    def silence_s(self, source: Hashable | None = None) -> float:
        """Seconds since the latest arrival (from ``source``, or from anyone if None).

        A source never heard from counts from construction or the last ``reset``.
        """
        last_s = self._last_arrival_s if source is None else self._last_by_source.get(source)
        return self._now() - (self._started_s if last_s is None else last_s)

    def is_silent(self, source: Hashable | None = None) -> bool:
        """Whether nothing arrived (from ``source``, or from anyone) for over ``timeout_s``."""
        return self.silence_s(source) > self.timeout_s

    def silent_sources(self) -> list[Hashable]:
        """Sources heard from before that have been silent for over ``timeout_s``."""
        now_s = self._now()
        return [
            source
            for source, last_s in self._last_by_source.items()
            if now_s - last_s > self.timeout_s
        ]

    def fresh_sources(self) -> list[Hashable]:
        """Sources heard from within the last ``timeout_s``."""
        now_s = self._now()
        return [
            source
            for source, last_s in self._last_by_source.items()
            if now_s - last_s <= self.timeout_s
        ]

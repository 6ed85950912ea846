"""Physically impossible ranges, rejected where they enter a controller, before the estimator.

A range the radio cannot have measured (negative, NaN, beyond its reach) or one that changed
more since the last accepted range of the same pair than the two could have moved apart or
together (relative speed bound times the time between them, plus the noise margin) is dropped,
counted by reason and logged (rate-limited). The estimator then treats it as a missing range: its
next update spans the gap (:mod:`mission_runner.enclosing.rlse`).

A neighbour's step message that says it flies faster than any vehicle of the mission may
(``StepMessage.command_*_m_s`` beyond the speed limit) loses that command, counted the same way:
the separation guard then counts the neighbour's motion as unknown rather than believing it.

This is a check of physics at the message boundary, not outlier gating of the estimate (that
belongs to the estimator). The band widens with time since the last accepted range, so a pair
whose true range really did change while ranges were rejected is accepted again once the time
allows that change; a source that keeps lying consistently is beyond any plausibility check,
which is why the bus authenticates who sent a range (:mod:`mission_runner.bus.auth`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

from ..bus import StepMessage
from ..bus.auth import RateLimitedWarnings
from ..config import Scenario

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RangeLimits:
    """What a range can physically be.

    max_range_m: the radio's reach. max_relative_speed_m_s: how fast two members (or a member
    and the target) can approach or separate. margin_m: what noise may add to a change."""

    max_range_m: float
    max_relative_speed_m_s: float
    margin_m: float

    def __post_init__(self) -> None:
        for name in ("max_range_m", "max_relative_speed_m_s", "margin_m"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")


#: A UWB radio's line-of-sight reach, when the scenario gives none [m].
DEFAULT_RADIO_REACH_M = 300.0


def range_limits(scenario: Scenario) -> RangeLimits:
    """What a range can be in ``scenario`` (``flight.range_check``, defaults from the sensors
    and the vehicles' speed limits)."""
    check = scenario.flight.range_check
    sensors = scenario.sensors
    reach_m = check.max_range_m or sensors.range_max_m or DEFAULT_RADIO_REACH_M
    speed_m_s = check.max_relative_speed_m_s or 2.0 * max(
        vehicle.speed_limit_m_s for vehicle in scenario.vehicles
    )
    margin_m = check.margin_m
    if margin_m is None:
        margin_m = 0.2 + 6.0 * math.sqrt(2.0) * sensors.range_noise_std_m
    return RangeLimits(reach_m, speed_m_s, margin_m)


@dataclass
class RangeGate:
    """Accepts or rejects one vehicle's ranges, pair by pair (peer 0: the target).

    ``rejected`` counts by reason: ``invalid`` (negative or not finite), ``beyond_reach``,
    ``jump``."""

    limits: RangeLimits
    vehicle_id: int = 0
    rejected: dict[str, int] = field(
        default_factory=lambda: {"invalid": 0, "beyond_reach": 0, "jump": 0}
    )
    _last: dict[int, tuple[float, float]] = field(default_factory=dict)
    _warnings: RateLimitedWarnings = field(
        default_factory=lambda: RateLimitedWarnings(logger), repr=False
    )

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def accept(self, peer_id: int, range_m: float, time_s: float) -> bool:
        """Whether the range ``range_m`` to ``peer_id`` measured at ``time_s`` (seconds, the
        sender's mission clock) is possible; a possible one becomes the pair's reference."""
        limits = self.limits
        if not math.isfinite(range_m) or range_m < 0 or not math.isfinite(time_s):
            return self._reject("invalid", peer_id, range_m, "negative or not a number")
        if range_m > limits.max_range_m:
            return self._reject(
                "beyond_reach", peer_id, range_m, f"beyond the radio's {limits.max_range_m:g} m"
            )
        last = self._last.get(peer_id)
        if last is not None:
            last_range_m, last_time_s = last
            allowed_m = limits.max_relative_speed_m_s * abs(time_s - last_time_s) + limits.margin_m
            if abs(range_m - last_range_m) > allowed_m:
                return self._reject(
                    "jump",
                    peer_id,
                    range_m,
                    f"{abs(range_m - last_range_m):.2f} m from {last_range_m:.2f} m in "
                    f"{abs(time_s - last_time_s):.3f} s (at most {allowed_m:.2f} m)",
                )
        self._last[peer_id] = (range_m, time_s)
        return True

    def _reject(self, reason: str, peer_id: int, range_m: float, why: str) -> bool:
        self.rejected[reason] += 1
        self._warnings.warn(
            reason,
            "vehicle %s: range to %s of %r m rejected before the estimator: %s; %d rejected so far",
            self.vehicle_id,
            "the target" if peer_id == 0 else f"vehicle {peer_id}",
            range_m,
            why,
            self.rejected_total,
        )
        return False


#: A command may exceed the speed limit by this much [m/s] (the sender's clamp rounds).
COMMAND_TOLERANCE_M_S = 1e-6


@dataclass
class CommandGate:
    """Drops the command of a step message that no vehicle of the mission may fly: faster than
    ``max_speed_m_s`` (the fastest vehicle's speed limit). Non-finite commands never get this far
    (the message does not decode). ``rejected`` counts ``command_speed``."""

    max_speed_m_s: float
    vehicle_id: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: {"command_speed": 0})
    _warnings: RateLimitedWarnings = field(
        default_factory=lambda: RateLimitedWarnings(logger), repr=False
    )

    def checked(self, message: StepMessage) -> StepMessage:
        """``message``, without its command if the command is impossible."""
        command = message.command_m_s
        if command is None or math.hypot(*command) <= self.max_speed_m_s + COMMAND_TOLERANCE_M_S:
            return message
        self.rejected["command_speed"] += 1
        self._warnings.warn(
            "command_speed",
            "vehicle %s: vehicle %s's step %d command of %.3g m/s dropped: faster than the "
            "%.3g m/s any vehicle may fly; %d dropped so far",
            self.vehicle_id,
            message.vehicle_id,
            message.step,
            math.hypot(*command),
            self.max_speed_m_s,
            self.rejected["command_speed"],
        )
        return dataclasses.replace(message, command_north_m_s=None, command_east_m_s=None)

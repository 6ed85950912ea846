"""Messages the vehicles, sensors and ground station exchange over the bus.

Each message is a frozen dataclass that encodes to compact UTF-8 JSON (``to_payload``) and
decodes with full validation (``from_payload``): every field must have its declared type,
every number must be finite and in range, and unknown or missing keys are rejected. A bad
payload raises ``MessageDecodeError``; subscriber loops count and skip it.

Units and frames are in the field names. "north"/"east" are axes of a frame that every
vehicle shares in orientation but not in origin (each vehicle's own odometry frame), so
only differences of odometry between two messages of the same sender are meaningful.
``time_s`` is the sender's clock in seconds; clocks are not assumed synchronised, and the
step index ``step`` is what aligns messages of the same instant kT across vehicles.

Optional fields are left out of the payload when they are None.
"""

from __future__ import annotations

import enum
import json
import math
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from types import NoneType, UnionType
from typing import Any, ClassVar, Self

from mission_runner.bus.errors import MessageDecodeError, MessageValueError
from mission_runner.bus.topics import TARGET_PEER_ID, TopicKind


class ControlCommand(enum.StrEnum):
    """Commands of the mission control topic.

    ``prepare``/``start`` run the handshake; during a mission ``hold`` (hover in place, still in
    OFFBOARD) and ``resume`` pause and continue the law; ``land``, ``return`` (to launch) and
    ``stop`` (leave OFFBOARD, the autopilot holds) end it. ``clock`` changes the mission
    clock's rate during a mission (see :class:`MissionControl`).
    """

    PREPARE = "prepare"
    CLOCK = "clock"
    START = "start"
    STOP = "stop"
    HOLD = "hold"
    RESUME = "resume"
    LAND = "land"
    RETURN = "return"


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} is not allowed")


class _Invalid(ValueError):
    """A value that does not fit its annotation: ``problem`` ("must be ..."), at ``path``
    (the indices into a field's nested arrays, e.g. ``[1][0]``)."""

    def __init__(self, problem: str, path: str = "") -> None:
        super().__init__(problem)
        self.problem, self.path = problem, path


_Checker = Callable[[Any], Any]


def _as_float(value: Any) -> float:
    if type(value) is float:  # what JSON numbers with a fraction decode to: the usual case
        if math.isfinite(value):
            return value
        raise _Invalid(f"must be finite, got {value!r}")
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _Invalid(f"must be a number, got {type(value).__name__}")
    try:
        number = float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise _Invalid("must be finite, got an integer too large for a float") from None
    if not math.isfinite(number):
        raise _Invalid(f"must be finite, got {value!r}")
    return number


def _as_int(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):  # bool is an int subclass
        raise _Invalid(f"must be an integer, got {type(value).__name__}")
    return value


def _as_bool(value: Any) -> bool:
    if not isinstance(value, bool):
        raise _Invalid(f"must be true or false, got {type(value).__name__}")
    return value


def _as_str(value: Any) -> str:
    if not isinstance(value, str):
        raise _Invalid(f"must be a string, got {type(value).__name__}")
    return value


def _enum_checker(kind: type[enum.Enum]) -> _Checker:
    allowed = ", ".join(repr(member.value) for member in kind)

    def check(value: Any) -> Any:
        try:
            return kind(value)
        except ValueError:
            raise _Invalid(f"must be one of {allowed}, got {value!r}") from None

    return check


def _optional_checker(check: _Checker) -> _Checker:
    def optional(value: Any) -> Any:
        return None if value is None else check(value)

    return optional


def _tuple_checker(items: tuple[Any, ...]) -> _Checker:
    """``tuple[X, ...]`` or ``tuple[X, Y]`` from a JSON array."""
    variadic = len(items) == 2 and items[1] is Ellipsis
    checks = [_checker(item) for item in (items[:1] if variadic else items)]

    def check(value: Any) -> tuple[Any, ...]:
        if not isinstance(value, list | tuple):
            raise _Invalid(f"must be an array, got {type(value).__name__}")
        if not variadic and len(value) != len(checks):
            raise _Invalid(f"must have {len(checks)} entries, got {len(value)}")
        each = checks * len(value) if variadic else checks
        out = []
        for index, (entry, item) in enumerate(zip(value, each, strict=True)):
            try:
                out.append(item(entry))
            except _Invalid as bad:
                raise _Invalid(bad.problem, f"[{index}]{bad.path}") from None
        return tuple(out)

    return check


_SCALARS: dict[Any, _Checker] = {float: _as_float, int: _as_int, bool: _as_bool, str: _as_str}


def _checker(annotation: Any) -> _Checker:
    """A function that returns a value checked (and normalised) against ``annotation``, built
    once per field (decoding a message runs it for every field of every message received)."""
    if isinstance(annotation, UnionType):
        options = typing.get_args(annotation)
        (inner,) = (option for option in options if option is not NoneType)
        return _optional_checker(_checker(inner))
    if typing.get_origin(annotation) is tuple:
        return _tuple_checker(typing.get_args(annotation))
    if annotation in _SCALARS:
        return _SCALARS[annotation]
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return _enum_checker(annotation)
    raise TypeError(f"unsupported field annotation {annotation!r}")


def _require(condition: bool, problem: str) -> None:
    if not condition:
        raise ValueError(problem)


class Message:
    """Base of the bus messages: typed construction, JSON encoding and validated decoding."""

    __slots__ = ()

    _hints: ClassVar[dict[str, Any]]
    _optional: ClassVar[frozenset[str]]
    _checkers: ClassVar[tuple[tuple[str, _Checker], ...]]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        cls._hints = {}

    def __post_init__(self) -> None:
        try:
            self._normalise()
            self._check()
        except ValueError as exc:
            raise MessageValueError(type(self).__name__, str(exc)) from None

    @classmethod
    def _field_types(cls) -> dict[str, Any]:
        if not cls._hints:
            hints = typing.get_type_hints(cls)
            field_hints = {field.name: hints[field.name] for field in fields(cls)}  # type: ignore[arg-type]
            cls._optional = frozenset(
                name
                for name, hint in field_hints.items()
                if isinstance(hint, UnionType) and NoneType in typing.get_args(hint)
            )
            cls._checkers = tuple((name, _checker(hint)) for name, hint in field_hints.items())
            cls._hints = field_hints
        return cls._hints

    def _normalise(self) -> None:
        self._field_types()
        for name, check in self._checkers:
            try:
                value = check(getattr(self, name))
            except _Invalid as bad:
                raise ValueError(f"{name}{bad.path} {bad.problem}") from None
            # Frozen dataclass: normalising an int to float must bypass __setattr__.
            object.__setattr__(self, name, value)

    def _check(self) -> None:
        """Constraints between fields and value ranges; raise ValueError. Override."""

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of this message (None fields left out, enums as their value)."""
        out: dict[str, Any] = {}
        for name in self._field_types():
            value = getattr(self, name)
            if value is None:
                continue
            out[name] = value.value if isinstance(value, enum.Enum) else value
        return out

    def to_payload(self) -> bytes:
        """Compact UTF-8 JSON encoding of this message."""
        return json.dumps(
            self.to_dict(), separators=(",", ":"), allow_nan=False, ensure_ascii=False
        ).encode("utf-8")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Self:
        """Build a message from a decoded JSON object; raise MessageDecodeError if invalid."""
        name = cls.__name__
        if not isinstance(data, Mapping):
            raise MessageDecodeError(name, f"expected a JSON object, got {type(data).__name__}")
        field_types = cls._field_types()
        unknown = sorted(set(data) - set(field_types))
        if unknown:
            raise MessageDecodeError(name, f"unknown field(s) {', '.join(map(str, unknown))}")
        missing = sorted(set(field_types) - set(data) - cls._optional)
        if missing:
            raise MessageDecodeError(name, f"missing field(s) {', '.join(missing)}")
        try:
            return cls(**data)
        except MessageValueError as exc:
            raise MessageDecodeError(name, exc.problem) from None

    @classmethod
    def from_payload(cls, payload: bytes | bytearray | memoryview) -> Self:
        """Decode a payload made by ``to_payload``; raise MessageDecodeError if invalid."""
        name = cls.__name__
        try:
            text = bytes(payload).decode("utf-8")
            data = json.loads(text, parse_constant=_reject_constant)
        except UnicodeDecodeError as exc:
            raise MessageDecodeError(name, f"payload is not UTF-8 ({exc.reason})") from None
        except (ValueError, RecursionError, TypeError) as exc:
            # ValueError covers JSONDecodeError, rejected NaN/Infinity and over-long integers.
            raise MessageDecodeError(name, f"payload is not valid JSON ({exc})") from None
        return cls.from_dict(data)


#: Shared ranges travel rounded to this many decimals of a metre (0.1 mm: far below any radio's
#: noise, and about 7 bytes a range instead of a float's 18).
SHARED_RANGE_DECIMALS = 4
#: At most this many shared ranges in one step message (the scenario's largest swarm).
MAX_SHARED_RANGES = 4096


def shared_range(range_m: float) -> float:
    """``range_m`` as a step message carries it (rounded to SHARED_RANGE_DECIMALS)."""
    return round(range_m, SHARED_RANGE_DECIMALS)


@dataclass(frozen=True, slots=True)
class StepMessage(Message):
    """What vehicle ``vehicle_id`` broadcasts at step ``step`` (time kT) of the algorithm.

    ``odometry_*_m`` is the vehicle's cumulative displacement since switch-on in its own
    north-east frame: a neighbour gets v_j(k) by differencing two of these, so a lost or
    late message never corrupts its estimate, it only delays it. ``phase_rad`` is the
    oscillator phase theta_i(k).

    The ``target_*`` fields relay the target (Assumption 2: vehicles that sense the target
    broadcast it). ``target_velocity_*`` is the velocity of the freshest observation this
    vehicle knows of (its own, or one relayed to it), made at step ``target_observed_step``
    (``step`` itself when left out, as older senders do): while nobody sees the target, every
    vehicle relays the same freshest observation, so all predict it alike. ``target_odometry_*``
    is the target's cumulative displacement in this vehicle's frame, set only when this vehicle
    observed the target itself at this step (and then with the velocity). ``odometry_down_m``
    is the sender's height (down, from its odometry origin on
    the ground) at t_k, with which a receiver takes the height difference out of a 3-D range.

    ``ranges_m`` (``algorithm.shared_ranges``) are the sender's own step-k ranges to its
    neighbours as ``(peer id, range [m])`` pairs, 3-D as measured, rounded by
    :func:`shared_range` (the sender uses the rounded values itself, so both ends of a pair
    average the same two numbers).

    ``command_*_m_s`` is the horizontal velocity setpoint the sender is flying as it sends (the
    one it set at step k - 1; none before its first): the separation guard's neighbours take it
    as the sender's motion in force. A receiver drops one faster than the sender may fly
    (:mod:`mission_runner.runner.plausibility`).
    """

    vehicle_id: int
    step: int
    time_s: float
    phase_rad: float
    odometry_north_m: float
    odometry_east_m: float
    target_odometry_north_m: float | None = None
    target_odometry_east_m: float | None = None
    target_velocity_north_m_s: float | None = None
    target_velocity_east_m_s: float | None = None
    odometry_down_m: float | None = None
    ranges_m: tuple[tuple[int, float], ...] | None = None
    target_observed_step: int | None = None
    command_north_m_s: float | None = None
    command_east_m_s: float | None = None

    @property
    def has_target(self) -> bool:
        """Whether this vehicle observed the target itself at this step."""
        return self.target_odometry_north_m is not None

    @property
    def relayed_target(self) -> tuple[int, tuple[float, float]] | None:
        """The freshest target observation relayed: ``(observed_step, (north, east) m/s)``."""
        north, east = self.target_velocity_north_m_s, self.target_velocity_east_m_s
        if north is None or east is None:
            return None
        observed = self.step if self.target_observed_step is None else self.target_observed_step
        return observed, (north, east)

    @property
    def command_m_s(self) -> tuple[float, float] | None:
        """The sender's setpoint in force ``(north, east)`` [m/s], if it sent one."""
        north, east = self.command_north_m_s, self.command_east_m_s
        return None if north is None or east is None else (north, east)

    def _check(self) -> None:
        _require(self.vehicle_id >= 1, f"vehicle_id must be >= 1, got {self.vehicle_id}")
        _require(self.step >= 0, f"step must be >= 0, got {self.step}")
        command = (self.command_north_m_s, self.command_east_m_s)
        _require(command.count(None) in (0, 2), "command_*_m_s must be set as a pair")
        velocity = (self.target_velocity_north_m_s, self.target_velocity_east_m_s)
        odometry = (self.target_odometry_north_m, self.target_odometry_east_m)
        _require(
            velocity.count(None) in (0, 2) and odometry.count(None) in (0, 2),
            "target_velocity_* and target_odometry_* must each be set as a pair",
        )
        relayed = velocity.count(None) == 0
        _require(
            relayed or (odometry.count(None) == 2 and self.target_observed_step is None),
            "target_odometry_* and target_observed_step need target_velocity_*",
        )
        observed = self.target_observed_step
        _require(
            observed is None or 0 <= observed <= self.step,
            f"target_observed_step must be in [0, step], got {observed}",
        )
        if self.ranges_m is not None:
            peers = [peer for peer, _ in self.ranges_m]
            _require(
                len(peers) <= MAX_SHARED_RANGES,
                f"ranges_m has {len(peers)} entries, at most {MAX_SHARED_RANGES}",
            )
            _require(len(set(peers)) == len(peers), "ranges_m names a peer twice")
            for peer, range_m in self.ranges_m:
                _require(
                    peer >= 1 and peer != self.vehicle_id,
                    f"ranges_m: peer must be another vehicle's id (>= 1), got {peer}",
                )
                _require(range_m >= 0.0, f"ranges_m: range to {peer} must be >= 0, got {range_m}")


#: At most this many ranges in one range set: far more peers than any swarm's radio ranges in one
#: round, and a bound on what a hostile set can make a receiver check.
MAX_RANGE_SET_ENTRIES = 1024


@dataclass(frozen=True, slots=True)
class RangeSet(Message):
    """The ranges vehicle ``vehicle_id``'s UWB radio measured in one ranging round at ``time_s``:
    ``ranges_m`` as ``(peer id, range [m])`` pairs (peer 0 = the target), 3-D as measured.

    ``step`` is the algorithm step whose boundary the round was sampled at, when the driver knows
    it; otherwise the consumer aligns by ``time_s``. A set is the whole round: a peer missing from
    it was not ranged (dropped, out of range, not in this step's airtime), and an empty set says
    that nothing was, so a receiver waits for no more ranges of that instant.
    """

    vehicle_id: int
    time_s: float
    ranges_m: tuple[tuple[int, float], ...] = ()
    step: int | None = None

    def _check(self) -> None:
        _require(self.vehicle_id >= 1, f"vehicle_id must be >= 1, got {self.vehicle_id}")
        _require(self.step is None or self.step >= 0, f"step must be >= 0, got {self.step}")
        _require(
            len(self.ranges_m) <= MAX_RANGE_SET_ENTRIES,
            f"ranges_m has {len(self.ranges_m)} entries, at most {MAX_RANGE_SET_ENTRIES}",
        )
        peers = {peer for peer, _ in self.ranges_m}
        _require(len(peers) == len(self.ranges_m), "ranges_m names a peer twice")
        for peer, range_m in self.ranges_m:
            _require(
                peer >= TARGET_PEER_ID and peer != self.vehicle_id,
                f"ranges_m: peer must be >= {TARGET_PEER_ID} (0 = target) and not the vehicle "
                f"itself ({self.vehicle_id}), got {peer}",
            )
            _require(range_m >= 0.0, f"ranges_m: range to {peer} must be >= 0, got {range_m}")


@dataclass(frozen=True, slots=True)
class TargetObservation(Message):
    """What a target tracker (radar, vision) on vehicle ``vehicle_id`` measured at ``time_s``.

    ``range_m`` is the vehicle-to-target distance; the velocity is the target's, in the
    shared north-east orientation. A tracker that looked and did not see the target (out of
    range, occluded, a miss) says so with all three left out (:attr:`seen` False): the
    controller then knows the observation of this instant is not coming and does not wait.
    """

    vehicle_id: int
    time_s: float
    range_m: float | None = None
    velocity_north_m_s: float | None = None
    velocity_east_m_s: float | None = None

    @property
    def seen(self) -> bool:
        """Whether the tracker saw the target (range and velocity are set)."""
        return self.range_m is not None

    @classmethod
    def not_seen(cls, vehicle_id: int, time_s: float) -> Self:
        """The tracker of ``vehicle_id`` looked at ``time_s`` and did not see the target."""
        return cls(vehicle_id, time_s)

    def _check(self) -> None:
        _require(self.vehicle_id >= 1, f"vehicle_id must be >= 1, got {self.vehicle_id}")
        values = (self.range_m, self.velocity_north_m_s, self.velocity_east_m_s)
        _require(
            values.count(None) in (0, 3),
            "range_m and velocity_* must be all set (target seen) or all left out (not seen)",
        )
        _require(
            self.range_m is None or self.range_m >= 0.0, f"range_m must be >= 0, got {self.range_m}"
        )


#: The longest note a command carries: with the rest of the message it stays far below the
#: receivers' max_message_bytes (a larger command would be sent, then dropped unread by every
#: vehicle as oversized).
MAX_REASON_CHARS = 1000


@dataclass(frozen=True, slots=True)
class MissionControl(Message):
    """A mission command from the ground station (see :class:`ControlCommand`).

    ``mission_id`` names one mission (a ground station run): vehicles answer ``prepare`` with
    statuses carrying it, act only on commands carrying it, and a retained message of an earlier
    mission is recognised as such. ``start`` carries k = 0 as ``time_s`` on the mission clock,
    which is ``mission_s = clock_reference_s + clock_rate * (unix_s - clock_reference_s)``
    (``clock_rate`` follows autopilots whose simulated time runs faster or slower than wall time).
    ``clock`` changes it during the mission: from UNIX time ``clock_reference_s`` on, the clock
    runs at ``clock_rate``, reading ``time_s`` then.
    """

    command: ControlCommand
    time_s: float
    reason: str | None = None
    mission_id: str | None = None
    clock_rate: float | None = None
    clock_reference_s: float | None = None
    vehicle_id: int | None = None  # hold/resume/land/return/stop for one vehicle; None: all

    def _check(self) -> None:
        _require(
            self.vehicle_id is None or self.vehicle_id >= 1,
            f"vehicle_id must be >= 1, got {self.vehicle_id}",
        )
        _require(
            self.mission_id is None or 0 < len(self.mission_id) <= 64,
            "mission_id must have 1 to 64 characters",
        )
        _require(
            self.clock_rate is None or 0.01 <= self.clock_rate <= 100.0,
            f"clock_rate must be in [0.01, 100], got {self.clock_rate}",
        )
        _require(
            self.reason is None or len(self.reason) <= MAX_REASON_CHARS,
            f"reason must have at most {MAX_REASON_CHARS} characters",
        )


@dataclass(frozen=True, slots=True)
class VehicleStatus(Message):
    """A vehicle's progress report (retained, and its last will), for progress views.

    ``state`` is the vehicle's state name (a :class:`mission_runner.records.ControllerState`,
    e.g. ``"following"``, ``"target_lost"``, ``"holding"``, ``"lost"``); ``tracking_ok``
    whether it currently follows the target with the algorithm on fresh data (not while the
    target is lost).
    ``mission_id`` is the mission it reports for (see :class:`MissionControl`);
    ``clock_rate`` its autopilot's boot-clock seconds per UNIX second, as measured;
    ``stale_steps`` (in its final report) how many steps it held or skipped for want of fresh
    data (:data:`mission_runner.records.STALE_STATES`).
    """

    vehicle_id: int
    time_s: float
    state: str
    step: int
    tracking_ok: bool
    detail: str = ""
    mission_id: str | None = None
    clock_rate: float | None = None
    stale_steps: int | None = None

    def _check(self) -> None:
        _require(
            self.clock_rate is None or self.clock_rate > 0,
            f"clock_rate must be > 0, got {self.clock_rate}",
        )
        _require(self.vehicle_id >= 1, f"vehicle_id must be >= 1, got {self.vehicle_id}")
        _require(self.step >= 0, f"step must be >= 0, got {self.step}")
        _require(bool(self.state), "state must not be empty")
        _require(
            self.stale_steps is None or self.stale_steps >= 0,
            f"stale_steps must be >= 0, got {self.stale_steps}",
        )


MESSAGE_TYPES: Mapping[TopicKind, type[Message]] = {
    TopicKind.STEP: StepMessage,
    TopicKind.RANGES: RangeSet,
    TopicKind.TARGET: TargetObservation,
    TopicKind.CONTROL: MissionControl,
    TopicKind.STATUS: VehicleStatus,
}
"""Which message type each topic kind of the layout carries."""

"""Topic layout of an enclosing mission, and MQTT topic-filter matching.

Every topic lives under a per-mission prefix, `enclosing/<mission_id>` by default, so
several missions can share one broker. `<id>` is a vehicle id (an integer >= 1, written
without leading zeros). Payloads are compact UTF-8 JSON objects (see
`mission_runner.bus.messages`).

| Topic | Payload | Published by | Retained |
|---|---|---|---|
| `<prefix>/vehicle/<id>/step` | `StepMessage` | vehicle `<id>`, once per step k | no |
| `<prefix>/vehicle/<id>/ranges` | `RangeSet` | UWB driver on `<id>`, once per ranging round | no |
| `<prefix>/vehicle/<id>/target` | `TargetObservation` | target tracker on `<id>` | no |
| `<prefix>/vehicle/<id>/status` | `VehicleStatus` | vehicle `<id>`; also its MQTT last will | yes |
| `<prefix>/control` | `MissionControl` | ground station / operator | no |

Subscription patterns (MQTT wildcards: `+` is one level, `#` the rest):

| Pattern | Receives |
|---|---|
| `<prefix>/vehicle/+/step` | every vehicle's step messages |
| `<prefix>/vehicle/+/ranges` | every vehicle's range sets |
| `<prefix>/vehicle/+/target` | every target observation |
| `<prefix>/vehicle/+/status` | every vehicle's status (progress views) |
| `<prefix>/#` | everything in the mission (logging) |

Control commands are not retained on purpose: a vehicle that (re)connects must not act on
an old `start`. Status is retained so a progress view that starts late sees every vehicle.

`topic_matches` is the one MQTT matcher of the package: the in-process bus routes with it
and the MQTT bus uses it to hand each incoming message to the right local subscriptions.
"""

from __future__ import annotations

import enum
import functools
from dataclasses import dataclass

from mission_runner.bus.errors import TopicError

MAX_TOPIC_BYTES = 65535
DEFAULT_PREFIX_ROOT = "enclosing"
TARGET_PEER_ID = 0


def _check_common(text: str, what: str) -> None:
    if not isinstance(text, str):
        raise TopicError(f"{what} must be a str, got {type(text).__name__}")
    if not text:
        raise TopicError(f"{what} must not be empty")
    if "\x00" in text:
        raise TopicError(f"{what} {text!r} contains a NUL character")
    if len(text.encode("utf-8")) > MAX_TOPIC_BYTES:
        raise TopicError(f"{what} is longer than {MAX_TOPIC_BYTES} bytes")


def validate_topic(topic: str) -> str:
    """Return ``topic`` if it is a valid MQTT topic name (no wildcards), else raise TopicError."""
    _check_common(topic, "topic")
    if "+" in topic or "#" in topic:
        raise TopicError(
            f"topic {topic!r} contains a wildcard; publish to a concrete topic, "
            "wildcards are only for subscriptions"
        )
    return topic


def validate_pattern(pattern: str) -> str:
    """Return ``pattern`` if it is a valid MQTT topic filter, else raise TopicError.

    ``+`` must fill a whole level; ``#`` must fill the last level.
    """
    _check_common(pattern, "pattern")
    levels = pattern.split("/")
    for index, level in enumerate(levels):
        if level == "#":
            if index != len(levels) - 1:
                raise TopicError(f"pattern {pattern!r}: '#' is only allowed as the last level")
        elif level != "+" and ("+" in level or "#" in level):
            raise TopicError(
                f"pattern {pattern!r}: level {level!r} mixes a wildcard with text; "
                "a wildcard must fill a whole level"
            )
    return pattern


#: Distinct (pattern, topic) pairs remembered by :func:`topic_matches`: a mission has a few
#: hundred; a flood of made-up topics only cycles the cache.
MATCH_CACHE_SIZE = 4096


@functools.lru_cache(maxsize=MATCH_CACHE_SIZE)
def topic_matches(pattern: str, topic: str) -> bool:
    """Whether ``topic`` matches the MQTT topic filter ``pattern``.

    Follows MQTT 3.1.1 section 4.7: ``+`` matches exactly one level (possibly empty), ``#``
    matches the parent level and any number of levels below it, and a wildcard in the first
    level never matches a topic that starts with ``$``. Both arguments are assumed valid
    (see ``validate_pattern`` and ``validate_topic``). Remembered: the in-process bus asks
    it for every subscription on every publish, the same few pairs over and over.
    """
    if pattern == topic:
        return True
    if topic.startswith("$") and pattern[:1] in ("+", "#"):
        return False
    pattern_levels = pattern.split("/")
    topic_levels = topic.split("/")
    for index, level in enumerate(pattern_levels):
        if level == "#":
            return True
        if index >= len(topic_levels):
            return False
        if level != "+" and level != topic_levels[index]:
            return False
    return len(pattern_levels) == len(topic_levels)


class TopicKind(enum.StrEnum):
    """What a topic of the mission layout carries."""

    STEP = "step"
    RANGES = "ranges"
    TARGET = "target"
    STATUS = "status"
    CONTROL = "control"


@dataclass(frozen=True, slots=True)
class ParsedTopic:
    """A topic of the mission layout, taken apart.

    ``vehicle_id`` is None for ``control``.
    """

    kind: TopicKind
    vehicle_id: int | None = None


def _check_level(text: str, what: str) -> str:
    _check_common(text, what)
    if "/" in text or "+" in text or "#" in text:
        raise TopicError(f"{what} {text!r} must be a single topic level without '/', '+' or '#'")
    return text


def _check_vehicle_id(vehicle_id: int, what: str = "vehicle id", minimum: int = 1) -> int:
    if isinstance(vehicle_id, bool) or not isinstance(vehicle_id, int) or vehicle_id < minimum:
        raise TopicError(f"{what} must be an integer >= {minimum}, got {vehicle_id!r}")
    return vehicle_id


def _parse_id(text: str, topic: str, minimum: int) -> int:
    # Only canonical decimal ids: "01" or "+1" would make two topics name one vehicle.
    if not text.isascii() or not text.isdigit() or (len(text) > 1 and text[0] == "0"):
        raise TopicError(f"topic {topic!r}: {text!r} is not a vehicle id")
    value = int(text)
    if value < minimum:
        raise TopicError(f"topic {topic!r}: id {value} must be >= {minimum}")
    return value


class Topics:
    """Builds and parses the topics of one mission (see the module docstring for the layout).

    >>> topics = Topics.for_mission("demo")
    >>> topics.step(2)
    'enclosing/demo/vehicle/2/step'
    >>> topics.parse("enclosing/demo/vehicle/2/ranges")
    ParsedTopic(kind=<TopicKind.RANGES: 'ranges'>, vehicle_id=2)
    """

    def __init__(self, prefix: str) -> None:
        validate_topic(prefix)
        if prefix.startswith("$"):
            raise TopicError(f"prefix {prefix!r} must not start with '$' (reserved by brokers)")
        if prefix.startswith("/") or prefix.endswith("/") or "//" in prefix:
            raise TopicError(f"prefix {prefix!r} must not have empty levels")
        self.prefix = prefix

    @classmethod
    def for_mission(cls, mission_id: str, root: str = DEFAULT_PREFIX_ROOT) -> Topics:
        """Topics under ``<root>/<mission_id>``."""
        return cls(f"{root}/{_check_level(mission_id, 'mission id')}")

    def __repr__(self) -> str:
        return f"Topics({self.prefix!r})"

    # Concrete topics --------------------------------------------------------------------
    def step(self, vehicle_id: int) -> str:
        """Topic of vehicle ``vehicle_id``'s per-step broadcast."""
        return f"{self.prefix}/vehicle/{_check_vehicle_id(vehicle_id)}/step"

    def ranges(self, vehicle_id: int) -> str:
        """Topic of the range sets measured by vehicle ``vehicle_id`` (one per ranging round)."""
        return f"{self.prefix}/vehicle/{_check_vehicle_id(vehicle_id)}/ranges"

    def target(self, vehicle_id: int) -> str:
        """Topic of target observations made on vehicle ``vehicle_id``."""
        return f"{self.prefix}/vehicle/{_check_vehicle_id(vehicle_id)}/target"

    def status(self, vehicle_id: int) -> str:
        """Topic of vehicle ``vehicle_id``'s status (retained; its last will)."""
        return f"{self.prefix}/vehicle/{_check_vehicle_id(vehicle_id)}/status"

    def control(self) -> str:
        """Topic of mission commands (start, stop, hold, land)."""
        return f"{self.prefix}/control"

    # Subscription patterns --------------------------------------------------------------
    def all_steps(self) -> str:
        """Pattern matching every vehicle's step topic."""
        return f"{self.prefix}/vehicle/+/step"

    def all_ranges(self) -> str:
        """Pattern matching every vehicle's range sets."""
        return f"{self.prefix}/vehicle/+/ranges"

    def all_targets(self) -> str:
        """Pattern matching every vehicle's target observations."""
        return f"{self.prefix}/vehicle/+/target"

    def all_status(self) -> str:
        """Pattern matching every vehicle's status."""
        return f"{self.prefix}/vehicle/+/status"

    def everything(self) -> str:
        """Pattern matching every topic of the mission."""
        return f"{self.prefix}/#"

    # Parsing ----------------------------------------------------------------------------
    def parse(self, topic: str) -> ParsedTopic:
        """Take a topic of this mission apart; raise TopicError if it is not one."""
        head = self.prefix + "/"
        if not isinstance(topic, str) or not topic.startswith(head):
            raise TopicError(f"topic {topic!r} is not under the mission prefix {self.prefix!r}")
        levels = topic[len(head) :].split("/")
        if levels == ["control"]:
            return ParsedTopic(TopicKind.CONTROL)
        if len(levels) >= 3 and levels[0] == "vehicle":
            vehicle_id = _parse_id(levels[1], topic, minimum=1)
            rest = levels[2:]
            if rest == ["step"]:
                return ParsedTopic(TopicKind.STEP, vehicle_id)
            if rest == ["target"]:
                return ParsedTopic(TopicKind.TARGET, vehicle_id)
            if rest == ["status"]:
                return ParsedTopic(TopicKind.STATUS, vehicle_id)
            if rest == ["ranges"]:
                return ParsedTopic(TopicKind.RANGES, vehicle_id)
        raise TopicError(f"topic {topic!r} does not fit the mission topic layout")

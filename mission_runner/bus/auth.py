"""Authenticated bus messages: who may say what on the bus, and how a receiver checks it.

Every non-empty payload on the bus is sealed by the sending bus and opened by the receiving bus
(``Bus`` does both, for every implementation): no command or message of the mission reads a
payload that did not pass here. Sealing prefixes the message body with one header line::

    MR1 <mac> <sender> <seq> <time_ms> <flags>\\n<body>

- ``mac``: HMAC-SHA256 under the mission's bus key (base64url, 43 characters) over the topic,
  the rest of the header and the body. The topic carries the mission's prefix, so a message of
  one mission replayed into another (or moved to another vehicle's topic) fails the MAC.
- ``sender``: the role that signed, ``ground``, ``vehicle-<id>`` or ``ranges`` (the range aid).
- ``seq``: the sender's sequence number, increasing by at least one per message and started at
  the sender's UNIX time in microseconds, so that a restarted sender continues above its
  previous run.
- ``time_ms``: the sender's UNIX time in milliseconds.
- ``flags``: ``-``, ``r`` (published retained) or ``w`` (the sender's MQTT last will).

A receiver drops and counts (:class:`AuthCounters`, rate-limited warnings):

- ``oversized``: more than ``max_message_bytes`` (checked before anything else);
- ``malformed``: no parsable header;
- ``forged``: the MAC does not match (no key, another key, a changed byte);
- ``unauthorised``: the sender's role may not publish on that topic (see :func:`allowed`):
  ``control`` is the ground station's, a vehicle's ``step`` and ``status`` its own, its
  ``ranges`` and ``target`` its own or the range aid's;
- ``stale``: sent more than ``time_window_s`` ago or ahead of the receiver's clock (a retained
  message, delivered from the broker's store: up to ``retained_max_age_s`` old);
- ``replayed``: a sequence number not above the last one accepted from that sender on that
  topic (MQTT keeps a publisher's order per topic, so this never drops a fresh message). A
  retained message handed again to a new subscription is the same message, not a replay;
- ``empty``: an empty payload (MQTT's "clear this retained topic"): no message, never handed on.

A last will is signed when the connection opens and published by the broker whenever the
sender drops off, so it is exempt from the time window; it is still MAC-checked and accepted
once per will (its own sequence track).

One shared key: whoever holds it can sign as any role; the role in the header catches
misdirected messages and is what the broker's ACL (``mission-runner broker-config``) enforces
per user. Empty payloads (MQTT's "clear this retained topic") carry no message: they are sent
unsigned (the broker clears the topic) and dropped on receipt.
"""

from __future__ import annotations

import base64
import enum
import hashlib
import hmac
import logging
import os
import secrets
import stat
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from mission_runner.bus.errors import BusAuthError
from mission_runner.environment import DEFAULT_KEY_ENV

logger = logging.getLogger(__name__)

MAGIC = b"MR1"
#: Shortest key accepted: 32 characters (``openssl rand -hex 32`` makes 64).
MIN_KEY_CHARS = 32
#: What an insecure bus (``--insecure-bus``) signs with: public, so anyone can forge.
INSECURE_KEY_TEXT = "mission-runner insecure bus: anyone can forge these messages"

_MAC_CHARS = 43  # base64url of 32 bytes, unpadded
_MAGIC_PREFIX = MAGIC + b" "
_FLAGS = {b"-": (False, False), b"r": (True, False), b"w": (True, True)}


class Role(enum.StrEnum):
    """What a signer is to the mission."""

    GROUND = "ground"
    VEHICLE = "vehicle"
    RANGES = "ranges"


@dataclass(frozen=True, slots=True)
class Sender:
    """A signer's identity: a role, and for a vehicle its id. ``str`` is its header form and
    the broker user name ``broker-config`` gives it (``ground``, ``vehicle-3``, ``ranges``)."""

    role: Role
    vehicle_id: int | None = None

    def __post_init__(self) -> None:
        if (self.role is Role.VEHICLE) != (self.vehicle_id is not None):
            raise ValueError("a vehicle sender needs its vehicle_id, and only a vehicle has one")
        if self.vehicle_id is not None and self.vehicle_id < 1:
            raise ValueError(f"vehicle_id must be >= 1, got {self.vehicle_id}")

    @classmethod
    def ground(cls) -> Sender:
        return cls(Role.GROUND)

    @classmethod
    def ranges(cls) -> Sender:
        """The range aid (synthesised UWB ranges and target observations for every vehicle)."""
        return cls(Role.RANGES)

    @classmethod
    def vehicle(cls, vehicle_id: int) -> Sender:
        return cls(Role.VEHICLE, vehicle_id)

    @classmethod
    def parse(cls, text: str) -> Sender:
        """The sender ``str(sender)`` wrote; ValueError if it is none."""
        if text in (Role.GROUND, Role.RANGES):
            return cls(Role(text))
        head, _, number = text.partition("-")
        if head != Role.VEHICLE or not number.isascii() or not number.isdigit():
            raise ValueError(f"not a sender: {text!r}")
        if len(number) > 1 and number[0] == "0":
            raise ValueError(f"not a sender: {text!r}")
        return cls(Role.VEHICLE, int(number))

    @classmethod
    def for_topic(cls, topic: str) -> Sender:
        """The sender a topic belongs to (a vehicle's topics: that vehicle; anything else: the
        ground station). For a bus that speaks for everyone on it: one process running the
        whole swarm, or a test."""
        owner = _owner(topic)
        if owner is None or owner[0] == "control":
            return cls.ground()
        return cls.vehicle(owner[1])

    def __str__(self) -> str:
        if self.role is Role.VEHICLE:
            return f"vehicle-{self.vehicle_id}"
        return self.role.value


#: The last level of a vehicle's topics (``<prefix>/vehicle/<id>/<kind>``).
_VEHICLE_TOPICS = frozenset({"step", "status", "target", "ranges"})


def _owner(topic: str) -> tuple[str, int] | None:
    """``(kind, vehicle id)`` of a vehicle topic of the mission layout (kind: step, status,
    target or ranges), ``("control", 0)`` for the control topic, None for anything else."""
    levels = topic.split("/")
    if levels[-1] == "control":
        return ("control", 0)
    if len(levels) < 3 or levels[-3] != "vehicle" or levels[-1] not in _VEHICLE_TOPICS:
        return None
    number, kind = levels[-2], levels[-1]
    if not number.isascii() or not number.isdigit() or number.startswith("0"):
        return None
    return (kind, int(number))


def allowed(sender: Sender, topic: str) -> bool:
    """Whether ``sender`` may publish on ``topic``.

    ``<prefix>/control``: the ground station only. ``vehicle/<id>/step`` and ``status``:
    vehicle ``<id>`` only. ``vehicle/<id>/ranges`` and ``target``: vehicle ``<id>`` (its
    own UWB and tracker) or the range aid. Topics outside the mission layout: any signer.
    """
    owner = _owner(topic)
    if owner is None:
        return True
    kind, vehicle_id = owner
    if kind == "control":
        return sender.role is Role.GROUND
    if sender.role is Role.VEHICLE:
        return sender.vehicle_id == vehicle_id
    return kind in ("ranges", "target") and sender.role is Role.RANGES


@dataclass(frozen=True)
class BusKey:
    """The mission's HMAC key. ``source`` says where it came from (for logs; never the key);
    ``fingerprint`` lets operators compare keys on two machines without showing them."""

    secret: bytes = field(repr=False)
    source: str
    insecure: bool = False

    def __post_init__(self) -> None:
        if len(self.secret) < MIN_KEY_CHARS and not self.insecure:
            raise BusAuthError(
                f"the bus key from {self.source} is {len(self.secret)} bytes long; it needs at "
                f"least {MIN_KEY_CHARS}",
                hint="make one with `openssl rand -hex 32` (or `mission-runner broker-config`)",
            )

    @property
    def fingerprint(self) -> str:
        return hashlib.sha256(b"mission-runner bus key fingerprint\n" + self.secret).hexdigest()[
            :12
        ]

    @classmethod
    def from_text(cls, text: str, source: str) -> BusKey:
        """A key written as text (surrounding whitespace ignored), e.g. 64 hex digits."""
        return cls(text.strip().encode("utf-8"), source)

    @classmethod
    def from_file(cls, path: Path) -> BusKey:
        """The key in ``path``. Warns when others than the owner may read the file."""
        try:
            mode = path.stat().st_mode
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as error:
            raise BusAuthError(
                f"cannot read the bus key file {path}: {error}",
                hint="give a readable file with --bus-key-file or bus.auth.key_file",
            ) from None
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            logger.warning(
                "bus key file %s can be read by other users (mode %o): chmod 600 it",
                path,
                stat.S_IMODE(mode),
            )
        return cls.from_text(text, f"file {path}")

    @classmethod
    def generate(cls, source: str = "generated for this process") -> BusKey:
        return cls(secrets.token_hex(32).encode("ascii"), source)

    @classmethod
    def insecure_key(cls) -> BusKey:
        """The public key of ``--insecure-bus``: messages are framed and replay-checked as
        usual, but anyone can sign them."""
        return cls(INSECURE_KEY_TEXT.encode("ascii"), "--insecure-bus (NO authentication)", True)


def resolve_key(
    *,
    kind: str,
    key_file: Path | None,
    cli_key_file: Path | None = None,
    key_env: str = DEFAULT_KEY_ENV,
    insecure: bool = False,
    environ: Mapping[str, str] | None = None,
) -> BusKey:
    """The bus key, from the first of: ``cli_key_file`` (``--bus-key-file``), the environment
    variable ``key_env``, ``key_file`` (``bus.auth.key_file``). Without one, an in-process bus
    gets a fresh random key (it never leaves the process) and an MQTT bus is refused unless
    ``insecure`` (``--insecure-bus``). Raises :class:`BusAuthError`."""
    environ = os.environ if environ is None else environ
    if cli_key_file is not None:
        return BusKey.from_file(cli_key_file)
    text = environ.get(key_env)
    if text:
        return BusKey.from_text(text, f"environment variable {key_env}")
    if key_file is not None:
        return BusKey.from_file(key_file)
    if kind == "inprocess":
        return BusKey.generate()
    if insecure:
        return BusKey.insecure_key()
    raise BusAuthError(
        "an MQTT bus needs a key: every message is signed with it, and messages without a "
        "valid signature are dropped",
        hint=f"give the same key file to every process with --bus-key-file FILE (or "
        f"bus.auth.key_file, or the environment variable {key_env}); "
        "`mission-runner broker-config` writes one; --insecure-bus runs without (closed bench "
        "networks only)",
    )


class Rejection(enum.StrEnum):
    """Why a received payload was dropped."""

    OVERSIZED = "oversized"
    MALFORMED = "malformed"
    FORGED = "forged"
    UNAUTHORISED = "unauthorised"
    STALE = "stale"
    REPLAYED = "replayed"
    #: An empty payload: MQTT's "clear this retained topic", which carries no message (the
    #: ground station's own clear of its ``prepare`` at the end counts here too).
    EMPTY = "empty"


@dataclass
class AuthCounters:
    """Payloads a bus accepted and dropped, by reason."""

    accepted: int = 0
    oversized: int = 0
    malformed: int = 0
    forged: int = 0
    unauthorised: int = 0
    stale: int = 0
    replayed: int = 0
    empty: int = 0

    @property
    def rejected(self) -> int:
        return sum(getattr(self, reason.value) for reason in Rejection)

    def as_dict(self) -> dict[str, int]:
        return {"accepted": self.accepted, **{r.value: getattr(self, r.value) for r in Rejection}}


class RateLimitedWarnings:
    """At most one warning line per ``interval_s`` per kind: the first at once, later ones
    with how many were held back. ``clock`` returns monotonic seconds (a test injects one)."""

    def __init__(
        self,
        log: logging.Logger,
        *,
        interval_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._log = log
        self._interval_s = interval_s
        self._clock = clock
        self._last_s: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def warn(self, kind: str, message: str, *args: object) -> bool:
        """Log ``message % args`` unless ``kind`` was logged within the interval; returns
        whether a line was written."""
        now_s = self._clock()
        last_s = self._last_s.get(kind)
        if last_s is not None and now_s - last_s < self._interval_s:
            self._held[kind] = self._held.get(kind, 0) + 1
            return False
        held = self._held.pop(kind, 0)
        self._last_s[kind] = now_s
        suffix = f" ({held} more since the last report)" if held else ""
        self._log.warning(message + suffix, *args)
        return True


@dataclass(frozen=True)
class AuthPolicy:
    """Receiver limits (``bus.auth`` in a scenario)."""

    time_window_s: float = 10.0
    retained_max_age_s: float = 600.0
    max_message_bytes: int = 16384


class MessageAuth:
    """Seals what a bus sends and opens what it receives (see the module docstring).

    One per bus: it holds the bus's sequence numbers (per sender, as one in-process bus may
    speak for several) and what it has accepted (per sender and topic). ``wall_clock`` is UNIX
    time in seconds; ``log_clock`` paces the warnings (both injectable for tests).
    """

    def __init__(
        self,
        key: BusKey,
        policy: AuthPolicy | None = None,
        *,
        endpoint: str = "",
        wall_clock: Callable[[], float] = time.time,
        log_clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.key = key
        self.policy = policy or AuthPolicy()
        self.counters = AuthCounters()
        self._endpoint = endpoint
        self._wall_clock = wall_clock
        self._warnings = RateLimitedWarnings(logger, clock=log_clock)
        self._sequence: dict[str, int] = {}
        # (sender, topic, is_will) -> (last accepted seq, its MAC)
        self._accepted: dict[tuple[str, str, bool], tuple[int, bytes]] = {}

    # Sending ---------------------------------------------------------------------------------
    def next_sequence(self, sender: str) -> int:
        now_us = int(self._wall_clock() * 1e6)
        sequence = max(self._sequence.get(sender, 0) + 1, now_us)
        self._sequence[sender] = sequence
        return sequence

    def seal(
        self, sender: Sender, topic: str, body: bytes, *, retain: bool = False, will: bool = False
    ) -> bytes:
        """``body`` with its header: what goes on the wire. Empty bodies stay empty."""
        if not body:
            return b""
        name = str(sender)
        flags = b"w" if will else b"r" if retain else b"-"
        rest = b"%s %d %d %s" % (
            name.encode("ascii"),
            self.next_sequence(name),
            round(self._wall_clock() * 1000),
            flags,
        )
        mac = self._mac(topic, rest, body)
        return b"%s %s %s\n%s" % (MAGIC, mac, rest, body)

    def _mac(self, topic: str, rest: bytes, body: bytes) -> bytes:
        digest = hmac.new(self.key.secret, digestmod=hashlib.sha256)
        digest.update(b"%s\n%s\n%s\n" % (MAGIC, topic.encode("utf-8"), rest))
        digest.update(body)
        return base64.urlsafe_b64encode(digest.digest())[:_MAC_CHARS]

    # Receiving -------------------------------------------------------------------------------
    def open(self, topic: str, data: bytes, *, retained: bool = False) -> bytes | None:
        """The body of ``data`` received on ``topic`` (``retained``: handed over from the
        broker's retained store), or None when it is dropped (counted and logged). An empty
        payload is never a message: dropped and counted, not logged (a flood of them must cost
        no more than counting)."""
        if not self.admits(topic, data):
            return None
        header, newline, body = data.partition(b"\n")
        parts = header.split(b" ")
        if not newline or len(parts) != 6 or parts[0] != MAGIC or len(parts[1]) != _MAC_CHARS:
            return self._reject(Rejection.MALFORMED, topic, "no bus message header")
        _, mac, sender_text, sequence_text, time_text, flags = parts
        rest = header[len(MAGIC) + 2 + _MAC_CHARS :]
        if not hmac.compare_digest(mac, self._mac(topic, rest, body)):
            return self._reject(Rejection.FORGED, topic, "bad MAC (no key, or another key)")
        try:
            sender = Sender.parse(sender_text.decode("ascii"))
            sequence, sent_ms = int(sequence_text), int(time_text)
            sent_retained, will = _FLAGS[flags]
        except (ValueError, KeyError, UnicodeDecodeError):
            return self._reject(Rejection.MALFORMED, topic, "unreadable header fields")
        if not allowed(sender, topic):
            return self._reject(Rejection.UNAUTHORISED, topic, f"{sender} may not publish here")
        key = (str(sender), topic, will)
        last = self._accepted.get(key)
        if retained and last is not None and last == (sequence, mac):
            self.counters.accepted += 1  # the retained message, handed to a new subscription
            return body
        if not will:
            age_s = self._wall_clock() - sent_ms / 1000.0
            oldest_s = (
                self.policy.retained_max_age_s
                if retained and sent_retained
                else self.policy.time_window_s
            )
            if age_s > oldest_s or age_s < -self.policy.time_window_s:
                when = f"{age_s:.1f} s ago" if age_s > 0 else f"{-age_s:.1f} s ahead of this clock"
                return self._reject(Rejection.STALE, topic, f"from {sender}, sent {when}")
        if last is not None and sequence <= last[0]:
            return self._reject(
                Rejection.REPLAYED, topic, f"from {sender}, seq {sequence} <= {last[0]}"
            )
        self._accepted[key] = (sequence, mac)
        self.counters.accepted += 1
        return body

    def admits(self, topic: str, data: bytes) -> bool:
        """Whether ``data`` received on ``topic`` may be a sealed message, judged on its length
        and first bytes only: an empty payload, one over ``max_message_bytes`` and one without
        the header's magic are dropped and counted here, as :meth:`open` would, before anything
        else is spent on them (the MQTT bus asks before its client builds a message)."""
        if not data:
            self.counters.empty += 1
            return False
        if len(data) > self.policy.max_message_bytes:
            self._reject(Rejection.OVERSIZED, topic, f"{len(data)} bytes")
            return False
        if not data.startswith(_MAGIC_PREFIX):
            self._reject(Rejection.MALFORMED, topic, "no bus message header")
            return False
        return True

    def skipped_oversized(self, packet_bytes: int) -> None:
        """Count an MQTT packet of ``packet_bytes`` skipped unread for its size (its topic was
        never read: see :mod:`mission_runner.bus.oversize`)."""
        self._reject(Rejection.OVERSIZED, "a topic not read", f"a {packet_bytes}-byte packet")

    def _reject(self, reason: Rejection, topic: str, detail: str) -> bytes | None:
        setattr(self.counters, reason.value, getattr(self.counters, reason.value) + 1)
        self._warnings.warn(
            reason.value,
            "bus %s: dropped a %s message on %s (%s); %d dropped so far",
            self._endpoint or "",
            reason.value,
            topic,
            detail,
            self.counters.rejected,
        )
        return None

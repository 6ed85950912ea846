"""MAVLink 2 message signing of one emulated vehicle, the way PX4 does it.

PX4's MAVLink module (``mavlink_sign_control.cpp``, ``mavlink_signing_storage.cpp`` and the
MAVLink C library's ``mavlink_signature_check``; user documentation: PX4 "MAVLink Message
Signing") behaves as follows, and so does :class:`VehicleSigning`:

- Without a key, signing is off: nothing is signed and everything is accepted.
- A SETUP_SIGNING with a key (on any link, broadcast or addressed to the autopilot, while
  disarmed) provisions it. From then on every link of the vehicle signs what it sends, and an
  incoming packet is accepted only when it carries a valid signature with that key, except
  HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE and COLLISION (:data:`UNSIGNED_ACCEPT_LIST`), which are
  accepted unsigned (or with a bad signature) whatever the state.
- Once a key is active, changing it needs a SETUP_SIGNING signed with the current key (an
  unsigned one is refused like any other unsigned packet); an all-zero key and timestamp,
  signed, turns signing off; an unsigned blank key is refused. SETUP_SIGNING is never passed
  on to the rest of the autopilot. Every change is refused while the vehicle is armed.
- Timestamps count 10 microseconds since 2015-01-01 00:00 UTC. Outgoing packets use the
  vehicle's timestamp and add one to it; it starts at the larger of the stored timestamp and
  the host's clock (PX4 reads CLOCK_REALTIME), and follows the newest accepted incoming one.
  A signed packet is accepted only if its stream (system, component, link id) has never sent
  a timestamp as large (replay) and, for a stream seen for the first time, if it is at most
  one minute behind the vehicle's timestamp; at most 16 streams are tracked.
- The key and timestamp are stored (PX4: ``/mavlink/mavlink-signing-key.bin`` on the SD card,
  32 key bytes then the little-endian uint64 timestamp, mode 0600): see :class:`FileKeyStore`
  and :class:`MemoryKeyStore`. A new key is stored when it arrives; the timestamp is stored
  again on a clean shutdown (:meth:`VehicleSigning.checkpoint`).

The links of one vehicle share one :class:`VehicleSigning` (PX4: one key file, one table of
signing streams); each link signs with its own link id (:data:`LINK_IDS`).
"""

from __future__ import annotations

import contextlib
import enum
import hashlib
import hmac
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from pymavlink.dialects.v20 import common as mavlink

logger = logging.getLogger(__name__)

KEY_BYTES = 32
#: 2015-01-01 00:00:00 UTC, the zero of MAVLink signing timestamps.
MAVLINK_SIGNING_EPOCH_UNIX_S = 1_420_070_400
TIMESTAMP_TICKS_PER_S = 100_000
#: A stream seen for the first time may be this far behind the vehicle's timestamp (1 min).
NEW_STREAM_MAX_AGE_TICKS = 60 * TIMESTAMP_TICKS_PER_S
#: MAVLINK_MAX_SIGNING_STREAMS of the C library PX4 uses.
MAX_SIGNING_STREAMS = 16
#: What PX4 accepts unsigned even while signing is on (``unsigned_messages`` in
#: mavlink_sign_control.cpp): discovery and safety traffic from systems that cannot sign.
UNSIGNED_ACCEPT_LIST: frozenset[int] = frozenset(
    [
        mavlink.MAVLINK_MSG_ID_HEARTBEAT,
        mavlink.MAVLINK_MSG_ID_RADIO_STATUS,
        mavlink.MAVLINK_MSG_ID_ADSB_VEHICLE,
        mavlink.MAVLINK_MSG_ID_COLLISION,
    ]
)
#: Link id of each link in the signatures it sends: PX4 uses the MAVLink instance number, and
#: PX4 SITL starts the GCS link first (0), then the API/offboard link (1), the payload (2) and
#: gimbal (3) links the emulator does not have, and SIH's ground-truth link (4).
LINK_IDS: dict[str, int] = {"gcs": 0, "api": 1, "truth": 4}

_SIGNATURE_BYTES = 13
_KEY_FILE_NAME = "mavlink-signing-key.bin"


def signing_timestamp(unix_time_s: float) -> int:
    """MAVLink signing timestamp (10 us ticks since 2015) of a UNIX time; 0 before 2015."""
    return max(0, int((unix_time_s - MAVLINK_SIGNING_EPOCH_UNIX_S) * TIMESTAMP_TICKS_PER_S))


def key_from_passphrase(passphrase: str) -> bytes:
    """The 32-byte key of a passphrase: its SHA-256, as MAVProxy's ``signing setup`` makes it."""
    return hashlib.sha256(passphrase.encode()).digest()


@dataclass(frozen=True, slots=True)
class SigningKey:
    """A secret key and the timestamp stored with it; all zeros means signing off."""

    key: bytes
    timestamp: int = 0

    def __post_init__(self) -> None:
        if len(self.key) != KEY_BYTES:
            raise ValueError(f"a MAVLink signing key has {KEY_BYTES} bytes, got {len(self.key)}")
        if not 0 <= self.timestamp < 2**64:
            raise ValueError(f"signing timestamp out of range: {self.timestamp}")

    @property
    def enabled(self) -> bool:
        """PX4 treats a non-zero key or timestamp as a key (``is_enabled``)."""
        return self.timestamp != 0 or any(self.key)

    def to_bytes(self) -> bytes:
        """PX4's key file: 32 key bytes, then the timestamp as a little-endian uint64."""
        return self.key + self.timestamp.to_bytes(8, "little")

    @classmethod
    def from_bytes(cls, data: bytes) -> SigningKey:
        if len(data) != KEY_BYTES + 8:
            raise ValueError(f"a signing key file has {KEY_BYTES + 8} bytes, got {len(data)}")
        return cls(bytes(data[:KEY_BYTES]), int.from_bytes(data[KEY_BYTES:], "little"))


BLANK_KEY = SigningKey(bytes(KEY_BYTES), 0)


class KeyStore(Protocol):
    """Where each vehicle's key survives a restart (PX4: the SD card), by system id."""

    def load(self, sysid: int) -> SigningKey | None: ...

    def save(self, sysid: int, key: SigningKey) -> None: ...


@dataclass
class MemoryKeyStore:
    """Keys kept in this process only: hand the same store to the next :class:`Emulator` and
    its vehicles boot with the keys the previous one ended with."""

    keys: dict[int, SigningKey] = field(default_factory=dict)

    def load(self, sysid: int) -> SigningKey | None:
        return self.keys.get(sysid)

    def save(self, sysid: int, key: SigningKey) -> None:
        self.keys[sysid] = key


class FileKeyStore:
    """One PX4 key file per vehicle: ``<directory>/vehicle_<sysid>/mavlink-signing-key.bin``
    (40 bytes, mode 0600, its folder 0700), replaced atomically on every change."""

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)

    def path(self, sysid: int) -> Path:
        return self.directory / f"vehicle_{sysid:03d}" / _KEY_FILE_NAME

    def load(self, sysid: int) -> SigningKey | None:
        path = self.path(sysid)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            return None
        try:
            return SigningKey.from_bytes(data)
        except ValueError as exc:
            # PX4 starts without a key when the file cannot be read whole.
            logger.warning("vehicle %d: ignoring signing key file %s: %s", sysid, path, exc)
            return None

    def save(self, sysid: int, key: SigningKey) -> None:
        path = self.path(sysid)
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        temporary = path.with_name(path.name + ".tmp")
        fd = os.open(temporary, os.O_CREAT | os.O_WRONLY | os.O_TRUNC, 0o600)
        try:
            with os.fdopen(fd, "wb") as file:
                file.write(key.to_bytes())
                file.flush()
                os.fsync(file.fileno())
            os.replace(temporary, path)
        except BaseException:
            with contextlib.suppress(OSError):
                temporary.unlink()
            raise


class Verdict(enum.Enum):
    """What the signing check made of one incoming packet."""

    ACCEPTED = "accepted"
    """Signing is off, or the packet is signed with the key, in time."""
    ACCEPTED_UNSIGNED = "accepted unsigned"
    """Unsigned (or badly signed) but on :data:`UNSIGNED_ACCEPT_LIST`."""
    UNSIGNED = "unsigned"
    BAD_SIGNATURE = "bad signature"
    REPLAY = "replayed timestamp"
    OLD_TIMESTAMP = "timestamp too old for a new stream"
    TOO_MANY_STREAMS = "too many signing streams"

    @property
    def accepted(self) -> bool:
        return self in (Verdict.ACCEPTED, Verdict.ACCEPTED_UNSIGNED)


class SetupResult(enum.Enum):
    """What a SETUP_SIGNING did (PX4's ``SetupSigningResult`` plus the armed guard)."""

    KEY_ACCEPTED = "key accepted"
    SIGNING_DISABLED = "signing disabled"
    BLANK_KEY_REJECTED = "blank key rejected: it must be signed"
    REJECTED_ARMED = "rejected while armed"
    NOT_ADDRESSED = "addressed to another system or component"
    STORAGE_ERROR = "key could not be stored"


class VehicleSigning:
    """The signing state of one vehicle, shared by all its links.

    ``store`` keeps the key across restarts; ``initial_key`` (if given) is provisioned at start
    as if a SETUP_SIGNING had brought it. ``unix_time_s`` is the host clock the timestamps
    start from; ``is_armed`` guards key changes. Counters: ``verdicts`` (incoming packets by
    :class:`Verdict`) and ``setups`` (SETUP_SIGNING messages by :class:`SetupResult`).
    """

    def __init__(
        self,
        sysid: int,
        *,
        compid: int = 1,
        store: KeyStore | None = None,
        initial_key: bytes | None = None,
        unix_time_s: Callable[[], float] = time.time,
        is_armed: Callable[[], bool] = lambda: False,
    ) -> None:
        self.sysid = sysid
        self.compid = compid
        self._store: KeyStore = store if store is not None else MemoryKeyStore()
        self._unix_time_s = unix_time_s
        self._is_armed = is_armed
        self._key: bytes | None = None
        #: The next outgoing signature's timestamp, in 10 us ticks since 2015.
        self.timestamp = 0
        #: Last timestamp per (system, component, link id) stream.
        self.streams: dict[tuple[int, int, int], int] = {}
        self.verdicts: dict[Verdict, int] = dict.fromkeys(Verdict, 0)
        self.setups: dict[SetupResult, int] = dict.fromkeys(SetupResult, 0)
        if initial_key is not None:
            self._provision(SigningKey(initial_key, 0))
        else:
            stored = self._store.load(sysid)
            if stored is not None and stored.enabled:
                self._apply(SigningKey(stored.key, max(stored.timestamp, self._now())))
        if self._key is not None:
            logger.info("vehicle %d: MAVLink signing on (key %s)", sysid, self.fingerprint)

    # ------------------------------------------------------------------ state
    @property
    def active(self) -> bool:
        """A key is set: outgoing packets are signed, unsigned incoming ones refused."""
        return self._key is not None

    @property
    def fingerprint(self) -> str:
        """First 8 hex digits of SHA-256 of the key, to tell keys apart in logs ("" if off)."""
        if self._key is None:
            return ""
        return hashlib.sha256(self._key).hexdigest()[:8]

    @property
    def rejected(self) -> int:
        """Incoming packets refused so far, whatever the reason."""
        return sum(count for verdict, count in self.verdicts.items() if not verdict.accepted)

    def _now(self) -> int:
        return signing_timestamp(self._unix_time_s())

    def _apply(self, key: SigningKey) -> None:
        if key.enabled:
            self._key = key.key
            self.timestamp = key.timestamp
        else:
            self._key = None
            self.timestamp = 0

    # --------------------------------------------------------------- incoming
    def check(self, msg: mavlink.MAVLink_message) -> Verdict:
        """Judge one decoded incoming packet (as the C library does before PX4 sees it)."""
        verdict = self._check(msg)
        self.verdicts[verdict] += 1
        return verdict

    def _check(self, msg: mavlink.MAVLink_message) -> Verdict:
        key = self._key
        if key is None:
            return Verdict.ACCEPTED
        buf = msg.get_msgbuf()
        signed = buf[0] == mavlink.PROTOCOL_MARKER_V2 and buf[2] & mavlink.MAVLINK_IFLAG_SIGNED
        if not signed:  # MAVLink 1 packets cannot be signed
            return self._unsigned(msg, Verdict.UNSIGNED)
        # The signature: link id, 48-bit timestamp, then the first 6 bytes of
        # SHA-256(key + the packet up to and including the timestamp).
        expected = hashlib.sha256(key + bytes(buf[:-6])).digest()[:6]
        if not hmac.compare_digest(expected, bytes(buf[-6:])):
            return self._unsigned(msg, Verdict.BAD_SIGNATURE)
        link_id = buf[-_SIGNATURE_BYTES]
        stamp = int.from_bytes(buf[-12:-6], "little")
        stream = (msg.get_srcSystem(), msg.get_srcComponent(), link_id)
        last = self.streams.get(stream)
        if last is None:
            if len(self.streams) >= MAX_SIGNING_STREAMS:
                return self._unsigned(msg, Verdict.TOO_MANY_STREAMS)
            if stamp + NEW_STREAM_MAX_AGE_TICKS < self.timestamp:
                return self._unsigned(msg, Verdict.OLD_TIMESTAMP)
        elif stamp <= last:
            return self._unsigned(msg, Verdict.REPLAY)
        self.streams[stream] = stamp
        # Whatever is sent next must not be older than what was accepted.
        self.timestamp = max(self.timestamp, stamp)
        return Verdict.ACCEPTED

    @staticmethod
    def _unsigned(msg: mavlink.MAVLink_message, failure: Verdict) -> Verdict:
        # The C library asks PX4's accept-unsigned callback for every packet that failed.
        if msg.get_msgId() in UNSIGNED_ACCEPT_LIST:
            return Verdict.ACCEPTED_UNSIGNED
        return failure

    # --------------------------------------------------------------- outgoing
    def send(self, encoder: mavlink.MAVLink, msg: mavlink.MAVLink_message, link_id: int) -> None:
        """Encode ``msg`` with ``encoder`` (a link's pymavlink encoder), signed with the current
        key, link id ``link_id`` and the vehicle's timestamp if signing is on."""
        signing = encoder.signing
        key = self._key
        if key is None:
            if signing.sign_outgoing:
                signing.sign_outgoing = False
                signing.secret_key = None
            encoder.send(msg)
            return
        signing.secret_key = key
        signing.sign_outgoing = True
        signing.link_id = link_id
        signing.timestamp = self.timestamp
        encoder.send(msg)
        self.timestamp = signing.timestamp  # pymavlink adds one per signed packet

    # ----------------------------------------------------------- SETUP_SIGNING
    def setup(self, msg: mavlink.MAVLink_message) -> SetupResult:
        """Handle a SETUP_SIGNING that passed :meth:`check`."""
        result = self._setup(msg)
        self.setups[result] += 1
        level = logging.INFO if result is not SetupResult.NOT_ADDRESSED else logging.DEBUG
        logger.log(
            level,
            "vehicle %d: SETUP_SIGNING from %d/%d: %s",
            self.sysid,
            msg.get_srcSystem(),
            msg.get_srcComponent(),
            result.value,
        )
        return result

    def _setup(self, msg: mavlink.MAVLink_message) -> SetupResult:
        if not (
            msg.target_system == 0
            or (msg.target_system == self.sysid and msg.target_component in (0, self.compid))
        ):
            return SetupResult.NOT_ADDRESSED
        if self._is_armed():
            return SetupResult.REJECTED_ARMED
        requested = SigningKey(bytes(msg.secret_key), msg.initial_timestamp)
        if not requested.enabled:
            if self._key is None:
                return SetupResult.SIGNING_DISABLED
            buf = msg.get_msgbuf()
            if not (buf[0] == mavlink.PROTOCOL_MARKER_V2 and buf[2] & mavlink.MAVLINK_IFLAG_SIGNED):
                return SetupResult.BLANK_KEY_REJECTED
            try:
                self._store.save(self.sysid, BLANK_KEY)
            except OSError:
                logger.exception("vehicle %d: cannot store the signing state", self.sysid)
                return SetupResult.STORAGE_ERROR
            self._apply(BLANK_KEY)
            return SetupResult.SIGNING_DISABLED
        try:
            self._provision(requested)
        except OSError:
            logger.exception("vehicle %d: cannot store the signing key", self.sysid)
            return SetupResult.STORAGE_ERROR
        return SetupResult.KEY_ACCEPTED

    def _provision(self, requested: SigningKey) -> None:
        """Store and use ``requested``, its timestamp never behind what the same key already
        used (in memory or stored) nor behind the host clock (PX4: reconcile_and_replace)."""
        stamp = requested.timestamp
        if self._key == requested.key:
            stamp = max(stamp, self.timestamp)
        stored = self._store.load(self.sysid)
        if stored is not None and stored.key == requested.key:
            stamp = max(stamp, stored.timestamp)
        state = SigningKey(requested.key, max(stamp, self._now()))
        self._store.save(self.sysid, state)
        self._apply(state)

    def checkpoint(self) -> None:
        """Store the current timestamp if it is ahead of the stored one for the same key
        (PX4 does so on a clean shutdown, so a restart does not reuse timestamps)."""
        key = self._key
        if key is None:
            return
        stored = self._store.load(self.sysid)
        if stored is None or stored.key != key:
            return
        stamp = max(self.timestamp, self._now())
        if stamp > stored.timestamp:
            try:
                self._store.save(self.sysid, SigningKey(key, stamp))
            except OSError:
                logger.exception("vehicle %d: cannot store the signing timestamp", self.sysid)

"""MAVLink v2 framing by hand for the range aid's two hot messages: HIL_STATE_QUATERNION read from
a simulator's ground-truth datagrams (400 per second for four instances) and the vision ODOMETRY
sent back. pymavlink's generic parser and packer cost most of the aid's CPU; the layouts, message
ids and CRC extras here are pymavlink's own (its message classes), only the per-frame work is
done once instead of on every frame.

A frame (v2): magic, payload length, incompat flags, compat flags, sequence, system, component,
24-bit message id, the payload with its trailing zeros cut, a CRC-16/MCRF4XX over everything
after the magic plus the message's CRC extra, then, if signed, a 13-byte signature.
"""

from __future__ import annotations

import math
import operator
import struct
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from pymavlink.dialects.v20 import common as mavlink

_HIL = mavlink.MAVLink_hil_state_quaternion_message
_ODOMETRY = mavlink.MAVLink_odometry_message
_V1 = mavlink.PROTOCOL_MARKER_V1
_V2 = mavlink.PROTOCOL_MARKER_V2
_V1_HEADER_BYTES = mavlink.HEADER_LEN_V1
_V2_HEADER_BYTES = mavlink.HEADER_LEN_V2
_SIGNED = mavlink.MAVLINK_IFLAG_SIGNED
_SIGNATURE_BYTES = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN
#: magic, length, incompat flags, compat flags, seq, system, component, id low 16, id high 8.
_V2_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")
_CRC_BYTES = _CRC.size
#: struct's codes of the MAVLink types the aid packs itself.
_STRUCT_CODES = {"uint64_t": "Q", "float": "f"}


def _crc_with_fastcrc(data: Any, extra: bytes) -> int:
    return int(mavlink.mcrf4xx(extra, mavlink.mcrf4xx(data, 0xFFFF)))


def _crc_in_python(data: Any, extra: bytes) -> int:
    crc = mavlink.x25crc(bytes(data))
    crc.accumulate(extra)
    return int(crc.crc)


#: MAVLink's X.25 CRC over ``data`` then the CRC extra byte(s) ``extra``: pymavlink's own helper,
#: fastcrc's C code when installed (as pymavlink uses it).
x25_crc: Callable[[Any, bytes], int] = (
    _crc_with_fastcrc if mavlink.mcrf4xx is not None else _crc_in_python
)


def _flat_index(message_class: Any, name: str) -> int:
    """Where field ``name`` starts in the values of ``message_class``'s payload struct (wire
    order, arrays flattened)."""
    index = 0
    for field, length in zip(message_class.ordered_fieldnames, message_class.lengths, strict=True):
        if field == name:
            return int(index)
        index += length
    raise KeyError(name)


class TruthState(NamedTuple):
    """What the aid reads of a HIL_STATE_QUATERNION, in its MAVLink units."""

    lat: int  # degE7
    lon: int  # degE7
    alt: int  # mm
    vx: int  # cm/s, north
    vy: int  # cm/s, east
    vz: int  # cm/s, down
    attitude_quaternion: tuple[float, float, float, float]  # w, x, y, z


_HIL_PICK = operator.itemgetter(*(_flat_index(_HIL, name) for name in TruthState._fields[:-1]))
_HIL_QUATERNION = _flat_index(_HIL, "attitude_quaternion")


class TruthDecoder:
    """HIL_STATE_QUATERNION frames of one system from whole datagrams. Counts in ``malformed``
    what is not acted on: frames cut short, with a bad CRC or unknown incompat flags, of another
    system (never mixed with this one's), and bytes where a frame should start (the rest of that
    datagram is dropped: UDP carries whole frames). Other messages and MAVLink v1 frames are
    skipped by their length, unread."""

    def __init__(self, system_id: int) -> None:
        self.system_id = system_id
        self.malformed = 0
        self._extra = bytes([_HIL.crc_extra])
        self._payload_bytes = _HIL.unpacker.size

    def states(self, data: bytes) -> list[TruthState]:
        """The datagram's HIL_STATE_QUATERNION of this system, in order."""
        found: list[TruthState] = []
        offset, end = 0, len(data)
        while offset < end:
            magic = data[offset]
            if magic == _V2:
                offset = self._v2_frame(data, offset, found)
            elif magic == _V1 and offset + 1 < end:
                offset += _V1_HEADER_BYTES + data[offset + 1] + _CRC_BYTES
                if offset > end:
                    self.malformed += 1  # cut short
            else:
                self.malformed += 1
                break
        return found

    def _v2_frame(self, data: bytes, start: int, found: list[TruthState]) -> int:
        """Read the v2 frame at ``start`` into ``found`` if it is one to keep; returns where the
        next frame starts (past the end: stop)."""
        if len(data) - start < _V2_HEADER_BYTES + _CRC_BYTES:
            self.malformed += 1
            return len(data)
        _, length, incompat, _, _, system, _, id_low, id_high = _V2_HEADER.unpack_from(data, start)
        crc_at = start + _V2_HEADER_BYTES + length
        following = crc_at + _CRC_BYTES + (_SIGNATURE_BYTES if incompat & _SIGNED else 0)
        if following > len(data) or incompat & ~_SIGNED:
            self.malformed += 1
            return following
        if id_low | id_high << 16 != _HIL.id:
            return following
        view = memoryview(data)
        if x25_crc(view[start + 1 : crc_at], self._extra) != _CRC.unpack_from(data, crc_at)[0]:
            self.malformed += 1
            return following
        if system != self.system_id:
            self.malformed += 1  # another instance's stream on this port: never mix them
            return following
        payload = bytes(view[start + _V2_HEADER_BYTES : crc_at])
        missing = self._payload_bytes - length
        # Trailing zeros are cut on the wire; longer payloads carry extensions this one has not.
        payload = payload + bytes(missing) if missing > 0 else payload[: self._payload_bytes]
        values = _HIL.unpacker.unpack(payload)
        quaternion = values[_HIL_QUATERNION : _HIL_QUATERNION + 4]
        found.append(TruthState._make([*_HIL_PICK(values), quaternion]))
        return following


def _diagonal_covariance(linear: float, angular: float) -> list[float]:
    """MAVLink's upper-triangular 6x6 covariance: ``linear`` on the x, y, z diagonal entries,
    ``angular`` on the three rotations', the rest unknown (NaN)."""
    covariance = [math.nan] * 21
    for index in (0, 6, 11):
        covariance[index] = linear
    for index in (15, 18, 20):
        covariance[index] = angular
    return covariance


class OdometryFrames:
    """ODOMETRY frames (local NED, a VIO's) of one sender whose covariances never change: the
    payload's constant part (no angular rates, the covariances, frames, estimator type) is packed
    once; each frame packs the values that change (time zero: the receiver stamps it) in front of
    it and counts its sequence number up."""

    #: The fields each frame gives, in wire order, ahead of every constant one.
    CHANGING = ("time_usec", "x", "y", "z", "q", "vx", "vy", "vz")
    UNKNOWN = ("rollspeed", "pitchspeed", "yawspeed")

    def __init__(
        self,
        system_id: int,
        component_id: int,
        *,
        position_variance_m2: float,
        attitude_variance_rad2: float,
        velocity_variance_m2_s2: float,
    ) -> None:
        constant: dict[str, Any] = {
            "pose_covariance": _diagonal_covariance(position_variance_m2, attitude_variance_rad2),
            "velocity_covariance": _diagonal_covariance(velocity_variance_m2_s2, math.nan),
            "frame_id": mavlink.MAV_FRAME_LOCAL_NED,
            "child_frame_id": mavlink.MAV_FRAME_LOCAL_NED,
            "reset_counter": 0,
            "estimator_type": mavlink.MAV_ESTIMATOR_TYPE_VIO,
            "quality": 100,
        } | dict.fromkeys(self.UNKNOWN, math.nan)
        fields = list(_ODOMETRY.ordered_fieldnames)
        if fields[: len(self.CHANGING)] != list(self.CHANGING):
            raise RuntimeError(f"pymavlink's ODOMETRY has another layout: {fields}")
        tail = [
            value
            for name in fields[len(self.CHANGING) :]
            for value in (constant[name] if isinstance(constant[name], list) else [constant[name]])
        ]
        types = dict(zip(_ODOMETRY.fieldnames, _ODOMETRY.fieldtypes, strict=True))
        lengths = dict(zip(fields, _ODOMETRY.lengths, strict=True))
        self._changing = struct.Struct(
            "<" + "".join(f"{lengths[n]}{_STRUCT_CODES[types[n]]}" for n in self.CHANGING)
        )
        changing_zeros = [0] * sum(lengths[n] for n in self.CHANGING)
        self._constant = _ODOMETRY.unpacker.pack(*changing_zeros, *tail)[self._changing.size :]
        self._ids = (system_id, component_id, _ODOMETRY.id & 0xFFFF, _ODOMETRY.id >> 16)
        self._extra = bytes([_ODOMETRY.crc_extra])
        self.seq = 0

    def frame(
        self,
        position_m: Sequence[float],
        quaternion: Sequence[float],
        velocity_m_s: Sequence[float],
    ) -> bytes:
        """The next frame: ``position_m`` and ``velocity_m_s`` NED, ``quaternion`` w, x, y, z."""
        payload = self._changing.pack(0, *position_m, *quaternion, *velocity_m_s) + self._constant
        # MAVLink 2 cuts the payload's trailing zeros, keeping at least one byte.
        payload = payload.rstrip(b"\0") or payload[:1]
        system, component, id_low, id_high = self._ids
        header = _V2_HEADER.pack(
            _V2, len(payload), 0, 0, self.seq, system, component, id_low, id_high
        )
        self.seq = (self.seq + 1) & 0xFF
        body = header + payload
        return body + _CRC.pack(x25_crc(memoryview(body)[1:], self._extra))

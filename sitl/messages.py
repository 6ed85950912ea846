"""MAVLink messages PX4 sends that pymavlink's ``common`` dialect does not define.

pymavlink 2.4.50 generates ``common`` from a MAVLink definition in which PROTOCOL_VERSION (300)
is no longer part of ``common`` (nor of any dialect it ships), while PX4 still answers
MAV_CMD_REQUEST_PROTOCOL_VERSION and REQUEST_MESSAGE(300) with it. The class here is written the
way pymavlink generates its own, so a vehicle link encodes it like any other message (and a
pymavlink parser that has it in its ``mavlink_map`` decodes and checks it). A plain pymavlink
receiver decodes it as ``UNKNOWN_300``; :func:`decode_protocol_version` reads that one's payload.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import ClassVar

from pymavlink.dialects.v20 import common as mavlink

MAVLINK_MSG_ID_PROTOCOL_VERSION = 300


class MAVLinkProtocolVersionMessage(mavlink.MAVLink_message):
    """PROTOCOL_VERSION: the MAVLink versions a component speaks (id 300, CRC extra 217).

    ``version``, ``min_version`` and ``max_version`` are 100 x the protocol version (200 for
    MAVLink 2); the hashes are the first 8 bytes of the spec's and the library's git hashes.
    """

    id = MAVLINK_MSG_ID_PROTOCOL_VERSION
    msgname = "PROTOCOL_VERSION"
    fieldnames: ClassVar[list[str]] = [
        "version",
        "min_version",
        "max_version",
        "spec_version_hash",
        "library_version_hash",
    ]
    ordered_fieldnames: ClassVar[list[str]] = fieldnames
    fieldtypes: ClassVar[list[str]] = ["uint16_t", "uint16_t", "uint16_t", "uint8_t", "uint8_t"]
    orders: ClassVar[list[int]] = [0, 1, 2, 3, 4]
    lengths: ClassVar[list[int]] = [1, 1, 1, 8, 8]
    array_lengths: ClassVar[list[int]] = [0, 0, 0, 8, 8]
    crc_extra = 217
    unpacker = struct.Struct("<HHH8B8B")

    def __init__(
        self,
        version: int,
        min_version: int,
        max_version: int,
        spec_version_hash: Sequence[int] = (0,) * 8,
        library_version_hash: Sequence[int] = (0,) * 8,
    ) -> None:
        mavlink.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = self.fieldnames
        self.version = version
        self.min_version = min_version
        self.max_version = max_version
        self.spec_version_hash = list(spec_version_hash)
        self.library_version_hash = list(library_version_hash)

    def pack(self, mav: mavlink.MAVLink, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(
            self.version,
            self.min_version,
            self.max_version,
            *self.spec_version_hash,
            *self.library_version_hash,
        )
        packed: bytes = self._pack(mav, self.crc_extra, payload, force_mavlink1=force_mavlink1)
        return packed


def decode_protocol_version(payload: bytes) -> MAVLinkProtocolVersionMessage:
    """PROTOCOL_VERSION from its MAVLink 2 payload (trailing zeros may have been trimmed)."""
    size = MAVLinkProtocolVersionMessage.unpacker.size
    fields = MAVLinkProtocolVersionMessage.unpacker.unpack(payload[:size].ljust(size, b"\0"))
    version, min_version, max_version = fields[:3]
    return MAVLinkProtocolVersionMessage(
        version, min_version, max_version, fields[3:11], fields[11:19]
    )

"""The ULog file format PX4's logger writes (``.ulg``), as far as a flight log needs it.

A ULog file is a 16-byte header (magic, version, start timestamp) and a stream of messages,
each ``uint16 size, uint8 type, payload``: first the definitions (flag bits, message formats,
information, parameters), then subscriptions ('A'), data ('D'), logged strings ('L') and sync
markers ('S'). :class:`ULogWriter` appends them to a ``bytearray`` that can be read while it
grows; pyulog, PX4's Flight Review and QGroundControl read the result. Field layout is packed
(no padding), little-endian, in the order of the format.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field

MAGIC = b"ULog\x01\x12\x35"
VERSION = 1
SYNC_MAGIC = bytes([0x2F, 0x73, 0x13, 0x20, 0x25, 0x0C, 0xBB, 0x12])

_TYPES: dict[str, str] = {
    "int8_t": "b",
    "uint8_t": "B",
    "int16_t": "h",
    "uint16_t": "H",
    "int32_t": "i",
    "uint32_t": "I",
    "int64_t": "q",
    "uint64_t": "Q",
    "float": "f",
    "double": "d",
    "bool": "?",
    "char": "c",
}
_FIELD = re.compile(r"^(\w+)(?:\[(\d+)\])?$")
_HEADER = struct.Struct("<HB")
_DATA = ord("D")


@dataclass(frozen=True, slots=True)
class Topic:
    """A logged message: ``fields`` as (ULog type, name) pairs, e.g. ("float[4]", "q"); the
    first field is ``uint64_t timestamp``, as ULog requires."""

    name: str
    fields: tuple[tuple[str, str], ...]
    packer: struct.Struct = field(init=False, repr=False, compare=False)
    data_message: struct.Struct = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.fields[:1] != (("uint64_t", "timestamp"),):
            raise ValueError(f"{self.name}: the first field must be 'uint64_t timestamp'")
        codes = "<"
        for kind, _ in self.fields:
            match = _FIELD.match(kind)
            if match is None or match.group(1) not in _TYPES:
                raise ValueError(f"{self.name}: unknown ULog type {kind!r}")
            codes += (match.group(2) or "") + _TYPES[match.group(1)]
        object.__setattr__(self, "packer", struct.Struct(codes))
        # A whole data message: header (size, 'D'), message id, then the fields.
        object.__setattr__(self, "data_message", struct.Struct("<HBH" + codes[1:]))

    @property
    def format(self) -> str:
        return f"{self.name}:" + "".join(f"{kind} {name};" for kind, name in self.fields)


class ULogWriter:
    """Builds one ULog file in ``data``; write the definitions, then :meth:`subscribe` and
    :meth:`write` data. Timestamps are microseconds of the vehicle's boot clock."""

    def __init__(self, start_timestamp_us: int) -> None:
        self.data = bytearray(MAGIC + struct.pack("<BQ", VERSION, start_timestamp_us))
        # Flag bits ('B') must come first: no compatibility flags, no appended data.
        self._message(b"B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
        self._topics: dict[str, Topic] = {}
        self._subscribed: dict[str, tuple[struct.Struct, int, int]] = {}

    def _message(self, kind: bytes, payload: bytes) -> None:
        self.data += _HEADER.pack(len(payload), kind[0])
        self.data += payload

    # ------------------------------------------------------------------ definitions
    def format(self, topic: Topic) -> None:
        self._topics[topic.name] = topic
        self._message(b"F", topic.format.encode())

    def info(self, key: str, value: str | int | float) -> None:
        """An information message: strings as char[n], ints as int32_t/uint32_t, floats."""
        if isinstance(value, str):
            raw = value.encode()
            typed = f"char[{len(raw)}] {key}"
        elif isinstance(value, int):
            signed = value < 0
            raw = struct.pack("<i" if signed else "<I", value)
            typed = f"{'int32_t' if signed else 'uint32_t'} {key}"
        else:
            raw = struct.pack("<f", value)
            typed = f"float {key}"
        self._message(b"I", bytes([len(typed)]) + typed.encode() + raw)

    def parameter(self, name: str, value: float, integer: bool) -> None:
        if integer:
            typed, raw = f"int32_t {name}", struct.pack("<i", int(value))
        else:
            typed, raw = f"float {name}", struct.pack("<f", value)
        self._message(b"P", bytes([len(typed)]) + typed.encode() + raw)

    # ------------------------------------------------------------------ data
    def subscribe(self, topic_name: str, multi_id: int = 0) -> None:
        if topic_name not in self._topics:
            raise ValueError(f"no format for {topic_name!r}: call format() first")
        msg_id = len(self._subscribed)
        topic = self._topics[topic_name]
        self._subscribed[topic_name] = (topic.data_message, topic.packer.size + 2, msg_id)
        self._message(b"A", struct.pack("<BH", multi_id, msg_id) + topic_name.encode())

    def write(self, topic_name: str, values: Sequence[float | int | bool]) -> None:
        """One sample of ``topic_name``: the field values in order, arrays flattened."""
        message, size, msg_id = self._subscribed[topic_name]
        self.data += message.pack(size, _DATA, msg_id, *values)

    def log(self, level: int, timestamp_us: int, text: str) -> None:
        """A logged string; ``level`` 0 (emergency) to 7 (debug), as MAV_SEVERITY."""
        self._message(b"L", struct.pack("<BQ", ord("0") + level, timestamp_us) + text.encode())

    def sync(self) -> None:
        self._message(b"S", SYNC_MAGIC)

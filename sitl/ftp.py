"""MAVLink FTP (FILE_TRANSFER_PROTOCOL) as PX4 serves it, over a small read-only file system.

PX4's MavlinkFTP (src/modules/mavlink/mavlink_ftp.cpp) runs one server per MAVLink link with a
single session; :class:`FtpServer` is that server for one link of one vehicle:

- reading: list directory, open read-only, read, burst read (a stream of data packets that ends
  with burst_complete after ~35 kB or with a NAK EOF at the end of the file, as PX4 sends it),
  terminate session, reset sessions, calc CRC32 (PX4's CRC: no initial or final inversion);
- a request whose sequence number is that of the last one gets the last (small) reply again;
- an idle session closes after 10 s, as on PX4;
- the file system is read-only: the write operations are NAKed FILE_PROTECTED, unknown opcodes
  UNKNOWN_COMMAND, like PX4 answers what it cannot do.

The files are a :class:`Directory` tree whose listings and contents are produced on demand (the
vehicle's flight logs change while it flies) plus *special files* such as ArduPilot's
``@PARAM/param.pck`` that take a query string. A file's content is fixed when it is opened, as
PX4 reads a file whose size it took when opening it.
"""

from __future__ import annotations

import enum
import logging
import struct
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as mavlink

from sitl.vehicle_state import Link

logger = logging.getLogger(__name__)

#: FILE_TRANSFER_PROTOCOL.payload length and the data that fits after the 12-byte header.
PAYLOAD_BYTES = 251
MAX_DATA_BYTES = PAYLOAD_BYTES - 12
#: PX4 ends a burst after this many bytes (when its transmit buffer runs low, which on a
#: UDP link of PX4 SITL happens a few kB later: measured 168 packets, 40 kB).
BURST_BYTES = 35_000
#: PX4 closes a session nobody has used for this long, s.
SESSION_TIMEOUT_S = 10.0

_HEADER = struct.Struct("<HBBBBBxI")


class Opcode(enum.IntEnum):
    """FTP opcodes (PayloadHeader.opcode)."""

    NONE = 0
    TERMINATE_SESSION = 1
    RESET_SESSIONS = 2
    LIST_DIRECTORY = 3
    OPEN_FILE_RO = 4
    READ_FILE = 5
    CREATE_FILE = 6
    WRITE_FILE = 7
    REMOVE_FILE = 8
    CREATE_DIRECTORY = 9
    REMOVE_DIRECTORY = 10
    OPEN_FILE_WO = 11
    TRUNCATE_FILE = 12
    RENAME = 13
    CALC_FILE_CRC32 = 14
    BURST_READ_FILE = 15
    ACK = 128
    NAK = 129


class FtpError(enum.IntEnum):
    """Error codes of a NAK (its first data byte)."""

    NONE = 0
    FAIL = 1
    FAIL_ERRNO = 2
    INVALID_DATA_SIZE = 3
    INVALID_SESSION = 4
    NO_SESSIONS_AVAILABLE = 5
    EOF = 6
    UNKNOWN_COMMAND = 7
    FILE_EXISTS = 8
    FILE_PROTECTED = 9
    FILE_NOT_FOUND = 10


_WRITE_OPCODES = frozenset(
    [
        Opcode.CREATE_FILE,
        Opcode.WRITE_FILE,
        Opcode.REMOVE_FILE,
        Opcode.CREATE_DIRECTORY,
        Opcode.REMOVE_DIRECTORY,
        Opcode.OPEN_FILE_WO,
        Opcode.TRUNCATE_FILE,
        Opcode.RENAME,
    ]
)


@dataclass(slots=True)
class FtpPayload:
    """FILE_TRANSFER_PROTOCOL.payload: PX4's packed PayloadHeader and its data."""

    seq_number: int
    session: int
    opcode: int
    size: int
    req_opcode: int = 0
    burst_complete: int = 0
    offset: int = 0
    data: bytes = b""

    @classmethod
    def unpack(cls, payload: bytes | list[int]) -> FtpPayload:
        raw = bytes(payload).ljust(PAYLOAD_BYTES, b"\0")
        seq, session, opcode, size, req_opcode, burst_complete, offset = _HEADER.unpack_from(raw)
        return cls(
            seq, session, opcode, size, req_opcode, burst_complete, offset, raw[12:PAYLOAD_BYTES]
        )

    def pack(self) -> list[int]:
        header = _HEADER.pack(
            self.seq_number & 0xFFFF,
            self.session,
            self.opcode,
            self.size,
            self.req_opcode,
            self.burst_complete,
            self.offset,
        )
        return list((header + self.data[: self.size]).ljust(PAYLOAD_BYTES, b"\0"))

    def text(self) -> str:
        """The data as PX4's _data_as_cstring reads it: up to ``size`` bytes, up to a NUL."""
        return (
            self.data[: min(self.size, MAX_DATA_BYTES - 1)]
            .split(b"\0", 1)[0]
            .decode("utf-8", errors="replace")
        )


def px4_crc32(data: bytes, crc: int = 0) -> int:
    """PX4's crc32part: the reflected CRC-32 table without initial or final inversion."""
    return ~zlib.crc32(data, ~crc & 0xFFFFFFFF) & 0xFFFFFFFF


# ---------------------------------------------------------------------- the file system
@dataclass(frozen=True, slots=True)
class File:
    """A file whose ``content()`` is produced when it is listed or opened."""

    content: Callable[[], bytes]


@dataclass(frozen=True, slots=True)
class Directory:
    """A directory whose ``entries()`` (name -> file or directory) are listed on demand."""

    entries: Callable[[], Mapping[str, File | Directory]]


def static_directory(entries: Mapping[str, File | Directory]) -> Directory:
    return Directory(lambda: entries)


@dataclass(slots=True)
class FileSystem:
    """What :class:`FtpServer` serves: ``root`` and special files by exact path (before a
    ``?query``), whose content depends on the query (``@PARAM/param.pck?withdefaults=1``)."""

    root: Directory = field(default_factory=lambda: static_directory({}))
    special: dict[str, Callable[[str], bytes]] = field(default_factory=dict)

    def resolve(self, path: str) -> File | Directory | None:
        node: File | Directory = self.root
        for part in path.split("/"):
            if part in ("", "."):
                continue
            if not isinstance(node, Directory):
                return None
            child = node.entries().get(part)
            if child is None:
                return None
            node = child
        return node

    def read(self, path: str) -> bytes | None:
        """The content of the file at ``path`` (special files included), None if none."""
        name, _, query = path.partition("?")
        special = self.special.get(name.lstrip("/"))
        if special is not None:
            return special(query)
        node = self.resolve(name)
        return node.content() if isinstance(node, File) else None


# ---------------------------------------------------------------------- the server
@dataclass(slots=True)
class _Session:
    number: int
    content: bytes
    last_used_s: float


class FtpServer:
    """PX4's FTP server of one link of vehicle ``sysid`` (component ``compid``), over
    ``files``; ``now_s()`` is the simulated time (for the session timeout).

    PX4 answers every open with session 0 and takes reads for session 0 only;
    ``echo_session`` keeps the number the client chose instead, as ArduPilot does (MAVProxy
    numbers its sessions at random and ignores replies for another one).
    """

    def __init__(
        self,
        files: FileSystem,
        *,
        sysid: int,
        compid: int = 1,
        now_s: Callable[[], float] = lambda: 0.0,
        echo_session: bool = False,
    ) -> None:
        self._files = files
        self._sysid = sysid
        self._compid = compid
        self._now_s = now_s
        self._echo_session = echo_session
        self._session: _Session | None = None
        self._last_reply: FtpPayload | None = None

    def handle(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        """Answer one FILE_TRANSFER_PROTOCOL message received on ``link``."""
        if msg.target_system not in (0, self._sysid) or msg.target_component not in (
            0,
            self._compid,
        ):
            return
        now = self._now_s()
        session = self._session
        if session is not None and now - session.last_used_s > SESSION_TIMEOUT_S:
            logger.info("vehicle %d: FTP session closed without activity", self._sysid)
            self._session = None
            self._last_reply = None
        request = FtpPayload.unpack(msg.payload)
        target = (msg.get_srcSystem(), msg.get_srcComponent())
        last = self._last_reply
        if last is not None and (request.seq_number + 1) & 0xFFFF == last.seq_number:
            # The reply got lost and the client asks again: the same answer, not the same work.
            self._send(link, target, last)
            return
        if self._session is not None:
            self._session.last_used_s = now
        self._last_reply = None
        reply: FtpPayload | None
        if request.size > MAX_DATA_BYTES:
            reply = self._nak(request, FtpError.INVALID_DATA_SIZE)
        else:
            reply = self._work(request, link, target)
        if reply is None:  # a burst: its packets are sent
            return
        if reply.size <= 4 and not (
            reply.opcode == Opcode.NAK and reply.data[:1] == bytes([FtpError.NO_SESSIONS_AVAILABLE])
        ):
            self._last_reply = reply
        self._send(link, target, reply)

    # ------------------------------------------------------------------ opcodes
    def _work(self, request: FtpPayload, link: Link, target: tuple[int, int]) -> FtpPayload | None:
        opcode = request.opcode
        if opcode == Opcode.NONE:
            return self._ack(request, size=0)
        if opcode == Opcode.TERMINATE_SESSION:
            if self._session is None or request.session != self._session.number:
                return self._nak(request, FtpError.INVALID_SESSION)
            self._session = None
            return self._ack(request, size=0)
        if opcode == Opcode.RESET_SESSIONS:
            self._session = None
            return self._ack(request, size=0)
        if opcode == Opcode.LIST_DIRECTORY:
            return self._list(request)
        if opcode == Opcode.OPEN_FILE_RO:
            return self._open(request)
        if opcode == Opcode.READ_FILE:
            return self._read(request)
        if opcode == Opcode.BURST_READ_FILE:
            if self._session is None or request.session != self._session.number:
                return self._nak(request, FtpError.INVALID_SESSION)
            self._burst(request, link, target)
            return None
        if opcode == Opcode.CALC_FILE_CRC32:
            content = self._files.read(request.text())
            if content is None:
                return self._nak(request, FtpError.FILE_NOT_FOUND)
            return self._ack(request, struct.pack("<I", px4_crc32(content)))
        if opcode in _WRITE_OPCODES:
            return self._nak(request, FtpError.FILE_PROTECTED)
        return self._nak(request, FtpError.UNKNOWN_COMMAND)

    def _list(self, request: FtpPayload) -> FtpPayload:
        node = self._files.resolve(request.text())
        if not isinstance(node, Directory):
            return self._nak(request, FtpError.FILE_NOT_FOUND)
        entries = sorted(node.entries().items())[request.offset :]
        if not entries:
            return self._nak(request, FtpError.EOF)
        data = bytearray()
        for name, child in entries:
            if isinstance(child, File):
                entry = b"F" + f"{name}\t{len(child.content())}".encode()
            else:
                entry = b"D" + name.encode()
            if len(data) + len(entry) + 1 > MAX_DATA_BYTES:
                break
            data += entry + b"\0"
        return self._ack(request, bytes(data))

    def _open(self, request: FtpPayload) -> FtpPayload:
        if self._session is not None:
            return self._nak(request, FtpError.NO_SESSIONS_AVAILABLE)
        content = self._files.read(request.text())
        if content is None:
            return self._nak(request, FtpError.FILE_NOT_FOUND)
        number = request.session if self._echo_session else 0
        self._session = _Session(number, content, self._now_s())
        return self._ack(request, struct.pack("<I", len(content)), session=number)

    def _read(self, request: FtpPayload) -> FtpPayload:
        session = self._session
        if session is None or request.session != session.number:
            return self._nak(request, FtpError.INVALID_SESSION)
        if request.offset >= len(session.content):
            return self._nak(request, FtpError.EOF)
        end = request.offset + request.size
        return self._ack(request, session.content[request.offset : end])

    def _burst(self, request: FtpPayload, link: Link, target: tuple[int, int]) -> None:
        session = self._session
        assert session is not None
        content = session.content
        offset = request.offset
        seq = request.seq_number + 1
        sent = 0
        while True:
            packet = FtpPayload(
                seq, session.number, Opcode.ACK, 0, Opcode.BURST_READ_FILE, 0, offset, b""
            )
            seq += 1
            if offset >= len(content):
                # As PX4's stream: the data is followed by a NAK EOF at the end of the file.
                packet.opcode = Opcode.NAK
                packet.data = bytes([FtpError.EOF])
                packet.size = 1
                self._send(link, target, packet)
                return
            chunk = content[offset : offset + MAX_DATA_BYTES]
            packet.data, packet.size = chunk, len(chunk)
            offset += len(chunk)
            sent += len(chunk)
            if sent > BURST_BYTES and offset < len(content):
                packet.burst_complete = 1
                self._send(link, target, packet)
                return
            self._send(link, target, packet)

    # ------------------------------------------------------------------ replies
    @staticmethod
    def _ack(
        request: FtpPayload,
        data: bytes = b"",
        *,
        size: int | None = None,
        session: int | None = None,
    ) -> FtpPayload:
        return FtpPayload(
            request.seq_number + 1,
            request.session if session is None else session,
            Opcode.ACK,
            len(data) if size is None else size,
            request.opcode,
            0,
            request.offset,
            data,
        )

    @staticmethod
    def _nak(request: FtpPayload, error: FtpError) -> FtpPayload:
        return FtpPayload(
            request.seq_number + 1,
            request.session,
            Opcode.NAK,
            1,
            request.opcode,
            0,
            request.offset,
            bytes([error]),
        )

    def _send(self, link: Link, target: tuple[int, int], reply: FtpPayload) -> None:
        link.send(
            mavlink.MAVLink_file_transfer_protocol_message(0, target[0], target[1], reply.pack())
        )

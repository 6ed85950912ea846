"""MAVLink telemetry logs (.tlog) as QGroundControl and MAVProxy write them.

A .tlog is the raw MAVLink packets, each preceded by an 8-byte big-endian timestamp in
microseconds since the Unix epoch; pymavlink's ``mavutil.mavlink_connection("x.tlog")`` and
MAVExplorer read it. Both directions go into the same file, in the order they happened.
"""

from __future__ import annotations

import struct
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

_TIMESTAMP = struct.Struct(">Q")


class TlogWriter:
    """Appends timestamped packets to one file; a context manager that closes it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file: BinaryIO | None = None
        self.packets = 0

    def open(self) -> TlogWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("wb", buffering=64 * 1024)
        return self

    def write(self, timestamp_us: int, packet: bytes | bytearray) -> None:
        file = self._file
        if file is None:
            return
        file.write(_TIMESTAMP.pack(timestamp_us))
        file.write(packet)
        self.packets += 1

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> TlogWriter:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

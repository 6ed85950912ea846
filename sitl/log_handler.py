"""The MAVLink log protocol (LOG_REQUEST_LIST / DATA / END, LOG_ERASE) as PX4 answers it.

PX4's MavlinkLogHandler (src/modules/mavlink/mavlink_log_handler.cpp) runs one handler per
MAVLink link; :class:`LogHandler` is that handler for one link, over the vehicle's
:class:`sitl.flight_log.FlightLogStore`:

- LOG_REQUEST_LIST takes a snapshot of the logs (oldest first, id 0 first) and sends a
  LOG_ENTRY for every id from ``start`` on, with PX4's ``last_log_num`` (the number of logs when
  ``end`` is 0xFFFF, else ``end``). Without logs PX4 sends nothing at all, and neither does this.
- LOG_REQUEST_DATA sends LOG_DATA packets of 90 bytes from ``ofs`` until ``count`` bytes are
  covered or the file ends (a short count still gets a whole packet); only after a list, only
  for an id of that list and an offset inside the file, else nothing. Like PX4 it sends as much
  as its budget allows (:data:`BYTES_PER_PUMP` per call of :meth:`pump`, every autopilot step)
  and goes on from there.
- LOG_REQUEST_END stops sending; LOG_ERASE deletes every log.
"""

from __future__ import annotations

from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from sitl.flight_log import FlightLog, FlightLogStore
from sitl.vehicle_state import Link

#: LOG_DATA.data length.
LOG_DATA_BYTES = 90
#: Data sent per :meth:`LogHandler.pump` (PX4 sends up to 256 kB per pass of its loop, as far
#: as its transmit buffer takes it; 128 kB per 20 ms is 6.4 MB per simulated second).
BYTES_PER_PUMP = 128 * 1024


@dataclass(slots=True)
class _Transfer:
    link: Link
    log_id: int
    log: FlightLog
    offset: int
    end: int


class LogHandler:
    """PX4's log handler of one link of vehicle ``sysid`` over ``store``."""

    def __init__(self, store: FlightLogStore, *, sysid: int) -> None:
        self._store = store
        self._sysid = sysid
        self._listed: list[FlightLog] | None = None
        self._transfer: _Transfer | None = None

    @property
    def sending(self) -> bool:
        return self._transfer is not None

    def handle(self, msg: mavlink.MAVLink_message, link: Link) -> None:
        """Answer one LOG_* message received on ``link``."""
        if msg.target_system not in (0, self._sysid):
            return
        kind = msg.get_type()
        if kind == "LOG_REQUEST_LIST":
            self._list(msg.start, msg.end, link)
        elif kind == "LOG_REQUEST_DATA":
            self._request_data(msg.id, msg.ofs, msg.count, link)
        elif kind == "LOG_REQUEST_END":
            self._transfer = None
        elif kind == "LOG_ERASE":
            self._transfer = None
            self._store.erase()

    def pump(self) -> None:
        """Send what the running transfer still owes, up to :data:`BYTES_PER_PUMP`."""
        transfer = self._transfer
        if transfer is None:
            return
        data = transfer.log.data
        size = len(data)
        budget = BYTES_PER_PUMP
        while budget > 0:
            if transfer.offset >= size or transfer.offset >= transfer.end:
                self._transfer = None
                return
            chunk = bytes(data[transfer.offset : transfer.offset + LOG_DATA_BYTES])
            transfer.link.send(
                mavlink.MAVLink_log_data_message(
                    transfer.log_id,
                    transfer.offset,
                    len(chunk),
                    list(chunk.ljust(LOG_DATA_BYTES, b"\0")),
                )
            )
            transfer.offset += len(chunk)
            budget -= len(chunk)

    # ------------------------------------------------------------------ requests
    def _list(self, start: int, end: int, link: Link) -> None:
        logs = list(self._store.logs)
        self._listed = logs
        count = len(logs)
        last = count if end == 0xFFFF else end
        for log_id in range(start, count):
            log = logs[log_id]
            link.send(
                mavlink.MAVLink_log_entry_message(
                    log_id, count, last, log.time_utc_s & 0xFFFFFFFF, log.size
                )
            )

    def _request_data(self, log_id: int, offset: int, count: int, link: Link) -> None:
        listed = self._listed
        if listed is None or log_id >= len(listed):
            self._transfer = None
            return
        log = listed[log_id]
        if offset >= log.size:
            self._transfer = None
            return
        self._transfer = _Transfer(link, log_id, log, offset, offset + count)
        self.pump()

"""One MAVLink-over-UDP link of one vehicle (the API link or the GCS link).

:class:`VehicleLink` is an asyncio ``DatagramProtocol``: it decodes every datagram with its own
pymavlink parser, hands decoded messages to the vehicle synchronously, and batches what the
vehicle sends into datagrams (several packets per datagram, as PX4 does) that :meth:`flush`
sends. Like PX4 it sends to a configured address until the first valid MAVLink packet arrives
and answers that sender from then on.

Malformed input is counted and dropped (a decoder failure on it is also logged); an exception in
the vehicle's handler is logged and counted (``handler_errors``) but never stops the link.

With a :class:`sitl.signing.VehicleSigning` the link signs what it sends once the vehicle has a
key, refuses what the signing check refuses (counted in ``rx_rejected``; such packets neither
reach the vehicle nor the tlog nor make their sender the link's partner) and handles
SETUP_SIGNING itself, as PX4's MAVLink module does; SETUP_SIGNING carries the key in clear, so
it is not written to the tlog.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

from pymavlink.dialects.v20 import common as mavlink

from sitl.config import StreamRates
from sitl.signing import LINK_IDS, VehicleSigning
from sitl.telemetry import StreamScheduler
from sitl.tlog import TlogWriter

logger = logging.getLogger(__name__)

#: Bytes per datagram before a batch is sent (below a 1500-byte Ethernet MTU).
MAX_DATAGRAM_BYTES = 1400

Address = tuple[str, int]


class VehicleLink(asyncio.DatagramProtocol):
    """A vehicle's UDP endpoint: ``name`` is ``"api"`` or ``"gcs"``.

    ``deliver(msg, link)`` receives every valid decoded message; ``now_us()`` gives the tlog
    timestamp. ``streams`` holds this link's telemetry schedule (at most one message of a kind
    per physics step of ``step_s``). ``signing`` is the vehicle's
    signing state (shared by its links); the link signs with its PX4 link id.
    """

    def __init__(
        self,
        name: str,
        *,
        sysid: int,
        local_port: int,
        remote_address: Address,
        rates: StreamRates,
        deliver: Callable[[mavlink.MAVLink_message, VehicleLink], None],
        stream_phase_s: float = 0.0,
        step_s: float = 0.0,
        tlog: TlogWriter | None = None,
        now_us: Callable[[], int] = lambda: 0,
        signing: VehicleSigning | None = None,
    ) -> None:
        self.name = name
        self.sysid = sysid
        self.local_port = local_port
        self.remote_address = remote_address
        self.partner: Address | None = None
        self.streams = StreamScheduler(rates, stream_phase_s, step_s)
        self._deliver = deliver
        self._tlog = tlog
        self._now_us = now_us
        self.signing = signing
        self._link_id = LINK_IDS.get(name, 0)
        self._encoder = mavlink.MAVLink(self, srcSystem=sysid, srcComponent=1)
        self._parser = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self._parser.robust_parsing = True
        self._transport: asyncio.DatagramTransport | None = None
        self._buffer = bytearray()
        #: False while a fault drops this link: nothing in, nothing out.
        self.up = True
        #: False once the vehicle is dead.
        self.alive = True
        self.rx_datagrams = 0
        self.rx_packets = 0
        self.rx_bad = 0
        #: Datagrams the decoder raised on (also counted in ``rx_bad``).
        self.decoder_errors = 0
        self.tx_packets = 0
        self.handler_errors = 0
        #: Valid packets the signing check refused.
        self.rx_rejected = 0

    # ------------------------------------------------------------ receiving
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport  # type: ignore[assignment]

    def connection_lost(self, exc: Exception | None) -> None:
        self._transport = None

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable while no client listens: normal for a GCS link.
        logger.debug("vehicle %d %s link: %s", self.sysid, self.name, exc)

    def datagram_received(self, data: bytes, addr: Address) -> None:
        self.rx_datagrams += 1
        if not (self.up and self.alive):
            return
        parser = self._parser
        try:
            messages = parser.parse_buffer(data) or []
        except Exception:
            # Broad on purpose: this is where bytes from the network meet the decoder. With
            # robust parsing pymavlink turns what it knows to be malformed into BAD_DATA
            # messages, so anything raised here is a decoder failure on hostile input. Let
            # through, it would skip the parser reset below (the garbage would spoil the next
            # datagram) and show only as the event loop's anonymous "Exception in callback";
            # here it costs this datagram alone, counted and logged with its sender.
            messages = []
            self.rx_bad += 1
            self.decoder_errors += 1
            if self.decoder_errors == 1 or self.decoder_errors % 1000 == 0:
                logger.warning(
                    "vehicle %d %s link: the MAVLink decoder failed on a %d-byte datagram from "
                    "%s:%d (%d such datagram(s) dropped)",
                    self.sysid,
                    self.name,
                    len(data),
                    *addr[:2],
                    self.decoder_errors,
                    exc_info=True,
                )
        # A datagram holds whole packets: leftovers are garbage, do not let them eat the next.
        parser.buf = bytearray()
        parser.buf_index = 0
        parser.expected_length = mavlink.HEADER_LEN_V1 + 2
        signing = self.signing
        for msg in messages:
            if msg.get_msgId() < 0:  # BAD_DATA
                self.rx_bad += 1
                continue
            if signing is not None and not signing.check(msg).accepted:
                self.rx_rejected += 1
                continue
            self.rx_packets += 1
            if self.partner is None:
                self.partner = (addr[0], addr[1])
                logger.info(
                    "vehicle %d %s link: client at %s:%d", self.sysid, self.name, *self.partner
                )
            if signing is not None and msg.get_msgId() == mavlink.MAVLINK_MSG_ID_SETUP_SIGNING:
                signing.setup(msg)
                continue
            if self._tlog is not None:
                self._tlog.write(self._now_us(), msg.get_msgbuf())
            try:
                self._deliver(msg, self)
            except Exception:
                # Broad on purpose, as above: a message that trips the vehicle's handler (an
                # emulator bug, likely on odd input) must cost that message alone, not the rest
                # of the datagram or the replies flushed below. Counted, so tests that expect
                # none (handler_errors == 0) still catch such bugs.
                self.handler_errors += 1
                logger.exception(
                    "vehicle %d %s link: error handling %s", self.sysid, self.name, msg.get_type()
                )
        self.flush()

    # -------------------------------------------------------------- sending
    def send(self, msg: mavlink.MAVLink_message) -> None:
        """Queue ``msg`` for the next :meth:`flush` (encoded with this link's sequence)."""
        if self.up and self.alive:
            if self.signing is None:
                self._encoder.send(msg)
            else:
                self.signing.send(self._encoder, msg, self._link_id)

    def write(self, packet: bytes) -> None:
        """pymavlink's encoder writes packed messages here."""
        if len(self._buffer) + len(packet) > MAX_DATAGRAM_BYTES:
            self.flush()
        self._buffer += packet
        self.tx_packets += 1
        if self._tlog is not None:
            self._tlog.write(self._now_us(), packet)

    @property
    def pending(self) -> bool:
        return bool(self._buffer)

    def flush(self) -> None:
        """Send the queued packets as one datagram."""
        if not self._buffer:
            return
        transport = self._transport
        if transport is not None:
            transport.sendto(bytes(self._buffer), self.partner or self.remote_address)
        self._buffer.clear()

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()

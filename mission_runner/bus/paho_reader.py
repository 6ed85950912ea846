"""How an MQTT client reads its socket: oversized packets skipped unread, small ones in batches.

paho reads a packet's whole remaining length before anyone sees it, with ``recv(remaining)``
calls that each allocate a buffer of what is left (64 MiB for a 64 MiB payload) and append to
one growing buffer, inside the event loop that also runs the vehicle's controller: four 64 MiB
payloads on the control topic stalled three vehicles of four until they were declared lost.
:func:`skip_oversized_packets` makes a client look at each packet's length first and skip
packets over the limit straight from the socket into a small scratch buffer, a bounded number of
bytes per event-loop turn, so that a huge packet costs the loop no more than a few small ones.

aiomqtt has paho read one packet per event-loop turn. A turn costs far more than parsing a small
packet (a poll, every ready callback, and the GIL handed back and forth with MAVSDK's threads), so
a flood of 40,000 small payloads took a vehicle process about 40 s to read (measured: ~1,000 a
second), and messages behind it on the same connection came seconds late. The guarded reader
goes on with the packets already waiting, up to ``packets_per_turn``, so a flood is read at the
speed of parsing, and no turn is longer than that many packets.

This relies on paho-mqtt 2.x's reader (``_packet_read``, ``_sock_recv``, ``_in_packet``); the
check is made when a client is built, and a paho without them is refused at once rather than
left unguarded.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from paho.mqtt.enums import MQTTErrorCode

from mission_runner.bus.errors import BusConnectionError

#: Bytes skipped per read call (one event-loop turn): 16 chunks of 64 KiB.
SKIP_CHUNK_BYTES = 64 * 1024
SKIP_CHUNKS_PER_TURN = 16
#: Packets read per event-loop turn at most (a few milliseconds of parsing).
PACKETS_PER_TURN = 64
_SUCCESS = MQTTErrorCode.MQTT_ERR_SUCCESS
#: What an MQTT PUBLISH adds to its payload: fixed header (up to 5 bytes), topic (ours are
#: under 200 bytes) and packet id.
PUBLISH_OVERHEAD_BYTES = 1024


def max_packet_bytes(max_message_bytes: int) -> int:
    """The longest MQTT packet that can carry a message of ``max_message_bytes`` (sealed): the
    client skips longer ones unread, and ``broker-config``'s broker refuses them."""
    return max_message_bytes + PUBLISH_OVERHEAD_BYTES


#: What paho's reader holds between packets (``paho.mqtt.client.Client._packet_read``).
_PAHO_READER = ("_packet_read", "_sock_recv", "_in_packet", "_sock", "on_message")


def _fresh_packet() -> dict[str, Any]:
    return {
        "command": 0,
        "have_remaining": 0,
        "remaining_count": [],
        "remaining_mult": 1,
        "remaining_length": 0,
        "packet": bytearray(b""),
        "to_process": 0,
        "pos": 0,
    }


def guard_reader(
    paho_client: Any,
    max_packet_bytes: int,
    on_skipped: Callable[[int], None],
    *,
    admits: Callable[[str, bytes], bool] | None = None,
    packets_per_turn: int = PACKETS_PER_TURN,
) -> None:
    """Make ``paho_client`` skip every incoming packet whose remaining length exceeds
    ``max_packet_bytes`` without reading it into memory, calling ``on_skipped(length)`` once
    each has been skipped, and read up to ``packets_per_turn`` waiting packets per call.
    ``admits(topic, payload)``: whether a message goes on to the client's ``on_message`` at all
    (a payload that cannot be a message is dropped before aiomqtt wraps and queues it).
    Raises BusConnectionError if this paho's reader is not the one this was written for."""
    if not all(hasattr(paho_client, name) for name in _PAHO_READER):
        raise BusConnectionError(
            "mqtt client",
            "this paho-mqtt has no packet reader to guard against oversized packets",
            hint="install paho-mqtt 2.x (pip install 'paho-mqtt>=2,<3')",
        )
    reader = _GuardedReader(paho_client, max_packet_bytes, on_skipped, packets_per_turn)
    paho_client._sock_recv = reader.receive
    paho_client._packet_read = reader.read
    if admits is not None:
        _filter_messages(paho_client, admits)


class _GuardedReader:
    """paho's reader (``_packet_read``, ``_sock_recv``) wrapped: a packet over
    ``max_packet_bytes`` is skipped from the socket into a small scratch buffer, and each call
    reads up to ``packets_per_turn`` packets. :func:`guard_reader` installs it."""

    __slots__ = (
        "_client",
        "_max_packet_bytes",
        "_on_skipped",
        "_packets_per_turn",
        "_read_packet",
        "_receive",
        "_scratch",
    )

    def __init__(
        self,
        paho_client: Any,
        max_packet_bytes: int,
        on_skipped: Callable[[int], None],
        packets_per_turn: int,
    ) -> None:
        self._client = paho_client
        self._max_packet_bytes = max_packet_bytes
        self._on_skipped = on_skipped
        self._packets_per_turn = packets_per_turn
        self._read_packet = paho_client._packet_read
        self._receive = paho_client._sock_recv
        self._scratch = memoryview(bytearray(SKIP_CHUNK_BYTES))

    def read(self) -> MQTTErrorCode:
        """paho's ``_packet_read``: up to ``packets_per_turn`` packets, as long as whole ones
        are waiting."""
        for _ in range(self._packets_per_turn):
            rc = self._skip_body() if self._oversized() else self._read_packet()
            if rc != _SUCCESS:
                return rc  # nothing more waiting (AGAIN), or an error paho handles
            if self._client._in_packet["command"] != 0:
                return _SUCCESS  # within a packet: the rest when the socket is readable again
        return _SUCCESS

    def receive(self, bufsize: int) -> bytes:
        """paho's ``_sock_recv``: never a buffer the size of the rest of a packet."""
        if self._oversized():
            # The length just became known: leave the body to _skip_body (paho takes this as
            # "no data yet" and keeps its state).
            raise BlockingIOError
        return self._receive(min(bufsize, SKIP_CHUNK_BYTES))

    def _oversized(self) -> bool:
        packet = self._client._in_packet
        return (
            bool(packet["have_remaining"]) and packet["remaining_length"] > self._max_packet_bytes
        )

    def _skip_body(self) -> MQTTErrorCode:
        """Up to ``SKIP_CHUNKS_PER_TURN`` chunks of an oversized packet's body read and dropped;
        once all of it is, paho's reader starts afresh and ``on_skipped`` hears the length."""
        paho_client = self._client
        packet = paho_client._in_packet
        sock = paho_client._sock
        if sock is None:
            return MQTTErrorCode.MQTT_ERR_NO_CONN
        for _ in range(SKIP_CHUNKS_PER_TURN):
            wanted = min(packet["to_process"], SKIP_CHUNK_BYTES)
            if wanted == 0:
                break
            try:
                count = sock.recv_into(self._scratch, wanted)
            except (BlockingIOError, InterruptedError):
                return _SUCCESS  # more when the socket is readable again
            except OSError:
                return MQTTErrorCode.MQTT_ERR_CONN_LOST  # paho disconnects, aiomqtt reports
            if count == 0:
                return MQTTErrorCode.MQTT_ERR_CONN_LOST
            packet["to_process"] -= count
            paho_client._last_bytes_received = time.monotonic()  # the broker is alive
        if packet["to_process"] > 0:
            return _SUCCESS
        length = packet["remaining_length"]
        paho_client._in_packet = _fresh_packet()
        self._on_skipped(length)
        return _SUCCESS


def _filter_messages(paho_client: Any, admits: Callable[[str, bytes], bool]) -> None:
    """Only messages that ``admits(topic, payload)`` go on to ``paho_client.on_message``."""
    deliver = paho_client.on_message

    def on_message(client: Any, userdata: Any, message: Any) -> None:
        if admits(message.topic, message.payload):
            deliver(client, userdata, message)

    paho_client.on_message = on_message

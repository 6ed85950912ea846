"""How an MQTT client writes its socket: at once, on the event loop's thread, when it can.

aiomqtt registers paho's socket for writing each time paho queues a packet: a
``call_soon_threadsafe`` (a byte through the loop's self-pipe), a turn to add the writer, a turn
in which the socket is found writable and paho writes, the writer removed, and only then the
publisher's confirmation event set and, a turn later, the publisher resumed; for a QoS 0 step
message that paho could have written in the same call. :func:`write_at_once` makes the client
write a queued packet straight away when paho queues it on the loop's thread (what paho does by
itself without an external loop), so that a publish that the socket takes whole completes in
its own call (``MQTTMessageInfo.is_published``); only what the socket does not take (its buffer
full) waits for the writer as before. From another thread (aiomqtt connects in an executor) or
from within one of paho's callbacks nothing changes.

This relies on paho-mqtt 2.x calling ``on_socket_register_write`` with ``_registered_write``
set and unsetting it when ``loop_write`` leaves nothing to write; checked when a client is built.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from mission_runner.bus.errors import BusConnectionError

#: What this leans on in paho's client and aiomqtt's.
_PAHO_WRITER = (
    "loop_write",
    "want_write",
    "_registered_write",
    "_in_callback_mutex",
    "on_socket_register_write",
)
_AIOMQTT_CLIENT = ("_client", "_disconnected")


def write_at_once(client: Any) -> None:
    """Make aiomqtt ``client``'s paho client write what it queues at once when it is queued on
    the calling thread (the event loop's); the rest as aiomqtt does. Raises BusConnectionError
    if this aiomqtt or paho is not the one this was written for."""
    paho: Any = getattr(client, "_client", None)
    missing = [name for name in _AIOMQTT_CLIENT if not hasattr(client, name)]
    missing += [name for name in _PAHO_WRITER if paho is None or not hasattr(paho, name)]
    if missing:
        raise BusConnectionError(
            "paho", f"this aiomqtt/paho has no {', '.join(missing)}: cannot write at once",
            hint="install the aiomqtt 2.x and paho-mqtt 2.x versions pyproject.toml names",
        )  # fmt: skip
    loop_thread = threading.get_ident()
    register_later: Callable[[Any, Any, Any], None] = paho.on_socket_register_write

    def register(paho_client: Any, userdata: Any, sock: Any) -> None:
        # Not from another thread, nor from within one of paho's callbacks (paho's own rule).
        if threading.get_ident() != loop_thread or not paho_client._in_callback_mutex.acquire(
            False
        ):
            register_later(paho_client, userdata, sock)
            return
        paho_client._in_callback_mutex.release()
        try:
            paho_client.loop_write()
        except Exception as error:  # what aiomqtt's own writer does with it
            if not client._disconnected.done():
                client._disconnected.set_exception(error)
            return
        if paho_client.want_write():  # the socket took part of it: the rest when writable
            register_later(paho_client, userdata, sock)

    paho.on_socket_register_write = register

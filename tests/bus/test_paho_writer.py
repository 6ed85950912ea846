"""Publishing through a real mosquitto: a packet the socket takes whole is written in the call
that queues it; one it cannot take at once waits for the writer and still arrives whole."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
from collections.abc import Iterator

import aiomqtt
import pytest

from mission_runner.bus.errors import BusConnectionError
from mission_runner.bus.paho_writer import write_at_once
from tests.mosquitto import MosquittoBroker

pytestmark = pytest.mark.mqtt

#: Far more than a loopback socket's send buffer takes in one call.
BIG_BYTES = 32 * 1024 * 1024


async def _published_in_call(broker: MosquittoBroker, *, at_once: bool, size: int) -> bool:
    async with aiomqtt.Client(broker.host, broker.port) as client:
        if at_once:
            write_at_once(client)
        info = client._client.publish("cpu/test", b"x" * size, qos=0)
        in_call = info.is_published()
        # aiomqtt's own path (and the rest of a partial write) completes in the loop.
        async with asyncio.timeout(30):
            while not info.is_published():
                await asyncio.sleep(0.001)
        return in_call


@pytest.mark.asyncio
async def test_a_small_publish_is_written_in_its_call(mosquitto: MosquittoBroker) -> None:
    assert await _published_in_call(mosquitto, at_once=True, size=300)
    # Without it, aiomqtt registers a writer and paho writes a loop turn or two later.
    assert not await _published_in_call(mosquitto, at_once=False, size=300)


@pytest.mark.asyncio
async def test_what_the_socket_does_not_take_goes_out_when_it_is_writable(
    mosquitto: MosquittoBroker,
) -> None:
    async with (
        aiomqtt.Client(mosquitto.host, mosquitto.port) as receiver,
        aiomqtt.Client(mosquitto.host, mosquitto.port) as sender,
    ):
        await receiver.subscribe("cpu/big")
        write_at_once(sender)
        # The broker paused: nothing drains the socket while the call writes (a broker reading
        # on the other core once took all 32 MiB in one call).
        with _paused(mosquitto):
            info = sender._client.publish("cpu/big", b"y" * BIG_BYTES, qos=0)
        assert not info.is_published()  # the rest waits for the socket
        await sender.publish("cpu/after", b"small")  # queued behind it, on the same socket
        async with asyncio.timeout(60):
            message = await anext(aiter(receiver.messages))
    assert info.is_published()
    assert message.payload == b"y" * BIG_BYTES


@contextlib.contextmanager
def _paused(broker: MosquittoBroker) -> Iterator[None]:
    process = broker._process
    assert process is not None
    os.kill(process.pid, signal.SIGSTOP)
    try:
        yield
    finally:
        os.kill(process.pid, signal.SIGCONT)


def test_an_unknown_client_is_refused() -> None:
    with pytest.raises(BusConnectionError, match="cannot write at once"):
        write_at_once(object())

"""Oversized packets through a real mosquitto with no size limit of its own: the MQTT bus skips
them as they arrive, without ever holding one in memory, counts them, and goes on delivering
the messages that follow on the same connection."""

from __future__ import annotations

import asyncio
import sys
import tracemalloc

import pytest

from mission_runner.bus import ControlCommand, MissionControl, MqttBus, Sender, Topics
from mission_runner.bus.errors import BusConnectionError
from mission_runner.bus.paho_reader import guard_reader
from tests.mosquitto import MosquittoBroker, bus_test_key

pytestmark = pytest.mark.mqtt

TOPICS = Topics.for_mission("oversize-test")
BIG_BYTES = 16 * 1024 * 1024
# The outsider is another process, so that its own copies of the payload are not traced here.
OUTSIDER = """
import sys
import paho.mqtt.client as mqtt
client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="outsider")
client.connect(sys.argv[1], int(sys.argv[2]))
client.loop_start()
client.publish(sys.argv[3], b"x" * int(sys.argv[4]), qos=1).wait_for_publish(timeout=30)
client.loop_stop()
client.disconnect()
"""


@pytest.mark.asyncio
async def test_a_16_mib_payload_is_skipped_unread_and_the_next_message_arrives(
    mosquitto: MosquittoBroker,
) -> None:
    command = MissionControl(ControlCommand.HOLD, 1.0, mission_id="m1")
    async with (
        MqttBus(mosquitto.host, mosquitto.port, key=bus_test_key(), client_id="receiver") as bus,
        bus.subscribe(TOPICS.control()) as control,
        MqttBus(
            mosquitto.host, mosquitto.port, key=bus_test_key(), client_id="ground", qos=1
        ) as ground,
    ):
        tracemalloc.start()
        try:
            outsider = await asyncio.create_subprocess_exec(
                sys.executable, "-c", OUTSIDER, mosquitto.host, str(mosquitto.port),
                TOPICS.control(), str(BIG_BYTES),
            )  # fmt: skip
            assert await asyncio.wait_for(outsider.wait(), 30) == 0
            # After the big payload on the same topic, so on the same connection behind it.
            await ground.publish_message(TOPICS.control(), command, timeout=30)
            _, message = await control.receive_message(MissionControl, timeout=30)
            _, peak_bytes = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        counters = bus.auth_counters.as_dict()
    assert message == command
    assert counters["oversized"] == 1
    assert counters["accepted"] == 1
    # Read into memory, the payload alone would be 16 MiB; skipped, the receiver holds a 64 KiB
    # scratch buffer at most.
    assert peak_bytes < 4 * 1024 * 1024, peak_bytes


def test_a_paho_without_the_guarded_reader_is_refused() -> None:
    with pytest.raises(BusConnectionError, match=r"paho-mqtt 2\.x"):
        guard_reader(object(), 1024, lambda _: None)


def test_the_sender_of_a_skipped_packet_is_not_needed_to_count_it() -> None:
    bus = MqttBus("127.0.0.1", 1, key=bus_test_key(), sender=Sender.ground())
    bus.auth.skipped_oversized(70_000_000)
    assert bus.auth_counters.oversized == 1

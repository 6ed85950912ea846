"""The live view spoken to as Foxglove does: a WebSocket client of the Foxglove protocol
(subprotocol ``foxglove.sdk.v1``) that reads the server's advertisements, subscribes and decodes the
binary message frames, against a flight's callbacks fed with a known run."""

import base64
import contextlib
import json
import struct
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from mission_runner.checks import validate_scenario
from mission_runner.cli import EXIT_BAD_INPUT, main
from mission_runner.live import FlightFeed, LiveLog, LiveServer
from mission_runner.records import Progress, TruthSample
from mission_runner.sim.simulator import simulate

from .test_recording import flight_records

websockets_sync = pytest.importorskip("websockets.sync.client")
websockets_exceptions = pytest.importorskip("websockets.exceptions")

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SUBPROTOCOL = "foxglove.sdk.v1"  # the SDK server speaks this name of the protocol
MESSAGE_DATA = 0x01
WAIT_S = 20.0  # a bound on waiting for the server, never a figure under test


class FoxgloveClient:
    """The client side of the Foxglove WebSocket protocol, as much as a viewer needs."""

    def __init__(self, socket):
        self.socket = socket
        self.channels = {}  # id -> advertised channel
        self.subscriptions = {}  # subscription id -> (channel, decode)

    def wait_for_topics(self, topics):
        """Read the server's control messages until ``topics`` are all advertised."""
        while not set(topics) <= {c["topic"] for c in self.channels.values()}:
            self._handle(self.socket.recv(timeout=WAIT_S))

    def subscribe(self, topics):
        by_topic = {c["topic"]: c for c in self.channels.values()}
        subscriptions = []
        for topic in topics:
            channel = by_topic[topic]
            subscription_id = len(self.subscriptions) + 1
            self.subscriptions[subscription_id] = (channel, decoder(channel))
            subscriptions.append({"id": subscription_id, "channelId": channel["id"]})
        self.socket.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def receive(self):
        """The next message data: (topic, log time ns, decoded message)."""
        while True:
            frame = self.socket.recv(timeout=WAIT_S)
            if isinstance(frame, bytes) and frame[0] == MESSAGE_DATA:
                subscription_id, log_time = struct.unpack_from("<IQ", frame, 1)
                channel, decode = self.subscriptions[subscription_id]
                return channel["topic"], log_time, decode(frame[13:])
            self._handle(frame)

    def _handle(self, frame):
        if isinstance(frame, str):
            message = json.loads(frame)
            if message["op"] == "advertise":
                self.channels.update({c["id"]: c for c in message["channels"]})


@contextlib.contextmanager
def foxglove_client(url):
    with websockets_sync.connect(url, subprotocols=[SUBPROTOCOL], open_timeout=WAIT_S) as socket:
        yield FoxgloveClient(socket)


def decoder(channel):
    if channel["encoding"] == "json":
        return json.loads
    schema = Schema(
        id=1,
        name=channel["schemaName"],
        encoding=channel["schemaEncoding"],
        data=base64.b64decode(channel["schema"]),
    )
    return DecoderFactory().decoder_for("protobuf", schema)


class Subscribed:
    """A server listener that tells when ``expected`` subscriptions are in place."""

    def __init__(self, expected):
        self.expected, self.count, self.done = expected, 0, threading.Event()

    def on_subscribe(self, client, channel):
        self.count += 1
        if self.count >= self.expected:
            self.done.set()


@contextlib.contextmanager
def subscribed(scenario, topics):
    """A live server for ``scenario`` and a client subscribed to ``topics`` (in place)."""
    listener = Subscribed(len(topics))
    with (
        LiveServer(scenario, port=0, listener=listener) as server,
        foxglove_client(server.url) as client,
    ):
        client.wait_for_topics(topics)
        client.subscribe(topics)
        assert listener.done.wait(WAIT_S)
        yield server, client


def short_scenario(steps):
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["timing"]["steps"] = steps
    return validate_scenario(data, "short")


def test_a_flight_feed_sends_a_pose_per_vehicle_per_step_to_a_foxglove_client():
    steps = 6
    scenario = short_scenario(steps)
    result = simulate(scenario)
    records = flight_records(result, start_s=0.0)
    ids = [1, 2, 3, 4]
    topics = [f"/vehicles/{i}/pose" for i in ids] + ["/vehicles/2/state", "/log"]
    with subscribed(scenario, topics) as (server, client):
        feed = FlightFeed(scenario, server.channels)
        live_log = LiveLog(server.channels)
        for k in range(steps):
            for vehicle_id in ids:
                feed.on_step(vehicle_id, records[vehicle_id][k])
            positions = result.positions_m[0, k]
            truth = TruthSample(k, k * 0.125, result.target_m[k], positions, np.ones(4, bool))
            feed.on_progress(Progress(k, steps, k * 0.125, {}, 0.1, 0.01, truth))
        live_log.emit(_record("the last line"))
        received = [client.receive() for _ in range(steps * (len(ids) + 1) + 1)]
    poses = {}
    for topic, log_time, message in received:
        if topic.endswith("/pose"):
            key = (int(topic.split("/")[2]), round(log_time / 0.125e9))
            assert key not in poses
            poses[key] = message.pose.position
    assert set(poses) == {(i, k) for i in ids for k in range(steps)}
    position = poses[(3, 4)]
    assert (position.y, position.x) == pytest.approx(tuple(result.positions_m[0, 4, 2]))
    states = [message for topic, _, message in received if topic == "/vehicles/2/state"]
    assert [state["step"] for state in states] == list(range(steps))
    assert states[3]["slot_north_m"] is not None
    assert received[-1][0] == "/log" and received[-1][2].message == "the last line"


def _record(message):
    import logging

    return logging.LogRecord("mission_runner.test", logging.WARNING, __file__, 1, message, (), None)


def test_view_needs_a_mission_on_mqtt(capsys):
    assert main(["view", str(CONFIGS / "paper_tracking.yaml"), "--port", "0"]) == EXIT_BAD_INPUT
    assert "bus.kind" in capsys.readouterr().err


@pytest.mark.mavsdk
@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_flown_mission_served_live_sends_a_pose_per_vehicle_per_step():
    """``run --live``'s wiring around a real flight (MAVSDK, UDP, the emulator in lockstep): a
    client subscribed before take-off gets every vehicle's pose at every step."""
    import asyncio

    from mission_runner.runner.mission import fly

    from .runner.flying import free_ports, load

    steps = 40
    data = load("paper_tracking_flyable").model_dump(mode="json")
    data["timing"]["steps"] = steps
    data["expect"] = {}
    scenario = validate_scenario(data, "short flight")
    ids = [vehicle.id for vehicle in scenario.vehicles]
    topics = [f"/vehicles/{i}/pose" for i in ids]
    listener = Subscribed(len(topics))
    received = []

    def watch(url):
        with foxglove_client(url) as client:
            client.wait_for_topics(topics)
            client.subscribe(topics)
            with contextlib.suppress(websockets_exceptions.ConnectionClosed):
                while len(received) < steps * len(ids):
                    received.append(client.receive())

    with LiveServer(scenario, port=0, listener=listener) as server:
        watcher = threading.Thread(target=watch, args=(server.url,), name="foxglove-client")
        watcher.start()
        assert listener.done.wait(WAIT_S)
        feed = FlightFeed(scenario, server.channels)
        outcome = asyncio.run(
            fly(
                scenario,
                emulator_overrides=free_ports(scenario),
                on_step=feed.on_step,
                on_progress=feed.on_progress,
            )
        )
        watcher.join(WAIT_S)
    start_s = outcome.start_s
    keys = [(int(t.split("/")[2]), round((at / 1e9 - start_s) / 0.125)) for t, at, _ in received]
    assert sorted(keys) == sorted((i, k) for i in ids for k in range(steps))


@pytest.mark.mqtt
@pytest.mark.timeout(60)
def test_the_view_of_a_mission_bus_sends_each_step_message_and_status(mosquitto):
    """``view`` / ``ground --live``: what vehicle processes publish on MQTT reaches a Foxglove
    client as each vehicle's state and its frame in its odometry; a status as an event."""
    import asyncio

    from mission_runner.bus import StepMessage, VehicleStatus, open_bus
    from mission_runner.live import serve_bus

    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": mosquitto.host, "port": mosquitto.port}}
    scenario = validate_scenario(data, "mqtt")
    topics = scenario.bus.topics(scenario.name)
    watched = ["/vehicles/1/state", "/vehicles/2/state", "/tf", "/mission/events"]
    steps, start_s = 5, 1.7e9

    async def mission(server, client):
        async with asyncio.TaskGroup() as group:
            view = group.create_task(
                serve_bus(scenario, server.channels, client_id="view"), name="view"
            )
            async with open_bus(scenario.bus, sender=None, client_id="vehicles") as bus:
                status = VehicleStatus(1, start_s, "following", 0, True)
                await bus.publish_message(topics.status(1), status, retain=True, timeout=5)
                # The retained status seen means the view is subscribed to the steps too.
                topic, _, event = await asyncio.to_thread(client.receive)
                assert topic == "/mission/events"
                assert event.message == "vehicle 1: following (step 0)"
                for k in range(steps):
                    for vehicle_id in (1, 2):
                        message = StepMessage(
                            vehicle_id, k, start_s + k * 0.125, 0.1 * k, 0.5 * k, -0.2 * k
                        )
                        await bus.publish_message(topics.step(vehicle_id), message, timeout=5)
                received = [await asyncio.to_thread(client.receive) for _ in range(4 * steps)]
            view.cancel()
        return received

    with subscribed(scenario, watched) as (server, client):
        received = asyncio.run(mission(server, client))
    states = [(t, m["step"], m["phase_rad"]) for t, _, m in received if t.endswith("/state")]
    assert sorted(states) == sorted(
        (f"/vehicles/{i}/state", k, pytest.approx(0.1 * k)) for i in (1, 2) for k in range(steps)
    )
    frames = [m.transforms[0] for t, _, m in received if t == "/tf"]
    assert {(f.parent_frame_id, f.child_frame_id) for f in frames} == {
        ("odom_1", "vehicle_1"),
        ("odom_2", "vehicle_2"),
    }
    last = [f for f in frames if f.child_frame_id == "vehicle_2"][-1]
    assert (last.translation.y, last.translation.x) == pytest.approx((0.5 * 4, -0.2 * 4))

"""``mission-runner broker-config``'s mosquitto configuration, run by a real mosquitto: per-role
logins, the ACL, and what a receiving bus drops of what gets through the broker."""

from __future__ import annotations

import base64
import hashlib
import re
import stat
import subprocess
from collections.abc import AsyncIterator
from pathlib import Path

import aiomqtt
import pytest
import pytest_asyncio

from mission_runner.bus import (
    BusConnectionError,
    BusKey,
    ControlCommand,
    MessageAuth,
    MissionControl,
    MqttBus,
    RangeSet,
    Sender,
    StepMessage,
    Topics,
    VehicleStatus,
    lost_vehicle_will,
)
from mission_runner.bus.broker import (
    BrokerFiles,
    TlsListener,
    mosquitto_password_hash,
    read_credentials,
    write_broker_config,
)
from tests.mosquitto import MosquittoBroker, bus_test_key, mosquitto_passwd_binary, secured_broker

TOPICS = Topics.for_mission("acl-test")
VEHICLES = [1, 2]


def test_the_password_hash_is_the_one_mosquitto_passwd_writes(tmp_path: Path) -> None:
    passwd = mosquitto_passwd_binary()
    if passwd is None:
        pytest.skip("mosquitto_passwd is not installed")
    path = tmp_path / "passwords"
    path.touch(mode=0o600)
    subprocess.run([passwd, "-b", str(path), "alice", "s3cret"], check=True, timeout=10)
    line = path.read_text().strip()
    salt = base64.b64decode(line.split("$")[3])
    assert line == "alice:" + mosquitto_password_hash("s3cret", salt=salt)


def test_a_password_hash_has_a_fresh_salt_and_verifies() -> None:
    first, second = mosquitto_password_hash("pw"), mosquitto_password_hash("pw")
    assert first != second
    match = re.fullmatch(r"\$7\$101\$([A-Za-z0-9+/=]+)\$([A-Za-z0-9+/=]+)", first)
    assert match is not None
    salt, digest = (base64.b64decode(part) for part in match.groups())
    assert len(salt) == 12
    assert hashlib.pbkdf2_hmac("sha512", b"pw", salt, 101) == digest


@pytest.mark.parametrize(("uid", "as_root"), [(0, True), (1000, False)])
def test_written_as_root_the_broker_stays_root_to_read_its_logins(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, uid: int, as_root: bool
) -> None:
    """mosquitto started as root switches to the user "mosquitto" unless told otherwise, and
    that user cannot read root's 0600 logins ("Unable to open pwfile"): following docs/real-px4.md
    as root failed so."""
    monkeypatch.setattr("mission_runner.bus.broker.os.geteuid", lambda: uid)
    files = write_broker_config(tmp_path / "out", TOPICS, [1], port=1883)
    assert ("user root" in files.config.read_text().splitlines()) is as_root


def test_the_files_written(tmp_path: Path) -> None:
    cert, key = tmp_path / "server.crt", tmp_path / "server.key"
    files = write_broker_config(
        tmp_path / "out", TOPICS, [1, 3], port=8883, tls=TlsListener(cert, key, None)
    )
    for secret in (files.passwords, files.credentials, files.bus_key):
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600, secret
    users = read_credentials(files.credentials)
    assert sorted(users) == [
        "ground",
        "operator",
        "ranges",
        "vehicle-1",
        "vehicle-1-flight",
        "vehicle-3",
        "vehicle-3-flight",
        "viewer",
    ]
    assert len(set(users.values())) == 8 and all(len(p) >= 24 for p in users.values())
    assert not any(password in files.passwords.read_text() for password in users.values())
    assert len(BusKey.from_file(files.bus_key).secret) == 64
    config = files.config.read_text().splitlines()
    assert "listener 8883" in config and "allow_anonymous false" in config
    assert "use_username_as_clientid true" in config
    assert f"certfile {cert}" in config and f"keyfile {key}" in config
    # Sized from the largest message the receivers accept (bus.auth.max_message_bytes).
    assert "max_packet_size 17408" in config and "message_size_limit 16384" in config
    acl = files.acl.read_text()
    assert "user ground\ntopic write enclosing/acl-test/control\n" in acl
    assert "user vehicle-3\ntopic write enclosing/acl-test/vehicle/3/step\n" in acl
    assert "user operator\ntopic write enclosing/acl-test/control\n" in acl
    assert "user viewer\ntopic read enclosing/acl-test/#\n" in acl
    # The controller's own connection logs in as its own user, with the vehicle's rights.
    assert "user vehicle-3-flight\ntopic write enclosing/acl-test/vehicle/3/step\n" in acl
    assert acl.count("topic write enclosing/acl-test/control") == 2
    assert "user ranges\ntopic write enclosing/acl-test/vehicle/+/ranges\n" in acl
    assert acl.count("topic write enclosing/acl-test/vehicle/3/ranges\n") == 2  # both logins
    assert "/range/" not in acl


@pytest.fixture
def broker(tmp_path: Path) -> AsyncIterator[tuple[MosquittoBroker, BrokerFiles]]:
    broker, files = secured_broker(tmp_path, TOPICS, VEHICLES)
    broker.start()
    try:
        yield broker, files
    finally:
        broker.stop()


def client(
    broker: MosquittoBroker,
    files: BrokerFiles,
    user: str,
    *,
    sender: Sender | None = None,
    key: BusKey | None = None,
    password: str | None = None,
) -> MqttBus:
    """A bus logged in as ``user`` (signing as ``sender``, default: that role)."""
    users = read_credentials(files.credentials)
    return MqttBus(
        broker.host,
        broker.port,
        key=key or bus_test_key(),
        # The operator and the viewer sign (if at all) as the ground station.
        sender=sender
        or (Sender.ground() if user in ("operator", "viewer") else Sender.parse(user)),
        client_id=f"test-{user}",
        username=user,
        password=password if password is not None else users[user],
        connect_timeout_s=3.0,
        qos=1,  # the broker's acknowledgement orders what follows on other connections
    )


pytestmark = pytest.mark.mqtt


@pytest.mark.asyncio
async def test_every_role_logs_in_and_strangers_do_not(
    broker: tuple[MosquittoBroker, BrokerFiles],
) -> None:
    server, files = broker
    for user in files.users:
        # A vehicle's second login signs as the vehicle; the operator and viewer as the ground.
        sender = (
            None if user in ("operator", "viewer") else Sender.parse(user.removesuffix("-flight"))
        )
        async with client(server, files, user, sender=sender) as bus:
            assert bus.connected
    for password in ("wrong", ""):
        with pytest.raises(BusConnectionError, match="refused the credentials"):
            async with client(server, files, "ground", password=password):
                pass


@pytest.mark.asyncio
async def test_a_vehicles_credentials_cannot_publish_a_control_message(
    broker: tuple[MosquittoBroker, BrokerFiles],
) -> None:
    """Even with the bus key and signing as the ground station, vehicle 2's broker login cannot
    command: mosquitto drops its start. Its own step goes through, in order, after it."""
    server, files = broker
    forged_start = MissionControl(ControlCommand.START, 1000.0, mission_id="m")
    async with (
        client(server, files, "vehicle-1") as vehicle_1,
        vehicle_1.subscribe(TOPICS.everything()) as everything,
    ):
        # One after the other: one connection per login (the second would take the first's).
        async with client(server, files, "vehicle-2", sender=Sender.ground()) as as_ground:
            await as_ground.publish_message(TOPICS.control(), forged_start, timeout=5.0)
        async with client(server, files, "vehicle-2") as vehicle_2:
            await vehicle_2.publish_message(TOPICS.control(), forged_start, timeout=5.0)
            step_1, step_2 = StepMessage(1, 0, 0, 0, 0, 0), StepMessage(2, 0, 0, 0, 0, 0)
            await vehicle_2.publish_message(TOPICS.step(1), step_1, timeout=5)
            await vehicle_2.publish_message(TOPICS.step(2), step_2, timeout=5)
        topic, _ = await everything.receive(timeout=5.0)
    assert topic == TOPICS.step(2)  # the start and vehicle 1's step never left the broker
    assert vehicle_1.auth_counters.rejected == 0  # nothing even reached the bus to be dropped


@pytest.mark.asyncio
async def test_the_range_aid_publishes_ranges_only_and_the_ground_commands(
    broker: tuple[MosquittoBroker, BrokerFiles],
) -> None:
    server, files = broker
    hold = MissionControl(ControlCommand.HOLD, 1.0, mission_id="m")
    async with (
        client(server, files, "vehicle-1") as vehicle_1,
        vehicle_1.subscribe(TOPICS.everything()) as everything,
        client(server, files, "ground") as ground,
    ):
        # One after the other: one connection per login (the second would take the first's).
        async with client(server, files, "ranges", sender=Sender.vehicle(2)) as ranges_as_vehicle:
            step = StepMessage(2, 0, 0, 0, 0, 0)
            await ranges_as_vehicle.publish_message(TOPICS.step(2), step, timeout=5)
        async with client(server, files, "ranges") as ranges:
            range_set = RangeSet(1, 0.0, ((2, 4.0),))
            await ranges.publish_message(TOPICS.ranges(1), range_set, timeout=5)
        await ground.publish_message(TOPICS.control(), hold, timeout=5.0)
        received = [(await everything.receive(timeout=5.0))[0] for _ in range(2)]
    assert sorted(received) == sorted([TOPICS.ranges(1), TOPICS.control()])


@pytest_asyncio.fixture
async def attacker(
    broker: tuple[MosquittoBroker, BrokerFiles],
) -> AsyncIterator[aiomqtt.Client]:
    """A raw MQTT client with the range aid's broker login (stolen) but not the bus key."""
    server, files = broker
    users = read_credentials(files.credentials)
    async with aiomqtt.Client(
        server.host, server.port, username="ranges", password=users["ranges"], identifier="evil"
    ) as raw:
        yield raw


@pytest.mark.asyncio
async def test_forged_replayed_oversized_and_malformed_ranges_are_dropped_and_counted(
    broker: tuple[MosquittoBroker, BrokerFiles], attacker: aiomqtt.Client
) -> None:
    """Everything comes through the broker (the login may publish ranges); the vehicle's bus
    drops all but the genuine messages, and counts each kind."""
    server, files = broker
    topic = TOPICS.ranges(1)
    forty = RangeSet(1, 0.0, ((2, 40.0),)).to_payload()
    genuine = MessageAuth(bus_test_key())  # what the real range aid signs
    first = genuine.seal(Sender.ranges(), topic, RangeSet(1, 0.0, ((2, 4.0),)).to_payload())
    wrong_key = MessageAuth(BusKey.from_text("x" * 64, "attacker"))
    async with (
        client(server, files, "vehicle-1") as vehicle_1,
        vehicle_1.subscribe(TOPICS.ranges(1)) as ranges,
    ):
        for payload in [
            forty,  # the forged ranges: unsigned
            wrong_key.seal(Sender.ranges(), topic, forty),  # signed with a guessed key
            first,
            first,  # replayed
            b"\x00\xff garbage",  # malformed
            b"",  # empty: MQTT's "clear the retained value", no message
            genuine.seal(Sender.ranges(), topic, RangeSet(1, 0.125, ((2, 4.1),)).to_payload()),
        ]:
            await attacker.publish(topic, payload)
        got = [(await ranges.receive_message(RangeSet, timeout=5.0))[1] for _ in range(2)]
        counters = vehicle_1.auth_counters.as_dict()
    assert [message.ranges_m for message in got] == [((2, 4.0),), ((2, 4.1),)]
    assert counters == {
        "accepted": 2,
        "oversized": 0,  # the broker forwards none (see the next test)
        "malformed": 2,
        "forged": 1,
        "unauthorised": 0,
        "stale": 0,
        "replayed": 1,
        "empty": 1,
    }


@pytest.mark.asyncio
async def test_a_vehicles_login_cannot_take_another_vehicles_client_id(
    broker: tuple[MosquittoBroker, BrokerFiles],
) -> None:
    """Vehicle 1's login connecting with vehicle 2's client id (seen on the network) used to make
    mosquitto drop vehicle 2 and publish its genuinely signed last will, "lost". The broker binds
    ids to logins now: vehicle 2 stays connected, and the ground hears its own status, no will."""
    server, files = broker
    users = read_credentials(files.credentials)
    will = lost_vehicle_will(TOPICS, 2, time_s=0.0)
    alive = VehicleStatus(2, 1.0, "ready", 0, False, "", mission_id="m")
    vehicle_2 = client(server, files, "vehicle-2")
    vehicle_2.will = will
    async with (
        client(server, files, "ground") as ground,
        ground.subscribe(TOPICS.status(2)) as status,
        vehicle_2,
    ):
        async with aiomqtt.Client(
            server.host,
            server.port,
            username="vehicle-1",
            password=users["vehicle-1"],
            identifier=vehicle_2.client_id,
        ):
            pass
        await vehicle_2.publish_message(TOPICS.status(2), alive, retain=True, timeout=5.0)
        _, heard = await status.receive_message(VehicleStatus, timeout=5.0)
        assert vehicle_2.connect_count == 1
    assert heard == alive


@pytest.mark.asyncio
async def test_the_broker_forwards_nothing_longer_than_a_message(
    broker: tuple[MosquittoBroker, BrokerFiles], attacker: aiomqtt.Client
) -> None:
    """A payload longer than any message the mission accepts never reaches a vehicle: the
    broker disconnects whoever sends it before reading it (64 MiB, the issue's attack), and
    drops one just over the limit in a shorter packet."""
    server, files = broker
    topic = TOPICS.ranges(1)
    async with (
        client(server, files, "vehicle-1") as vehicle_1,
        vehicle_1.subscribe(TOPICS.ranges(1)) as ranges,
        # The attacker holds the range aid's login (one connection a login): vehicle 1's
        # controller connection publishes the genuine range.
        client(server, files, "vehicle-1-flight", sender=Sender.vehicle(1)) as range_aid,
    ):
        await attacker.publish(topic, b"x" * (16384 + 512), qos=1, timeout=10)
        # Disconnected unread: the acknowledgement never comes.
        with pytest.raises(aiomqtt.MqttError):
            await attacker.publish(topic, b"x" * (64 * 1024 * 1024), qos=1, timeout=5)
        await range_aid.publish_message(topic, RangeSet(1, 0.0, ((2, 4.0),)), timeout=5)
        _, got = await ranges.receive_message(RangeSet, timeout=5.0)
        counters = vehicle_1.auth_counters.as_dict()
    assert got.ranges_m == ((2, 4.0),)
    assert counters["oversized"] == 0 and counters["malformed"] == 0
    assert counters["accepted"] == 1

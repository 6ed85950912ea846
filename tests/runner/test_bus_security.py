"""The issue's two attacks, through a real mosquitto running ``broker-config``'s configuration
(per-role logins and ACL): "one forged start with time_s 1000 makes every vehicle process
declare itself lost at step 2" and "forged ranges (40 m for every pair) give 264 m of
localization error with no warning". Both are now dropped before anything acts on them, and
counted."""

import asyncio
import time

import aiomqtt
import pytest

from mission_runner.bus import (
    BusAccess,
    BusKey,
    ControlCommand,
    MessageAuth,
    MissionControl,
    MqttBus,
    RangeSet,
    Sender,
    Topics,
)
from mission_runner.bus.broker import read_credentials
from mission_runner.checks import validate_scenario
from mission_runner.metrics import run_metrics
from mission_runner.outputs import bus_security, bus_security_line
from mission_runner.runner.handshake import (
    MAX_START_LAG_S,
    MAX_START_LEAD_S,
    next_command,
    start_problem,
)
from mission_runner.runner.mission import fly
from tests.mosquitto import add_login, bus_test_key, secured_broker

from .flying import free_ports, load

NOW_S = 1_800_000_000.0


def start(time_s, **fields):
    return MissionControl(ControlCommand.START, time_s, mission_id="m1", **fields)


@pytest.mark.parametrize(
    ("command", "problem"),
    [
        (start(NOW_S + 2.0), None),
        (start(NOW_S - MAX_START_LAG_S + 0.5), None),
        (start(1000.0), "ago"),  # the forged start
        (start(NOW_S + MAX_START_LEAD_S + 1.0), "from now"),
        (start(NOW_S + 4.0, clock_rate=2.0, clock_reference_s=NOW_S - 1.0), None),
        (start(NOW_S + 2.0, clock_rate=2.0, clock_reference_s=1000.0), "clock reference"),
        # A clock running 100x from a reference 100 s ago is 9900 s ahead: k = 0 long past.
        (start(NOW_S + 2.0, clock_rate=100.0, clock_reference_s=NOW_S - 100.0), "ago"),
    ],
)
def test_a_start_must_make_sense_on_the_receivers_clock(command, problem):
    found = start_problem(command, NOW_S)
    assert (found is None) if problem is None else (problem in found), found


def mqtt_client(broker, files, user, *, sender=None):
    users = read_credentials(files.credentials)
    return MqttBus(
        broker.host,
        broker.port,
        key=bus_test_key(),
        sender=sender or Sender.parse(user),
        client_id=f"test-{user}",
        username=user,
        password=users[user],
        qos=1,  # acknowledged by the broker before the next publish: a defined order
    )


def raw_client(broker, files, user):
    """An MQTT client with a stolen broker login and no bus key."""
    users = read_credentials(files.credentials)
    return aiomqtt.Client(
        broker.host, broker.port, username=user, password=users[user], identifier=f"evil-{user}"
    )


@pytest.mark.mqtt
@pytest.mark.asyncio
async def test_a_forged_start_with_time_1000_does_nothing(tmp_path):
    """A vehicle waiting for its start gets only the ground station's real one: the forged
    starts are dropped by the broker (a vehicle's login), by the bus (no key, or signed by a
    vehicle) or by the handshake (signed by the ground role, but k = 0 in 1970)."""
    topics = Topics.for_mission("forged-start")
    broker, files = secured_broker(tmp_path, topics, [1, 2])
    await broker.astart()
    now_s = time.time()
    forged = start(1000.0)
    try:
        async with (
            mqtt_client(broker, files, "vehicle-1") as vehicle,
            vehicle.subscribe(topics.control()) as control,
            mqtt_client(broker, files, "vehicle-2", sender=Sender.ground()) as vehicle_as_ground,
        ):
            # The ground's login in turns: one connection per login (ids are bound to logins).
            async with mqtt_client(broker, files, "ground") as ground:
                prepare = MissionControl(ControlCommand.PREPARE, now_s, mission_id="m1")
                await ground.publish_message(topics.control(), prepare, retain=True, timeout=5)
            got = await next_command(control, {ControlCommand.PREPARE}, timeout_s=5)
            assert got.mission_id == "m1"
            # No key: the attack as it was made.
            async with raw_client(broker, files, "ground") as stolen_login:
                await stolen_login.publish(topics.control(), forged.to_payload(), qos=1)
            # A vehicle's login with the key, signing as the ground: the broker's ACL.
            await vehicle_as_ground.publish_message(topics.control(), forged, timeout=5)
            # The ground role (its key and login) with an insane start time: the handshake.
            async with mqtt_client(broker, files, "ground") as ground:
                await ground.publish_message(topics.control(), forged, timeout=5)
                await ground.publish_message(topics.control(), start(now_s + 3600), timeout=5)
                real = start(now_s + 2.0)
                await ground.publish_message(topics.control(), real, timeout=5)
            got = await next_command(
                control, {ControlCommand.START}, mission_id="m1", unix_clock=lambda: now_s
            )
            counters = vehicle.auth_counters.as_dict()
    finally:
        await broker.astop()
    assert got == real
    assert counters["malformed"] == 1  # the unsigned start
    assert counters["accepted"] == 4  # prepare, the two starts the handshake refused, the start


@pytest.mark.mqtt
@pytest.mark.mavsdk
@pytest.mark.slow
@pytest.mark.asyncio
@pytest.mark.timeout(240)
async def test_forged_ranges_for_every_pair_leave_the_mission_unharmed(tmp_path):
    """The tracking mission flown over mosquitto with the ACL on, every vehicle with its own
    login, while someone with a login that may publish ranges (as the range aid's may) and no
    key publishes 40 m for every pair at every step: the mission converges as without them, and
    the summary counts them. (The range aid's own login, stolen, would take over the range aid's
    connection instead: client ids are bound to logins.)"""
    data = load("paper_tracking_flyable").model_dump(mode="json")
    data["name"] = "forged_ranges"
    data["timing"]["steps"] = 320
    topics = Topics.for_mission("forged_ranges")
    broker, files = secured_broker(tmp_path, topics, [v["id"] for v in data["vehicles"]])
    add_login(files, "intruder", [f"topic write {topics.all_ranges()}"])
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    scenario = validate_scenario(data)
    scenario = scenario.model_copy(
        update={"bus": scenario.bus.with_access(BusAccess(credentials_file=files.credentials))}
    )
    ids = [v.id for v in scenario.vehicles]
    await broker.astart()
    forging = []
    try:
        async with raw_client(broker, files, "intruder") as attacker:
            wrong_key = MessageAuth(BusKey.from_text("attacker-" * 8, "attacker"))

            async def forge(step):
                for own in ids:
                    topic = topics.ranges(own)
                    forged = tuple((peer, 40.0) for peer in ids if peer != own)
                    body = RangeSet(own, 0.0, forged, step=step).to_payload()
                    await attacker.publish(topic, body)
                    await attacker.publish(topic, wrong_key.seal(Sender.ranges(), topic, body))

            def on_progress(progress):
                forging.append(asyncio.get_running_loop().create_task(forge(progress.step + 1)))

            outcome = await fly(
                scenario, emulator_overrides=free_ports(scenario), on_progress=on_progress
            )
            await asyncio.gather(*forging)
    finally:
        await broker.astop()
    metrics = {key: value[0] for key, value in run_metrics(outcome.result).items()}
    assert metrics["final_localization_error_m"] < 0.05
    assert metrics["final_tracking_error_m"] < 0.1
    assert metrics["vehicles_disarmed_at_end"] == 4
    messages = outcome.bus_security["messages"]
    forged_per_step = len(ids)  # each vehicle's bus sees its own range sets only
    assert messages["malformed"] >= forged_per_step * 100
    assert messages["forged"] >= forged_per_step * 100
    assert outcome.bus_security["ranges_rejected"] == {
        str(i): {"invalid": 0, "beyond_reach": 0, "jump": 0} for i in ids
    }
    assert outcome.bus_security["commands_rejected"] == {str(i): 0 for i in ids}


def test_the_summary_counts_every_kind_of_dropped_input_and_says_so_in_one_line():
    quiet = bus_security({"accepted": 10}, {1: {"invalid": 0, "jump": 0}}, {1: 0})
    assert bus_security_line({"bus_security": quiet}) is None
    security = bus_security({"accepted": 10, "forged": 2}, {1: {"jump": 1}}, {1: 3, 2: 1})
    assert security["messages_dropped"] == 2
    assert security["commands_rejected"] == {"1": 3, "2": 1}
    line = bus_security_line({"bus_security": security})
    assert line == (
        "bus: dropped 2 of 12 messages (2 forged); impossible ranges rejected: 1 jump; "
        "impossible neighbour commands dropped: 4"
    )
    commands_only = bus_security({"accepted": 10}, {}, {3: 2})
    assert bus_security_line({"bus_security": commands_only}).endswith(
        "impossible neighbour commands dropped: 2"
    )

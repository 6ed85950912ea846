"""Vehicle-to-vehicle message bus: one interface, an in-process and an MQTT implementation.

Each vehicle controller publishes its per-step message and subscribes to its neighbours'
through a ``Bus``; sensor drivers publish ranges and target observations; a ground station
publishes mission commands. ``open_bus(settings)`` builds the bus the scenario asks for.
A step loop on the bus (tests/bus/test_usage.py runs this pattern)::

    topics = settings.bus.topics(mission_id)
    async with (
        open_bus(settings.bus, sender=Sender.vehicle(i), client_id=f"vehicle-{i}",
                 will=lost_vehicle_will(topics, i, time_s=clock.now_s())) as bus,
        bus.subscribe(topics.all_steps()) as neighbours,
    ):
        last_heard_s = clock.now_s()
        for k in itertools.count():
            own = StepMessage(i, k, clock.now_s(), theta_i, odometry_north_m, odometry_east_m)
            with contextlib.suppress(BusConnectionError):  # a lost message costs freshness only
                await bus.publish_message(topics.step(i), own, timeout=T_s / 4)
            await clock.sleep(until_collection_deadline_s)
            step_k = {}
            for _, message in neighbours.drain_messages(StepMessage):
                if message.vehicle_id != i:
                    last_heard_s = clock.now_s()
                    if message.step == k:
                        step_k[message.vehicle_id] = message
            if clock.now_s() - last_heard_s > silence_timeout_s:
                ...  # nobody heard for a while: hold position, do not follow the algorithm
            ...  # use step_k; a neighbour missing from it is late or lost this step

The mission's controller (``mission_runner.runner.controller``) follows the same rules; it
feeds a step inbox from ``Subscription.messages`` and waits for each step's messages until
the step's deadline, instead of sleeping to the deadline and draining.

Every message is signed by its sender's role and checked on arrival (``auth``); what fails
is dropped and counted in ``Bus.auth_counters``, never handed to a subscription.

Modules: ``topics`` (layout and MQTT matching), ``messages`` (payloads), ``auth`` (message
keys, signing, replay protection, who may publish what), ``base`` (the interface and
subscriptions), ``inprocess`` and ``mqtt`` (implementations), ``broker`` (mosquitto's
configuration and broker logins), ``settings`` (typed config), ``errors`` (exception tree).
"""

from __future__ import annotations

import logging
import random

from mission_runner.bus.auth import (
    AuthCounters,
    AuthPolicy,
    BusKey,
    MessageAuth,
    Rejection,
    Role,
    Sender,
)
from mission_runner.bus.base import DEFAULT_QUEUE_SIZE, Bus, BusClient, Subscription
from mission_runner.bus.broker import broker_login
from mission_runner.bus.errors import (
    BusAuthError,
    BusConnectionError,
    BusError,
    BusTimeoutError,
    MessageDecodeError,
    MessageValueError,
    TopicError,
)
from mission_runner.bus.inprocess import InProcessBus, LinkModel
from mission_runner.bus.messages import (
    MESSAGE_TYPES,
    ControlCommand,
    Message,
    MissionControl,
    RangeSet,
    StepMessage,
    TargetObservation,
    VehicleStatus,
    shared_range,
)
from mission_runner.bus.mqtt import Backoff, LastWill, MqttBus, lost_vehicle_will
from mission_runner.bus.settings import (
    AuthSettings,
    BusAccess,
    BusSettings,
    LinkSettings,
    MqttSettings,
    TlsSettings,
)
from mission_runner.bus.topics import (
    ParsedTopic,
    TopicKind,
    Topics,
    topic_matches,
    validate_pattern,
    validate_topic,
)
from mission_runner.clock import Clock, ManualClock, MonotonicClock

logger = logging.getLogger(__name__)

__all__ = [
    "DEFAULT_QUEUE_SIZE",
    "MESSAGE_TYPES",
    "AuthCounters",
    "AuthPolicy",
    "AuthSettings",
    "Backoff",
    "Bus",
    "BusAccess",
    "BusAuthError",
    "BusClient",
    "BusConnectionError",
    "BusError",
    "BusKey",
    "BusSettings",
    "BusTimeoutError",
    "Clock",
    "ControlCommand",
    "InProcessBus",
    "LastWill",
    "LinkModel",
    "LinkSettings",
    "ManualClock",
    "Message",
    "MessageAuth",
    "MessageDecodeError",
    "MessageValueError",
    "MissionControl",
    "MonotonicClock",
    "MqttBus",
    "MqttSettings",
    "ParsedTopic",
    "RangeSet",
    "Rejection",
    "Role",
    "Sender",
    "StepMessage",
    "Subscription",
    "TargetObservation",
    "TlsSettings",
    "TopicError",
    "TopicKind",
    "Topics",
    "VehicleStatus",
    "lost_vehicle_will",
    "open_bus",
    "shared_range",
    "topic_matches",
    "validate_pattern",
    "validate_topic",
]


def open_bus(
    settings: BusSettings,
    *,
    sender: Sender | None,
    client_id: str | None = None,
    will: LastWill | None = None,
    clock: Clock | None = None,
    rng: random.Random | None = None,
    login: str | None = None,
) -> Bus:
    """The bus ``settings`` describe, not yet entered: use it as ``async with``.

    ``sender`` is whom this process signs as (None: each topic's owner, for one process that
    is the whole swarm) and which broker user it logs in as (see ``broker.broker_login``),
    unless ``login`` names another (a client beside the ground station: ``operator``, ``viewer``).
    The key comes from ``settings.bus_key()``: raises BusAuthError when an MQTT bus has none.
    ``client_id`` overrides ``settings.mqtt.client_id`` (give each vehicle its own);
    ``will`` is the MQTT last will (see ``lost_vehicle_will``). ``clock`` and ``rng`` are
    for tests. The in-process bus ignores ``client_id``, ``will`` and ``rng``.
    """
    key = settings.bus_key()
    policy = settings.auth.policy()
    if settings.kind == "inprocess":
        link = settings.link.link_model() if settings.link is not None else None
        return InProcessBus(
            link=link,
            clock=clock,
            queue_size=settings.queue_size,
            key=key,
            sender=sender,
            auth_policy=policy,
        )
    if key.insecure:
        logger.warning(
            "INSECURE BUS: messages to %s:%d are signed with a public key; anyone on the "
            "network can forge commands (--insecure-bus)",
            settings.mqtt.host,
            settings.mqtt.port,
        )
    mqtt = settings.mqtt
    username, password = broker_login(
        settings.access.credentials_file or mqtt.credentials_file,
        sender or Sender.ground(),
        user=login,
    )
    return MqttBus(
        mqtt.host,
        mqtt.port,
        key=key,
        sender=sender,
        auth_policy=policy,
        client_id=client_id or mqtt.client_id,
        username=username,
        password=password,
        tls=mqtt.tls,
        keepalive_s=mqtt.keepalive_s,
        connect_timeout_s=mqtt.connect_timeout_s,
        subscribe_timeout_s=mqtt.subscribe_timeout_s,
        reconnect_initial_s=mqtt.reconnect_initial_s,
        reconnect_max_s=mqtt.reconnect_max_s,
        qos=mqtt.qos,
        will=will,
        queue_size=settings.queue_size,
        clock=clock,
        rng=rng,
    )

"""MQTT bus: the mission's messages through a broker, riding out broker outages.

``MqttBus`` owns one background task (in its own task group) that keeps a connection to
the broker through aiomqtt: it connects, subscribes every live subscription, hands each
incoming message to the local subscriptions whose pattern matches it, and after losing the
broker reconnects with capped, jittered exponential backoff and subscribes again. While it
is disconnected, ``publish`` waits at most its ``timeout`` and then raises
``BusConnectionError``; nothing is queued for later, because a vehicle's step message is
worthless once the next step has started.

Entering the bus waits for the first connection (``connect_timeout_s``) and raises
``BusConnectionError`` if there is none; refused credentials fail at once, since retrying
cannot fix them. Later outages are ridden out in the background.

``connected``, ``wait_connected``/``wait_disconnected`` and ``last_message_s`` (when the
broker last delivered anything) tell a caller about outages and silence; the mission's
controllers need none of them, as they hold whenever no neighbour message has arrived for
their silence timeout, whatever the cause. A ``LastWill`` on the vehicle's status topic
tells the others when a vehicle drops off without saying goodbye.

Client ids: every bus appends a random suffix to the id it is given (one per bus, kept across
reconnects). The broker drops a connection when another one arrives with its id, and publishes
its will: a guessable id (``<name>-vehicle-2``) let anyone who can reach the broker knock a
vehicle off the bus and announce it lost. After a reconnect the bus publishes again the last
retained message it published on its will's topic, so that the will the broker published (and
retained) does not outlive the connection it was about; receivers treat a will as a drop-off, not
as final (``runner/process.py``). ``broker-config`` also binds ids to logins at the broker.

Broker setup: set ``set_tcp_nodelay true`` in mosquitto.conf. Without it mosquitto lets
Nagle's algorithm hold small messages to subscribers for up to a delayed-ACK period (40 ms
on Linux): on loopback the p99 latency of 8 Hz step messages drops from ~43 ms to ~3 ms
with it (bench/bus_bench.py). The client side sets TCP_NODELAY itself.

Every message is sealed before it goes to the broker and opened when it arrives
(``mission_runner.bus.auth``): forged, replayed, stale, oversized or malformed payloads never
reach a subscription; ``auth_counters`` counts them. The last will is sealed on every
connection. The key is required: ``open_bus`` resolves it (and refuses an MQTT bus without one
unless ``--insecure-bus``).

One connection per bus. Wildcard patterns are matched locally with ``topic_matches``; the
broker is asked once per distinct pattern. MQTT 3.1.1 is used: with it, mosquitto sends a
message matching several patterns of one client once, which is what local matching needs.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
import os
import random
import secrets
import socket
import ssl
import time
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from typing import Self, TypeVar

import aiomqtt
from aiomqtt.exceptions import MqttCodeError, MqttConnectError
from paho.mqtt.client import MQTTMessage

from mission_runner.bus.auth import AuthPolicy, BusKey, MessageAuth, Sender
from mission_runner.bus.base import DEFAULT_QUEUE_SIZE, Bus, Routes, Subscription
from mission_runner.bus.errors import BusConnectionError, BusTimeoutError
from mission_runner.bus.messages import VehicleStatus
from mission_runner.bus.paho_reader import guard_reader, max_packet_bytes
from mission_runner.bus.paho_writer import write_at_once
from mission_runner.bus.settings import TlsSettings
from mission_runner.bus.topics import Topics, validate_pattern, validate_topic
from mission_runner.clock import Clock, MonotonicClock
from mission_runner.records import ControllerState

_T = TypeVar("_T")
logger = logging.getLogger(__name__)

# CONNACK codes meaning "these credentials are not welcome" in MQTT 3.1.1 (4, 5) and as
# paho reports them (MQTT 5 reason codes 134 "bad user name or password", 135 "not
# authorized"). Retrying cannot fix them, so the first connection fails fast on them.
_AUTH_REFUSED_CODES = frozenset({4, 5, 134, 135})
#: Publishes awaiting their hand-over to the socket above which aiomqtt logs a warning.
PENDING_PUBLISHES_WARNING = 64


@dataclass(frozen=True, slots=True)
class LastWill:
    """What the broker publishes for this client if it vanishes without disconnecting."""

    topic: str
    payload: bytes
    retain: bool = True
    qos: int = 1

    def __post_init__(self) -> None:
        validate_topic(self.topic)
        if self.qos not in (0, 1, 2):
            raise ValueError(f"qos must be 0, 1 or 2, got {self.qos!r}")


def lost_vehicle_will(topics: Topics, vehicle_id: int, *, time_s: float) -> LastWill:
    """A retained ``VehicleStatus`` saying vehicle ``vehicle_id`` lost the bus.

    The payload is fixed when the bus opens, so ``time_s`` is that moment, not the loss.
    """
    status = VehicleStatus(
        vehicle_id=vehicle_id,
        time_s=time_s,
        state=ControllerState.LOST,
        step=0,
        tracking_ok=False,
        detail="connection to the bus lost (last will)",
    )
    return LastWill(topics.status(vehicle_id), status.to_payload(), retain=True, qos=1)


class Backoff:
    """Capped exponential backoff with jitter.

    The n-th delay (n = 0, 1, ...) is ``U(0.5, 1) * min(max_s, initial_s * 2**n)``: the
    jitter keeps vehicles that lost the broker together from reconnecting in lockstep.
    """

    def __init__(self, initial_s: float, max_s: float, rng: random.Random) -> None:
        if not 0.0 < initial_s <= max_s:
            raise ValueError(f"need 0 < initial_s <= max_s, got {initial_s}, {max_s}")
        self.initial_s = initial_s
        self.max_s = max_s
        self.attempts = 0
        self._rng = rng

    def next_delay_s(self) -> float:
        """The delay before the next attempt; each call counts one failed attempt."""
        ceiling_s = min(self.max_s, self.initial_s * 2.0 ** min(self.attempts, 60))
        self.attempts += 1
        return ceiling_s * self._rng.uniform(0.5, 1.0)

    def reset(self) -> None:
        """Start over after a successful connection."""
        self.attempts = 0


def default_client_id(prefix: str = "mission-runner") -> str:
    """A client id unique to this process and call (MQTT ids must not collide)."""
    return f"{prefix}-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


#: Random hex digits appended to every client id: 64 bits, not to be guessed over a network.
CLIENT_ID_SUFFIX_CHARS = 16


def unguessable_client_id(base: str) -> str:
    """``base`` with a random suffix: an id nobody can take over without having seen it (the
    broker drops a connection whose id another connection presents, and publishes its will)."""
    return f"{base}-{secrets.token_hex(CLIENT_ID_SUFFIX_CHARS // 2)}"


def _connack_code(exc: BaseException) -> int | None:
    if not isinstance(exc, MqttConnectError):
        return None
    rc = exc.rc
    value = getattr(rc, "value", rc)
    return value if isinstance(value, int) else None


async def _bounded(call: Awaitable[_T], timeout_s: float) -> _T:
    """An aiomqtt call made with ``timeout=math.inf``, bounded by ``timeout_s`` here instead:
    aiomqtt bounds its calls with ``asyncio.wait_for``, which on Python 3.11 drops a
    cancellation that arrives as the call completes, so that the cancelled caller runs on (a
    controller told to stop by the operator flew on to the end of the mission). Times out as
    aiomqtt would, with an :class:`aiomqtt.MqttError`."""
    try:
        async with asyncio.timeout(timeout_s):
            return await call
    except TimeoutError:
        raise aiomqtt.MqttError("Operation timed out") from None


def _abandon(client: aiomqtt.Client) -> None:
    """Close the socket of a client whose ``__aenter__`` did not complete.

    aiomqtt 2.x leaves the TCP socket open (reader registered, housekeeping task running)
    when ``__aenter__`` times out waiting for CONNACK or is cancelled after the TCP
    connect. Closing it through paho runs aiomqtt's socket-close callback, which removes
    the reader and cancels that task, so nothing leaks into the next attempt.
    """
    paho_client = getattr(client, "_client", None)
    close = getattr(paho_client, "_sock_close", None)
    if close is not None:
        close()


class _ClosingSSLSocket(ssl.SSLSocket):
    """An SSL socket that closes itself when its handshake fails.

    paho creates, wraps and handshakes the socket in one call and drops it unclosed when
    the handshake fails (e.g. an untrusted broker certificate); closing it here keeps
    every failed TLS attempt from leaking a file descriptor.
    """

    def do_handshake(self, block: bool = False) -> None:
        try:
            super().do_handshake(block)
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            raise
        except BaseException:
            self.close()
            raise


class MqttBus(Bus):
    """A bus through an MQTT broker (see the module docstring).

    Parameters mirror ``MqttSettings``; ``open_bus`` builds one from settings. ``key`` signs
    and checks every message, ``sender`` is whom this client signs as (None: each topic's
    owner), ``auth_policy`` the receiver's limits and ``wall_clock`` the UNIX time they are
    checked against. ``clock`` times reconnect delays and ``last_message_s``; ``rng`` draws the
    backoff jitter.

    Counters: ``connect_count`` (successful connections; reconnects are this minus one),
    ``failed_attempts`` (connections that failed or ended), ``published``, ``received``
    (messages from the broker, before local matching). ``last_error`` says why the last
    connection failed or ended.
    """

    def __init__(
        self,
        host: str,
        port: int = 1883,
        *,
        key: BusKey,
        sender: Sender | None = None,
        auth_policy: AuthPolicy | None = None,
        wall_clock: Callable[[], float] = time.time,
        client_id: str | None = None,
        username: str | None = None,
        password: str | None = None,
        tls: TlsSettings | None = None,
        keepalive_s: int = 5,
        connect_timeout_s: float = 5.0,
        subscribe_timeout_s: float = 5.0,
        reconnect_initial_s: float = 0.1,
        reconnect_max_s: float = 5.0,
        qos: int = 0,
        will: LastWill | None = None,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        clock: Clock | None = None,
        rng: random.Random | None = None,
    ) -> None:
        if qos not in (0, 1, 2):
            raise ValueError(f"qos must be 0, 1 or 2, got {qos!r}")
        self.host = host
        self.port = port
        self.endpoint = f"{host}:{port}"
        self.client_id = unguessable_client_id(client_id or default_client_id())
        self.auth = MessageAuth(key, auth_policy, endpoint=self.endpoint, wall_clock=wall_clock)
        self.sender = sender
        self.qos = qos
        self.keepalive_s = keepalive_s
        self.connect_timeout_s = connect_timeout_s
        self.subscribe_timeout_s = subscribe_timeout_s
        self.queue_size = queue_size
        self.will = will
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self._username = username
        self._password = password
        self._tls = tls
        self._ssl_context: ssl.SSLContext | None = None
        self._backoff = Backoff(reconnect_initial_s, reconnect_max_s, rng or random.Random())

        self.connect_count = 0
        self.failed_attempts = 0
        self.published = 0
        self.received = 0
        self.last_error: str | None = None
        self.last_message_s: float | None = None

        self._client: aiomqtt.Client | None = None
        self._connected = False
        self._fatal: BusConnectionError | None = None
        self._state = asyncio.Condition()
        self._subscriptions = Routes()
        self._patterns: collections.Counter[str] = collections.Counter()
        self._open = False
        self._closed = False
        # What the bus owns while entered (the connection task's group), unwound on exit.
        self._stack = contextlib.AsyncExitStack()
        self._connected_since_s: float | None = None
        # The last retained message published on the will's topic (payload, signer), published
        # again after a reconnect: the broker may have put the will in its place meanwhile.
        self._will_topic_retained: tuple[bytes, Sender | None] | None = None
        #: Messages of the connection being made, delivered once it is in place (see _deliver).
        self._held: list[MQTTMessage] | None = None

    def __repr__(self) -> str:
        state = "connected" if self._connected else "disconnected"
        return f"<MqttBus {self.client_id} -> {self.endpoint} {state}>"

    # Lifetime ---------------------------------------------------------------------------
    async def __aenter__(self) -> Self:
        if self._open or self._closed:
            raise RuntimeError("an MqttBus can be entered only once")
        if self._tls is not None:
            try:
                # Reads certificate files: keep that off the event loop.
                self._ssl_context = await asyncio.to_thread(self._tls.ssl_context)
                self._ssl_context.sslsocket_class = _ClosingSSLSocket
            except (OSError, ssl.SSLError) as exc:
                raise BusConnectionError(
                    self.endpoint,
                    f"cannot load the TLS files ({exc})",
                    hint="check bus.mqtt.tls: ca_file, cert_file and key_file must be "
                    "readable PEM files",
                ) from exc
        async with contextlib.AsyncExitStack() as stack:
            task_group = await stack.enter_async_context(asyncio.TaskGroup())
            runner = task_group.create_task(
                self._keep_connected(), name=f"mqtt bus {self.client_id} -> {self.endpoint}"
            )
            # Cancelling the runner disconnects gracefully (so the broker does not publish
            # the last will): see _session.
            stack.callback(runner.cancel)
            stack.push_async_callback(self._close)
            self._open = True
            failure = await self._first_connection()
            if failure is None:
                self._stack = stack.pop_all()
        if failure is not None:
            # Raised once the task group is closed, so that the caller gets this error
            # itself, not wrapped in an exception group.
            raise failure
        return self

    async def _first_connection(self) -> BusConnectionError | None:
        """Why the first connection failed, or None once connected."""
        try:
            await self._wait_until(
                lambda: self._connected or self._fatal is not None,
                self.connect_timeout_s,
                f"first connection to the MQTT broker at {self.endpoint}",
            )
        except BusTimeoutError:
            return BusConnectionError(
                self.endpoint,
                f"no connection within {self.connect_timeout_s:g} s "
                f"(last error: {self.last_error or 'none'})",
                hint="check that the broker runs and that bus.mqtt.host and "
                "bus.mqtt.port point at it",
            )
        if self._fatal is not None:
            return BusConnectionError(
                self._fatal.endpoint, self._fatal.reason, hint=self._fatal.hint
            )
        return None

    async def _close(self) -> None:
        """End every subscription and wake whoever waits on the connection state."""
        self._close_subscriptions()
        self._patterns.clear()
        await self._notify()

    # State ------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """Whether the bus is connected to the broker and its subscriptions are in place."""
        return self._connected

    async def _notify(self) -> None:
        async with self._state:
            self._state.notify_all()

    async def _wait_until(self, predicate: Callable[[], bool], timeout: float, what: str) -> None:
        try:
            async with asyncio.timeout(timeout), self._state:
                await self._state.wait_for(predicate)
        except TimeoutError:
            raise BusTimeoutError(what, timeout) from None

    async def wait_connected(self, *, timeout: float) -> None:
        """Wait until connected (subscriptions in place); BusTimeoutError after ``timeout``."""
        await self._wait_until(
            lambda: self._connected or self._closed,
            timeout,
            f"connection to the MQTT broker at {self.endpoint}",
        )
        if not self._connected:
            raise BusConnectionError(self.endpoint, "the bus is closed")

    async def wait_disconnected(self, *, timeout: float) -> None:
        """Wait until the connection is lost; BusTimeoutError after ``timeout``."""
        await self._wait_until(
            lambda: not self._connected,
            timeout,
            f"loss of the connection to {self.endpoint}",
        )

    # Connection task --------------------------------------------------------------------
    def _new_client(self) -> aiomqtt.Client:
        will = None
        if self.will is not None:
            # Signed afresh for every connection: receivers accept each will once.
            signer = self.sender or Sender.for_topic(self.will.topic)
            payload = self.auth.seal(signer, self.will.topic, self.will.payload, will=True)
            will = aiomqtt.Will(
                self.will.topic, payload, qos=self.will.qos, retain=self.will.retain
            )
        client = aiomqtt.Client(
            self.host,
            self.port,
            username=self._username,
            password=self._password,
            identifier=self.client_id,
            will=will,
            clean_session=True,
            keepalive=self.keepalive_s,
            timeout=self.connect_timeout_s,
            tls_context=self._ssl_context,
            # Without hostname checking in the context, paho would call the deprecated
            # ssl.match_hostname; tls_insecure tells it the check is off on purpose.
            tls_insecure=(not self._tls.check_hostname) if self._tls is not None else None,
            # Bounds, not expected loads: the runner drains incoming messages at once and
            # publishes only while connected.
            max_queued_incoming_messages=100_000,
            max_queued_outgoing_messages=self.queue_size,
            # Step messages are small and due now: Nagle's algorithm would hold them back
            # for up to a delayed-ACK period (40 ms on Linux), a third of a step.
            socket_options=((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),),
            logger=logging.getLogger(f"{__name__}.client"),
        )
        # aiomqtt warns above 10 publishes awaiting their hand-over; a range aid hands a step's
        # dozen over at once, which is no backlog.
        client.pending_calls_threshold = PENDING_PUBLISHES_WARNING
        self._held = []
        client._client.on_message = self._deliver  # see _deliver; the guard below wraps it
        # A packet too long to be a message is skipped as it arrives, never read into memory in
        # the loop the controller runs in (four 64 MiB payloads stalled vehicles for seconds),
        # and waiting packets are read in batches (see paho_reader.py).
        guard_reader(
            client._client,  # aiomqtt's paho client: see paho_reader.py
            max_packet_bytes(self.auth.policy.max_message_bytes),
            self.auth.skipped_oversized,
            admits=self.auth.admits,
        )
        # A publish the socket takes whole completes in its call, not three loop turns later.
        write_at_once(client)
        return client

    async def _keep_connected(self) -> None:
        while True:
            self._connected_since_s = None
            try:
                await self._session(self._new_client())
                reason = "the broker closed the connection"
            except (aiomqtt.MqttError, OSError) as exc:
                reason = str(exc) or type(exc).__name__
                if exc.__cause__ is not None:
                    reason += f" ({exc.__cause__})"
                code = _connack_code(exc)
                if code in _AUTH_REFUSED_CODES and self.connect_count == 0:
                    self._fatal = BusConnectionError(
                        self.endpoint,
                        f"the broker refused the credentials of {self.client_id!r} ({exc})",
                        hint="check the broker login: --bus-credentials (or bus.mqtt."
                        "credentials_file, or MISSION_BUS_USERNAME/MISSION_BUS_PASSWORD)",
                    )
                    self.last_error = reason
                    await self._notify()
                    return
            self.last_error = reason
            self.failed_attempts += 1
            if (
                self._connected_since_s is not None
                and self.clock.now_s() - self._connected_since_s >= self._backoff.max_s
            ):
                # Only a connection that held for a while resets the backoff: a broker that
                # accepts and drops at once (e.g. another client took over this client id)
                # must not be hammered every reconnect_initial_s.
                self._backoff.reset()
            delay_s = self._backoff.next_delay_s()
            logger.warning(
                "MQTT broker %s unavailable (%s); reconnecting in %.2f s (attempt %d)",
                self.endpoint,
                reason,
                delay_s,
                self._backoff.attempts,
            )
            await self.clock.sleep(delay_s)

    async def _session(self, client: aiomqtt.Client) -> None:
        """One connection: connect, subscribe, dispatch until the connection ends."""
        # A task of its own only so that it can be shielded; this session awaits it on every
        # path, and its failure (a refused or timed-out connection) is this session's.
        entering = asyncio.get_running_loop().create_task(
            client.__aenter__(), name=f"mqtt connect {self.client_id} -> {self.endpoint}"
        )
        try:
            await asyncio.shield(entering)
        except asyncio.CancelledError:
            # Closing while connecting: let the attempt end (it is bounded by the client's
            # timeout) so that its socket can be closed rather than leaked.
            await asyncio.wait({entering})
            error = None if entering.cancelled() else entering.exception()
            if entering.cancelled() or error is not None:
                if error is not None:
                    logger.debug("connecting to %s while closing failed: %r", self.endpoint, error)
                _abandon(client)
            else:
                await self._leave(client)
            raise
        except BaseException:
            _abandon(client)
            raise
        try:
            await self._run_connected(client)
        finally:
            await self._leave(client)

    async def _leave(self, client: aiomqtt.Client) -> None:
        if self._client is client:
            self._client = None
            self._connected = False
            await self._notify()
        try:
            await client.__aexit__(None, None, None)
        except aiomqtt.MqttError as exc:
            logger.debug("disconnecting from %s did not complete cleanly: %s", self.endpoint, exc)
            _abandon(client)

    async def _run_connected(self, client: aiomqtt.Client) -> None:
        self._client = client
        patterns = list(self._patterns)
        if patterns:
            codes = await _bounded(
                client.subscribe([(pattern, self.qos) for pattern in patterns], timeout=math.inf),
                self.subscribe_timeout_s,
            )
            for pattern, code in zip(patterns, codes, strict=False):
                if getattr(code, "is_failure", False) or code == 0x80:
                    logger.error(
                        "the broker at %s refused the subscription to %r (ACL?)",
                        self.endpoint,
                        pattern,
                    )
        await self._restore_will_topic(client)
        self.connect_count += 1
        self._connected_since_s = self.clock.now_s()
        self._connected = True
        await self._notify()
        logger.info(
            "connected to MQTT broker %s as %s (%d subscription pattern(s))",
            self.endpoint,
            self.client_id,
            len(patterns),
        )
        held, self._held = self._held, None
        for message in held or ():
            self._deliver_now(message)
        # Messages arrive through _deliver from here on; the connection ends as aiomqtt's
        # message iterator would end it.
        await asyncio.wait({client._disconnected})
        raise aiomqtt.MqttError("Disconnected during message iteration") from (
            client._disconnected.exception()
        )

    def _deliver(self, _client: object, _userdata: object, message: MQTTMessage) -> None:
        """paho's ``on_message``, in the event loop's thread as paho reads the socket: what
        comes before the connection is in place (retained messages as the subscriptions are
        made) waits until then, in order.

        aiomqtt would queue the message and its iterator wake the connection task for it (a
        task and an ``asyncio.wait`` a message, the most of what a vehicle process's event
        loop ran in flight); handed on here, the subscriptions' readers are the only ones
        woken, once for all a read brought them."""
        if self._held is not None:
            self._held.append(message)
        else:
            self._deliver_now(message)

    def _deliver_now(self, message: MQTTMessage) -> None:
        self.received += 1
        self.last_message_s = self.clock.now_s()
        topic, payload = message.topic, message.payload
        if not isinstance(payload, bytes):
            payload = bytes(payload)
        body = self.auth.open(topic, payload, retained=bool(message.retain))
        if body is None:
            return  # dropped and counted: never handed to a subscription
        for subscription in self._subscriptions.matching(topic):
            subscription.offer(topic, body)

    async def _restore_will_topic(self, client: aiomqtt.Client) -> None:
        """Publish again, before anything else of this connection, the last retained message
        this bus published on its will's topic: if the previous connection ended without a
        goodbye (a network drop, or another connection with this client id), the broker has
        published and retained the will in its place, though this client goes on."""
        if self.will is None or self._will_topic_retained is None:
            return
        payload, sender = self._will_topic_retained
        topic = self.will.topic
        sealed = self._seal(topic, payload, retain=True, sender=sender)
        await _bounded(
            client.publish(topic, sealed, qos=self.will.qos, retain=True, timeout=math.inf),
            self.subscribe_timeout_s,
        )
        logger.info("reconnected to %s: published %s again over the will", self.endpoint, topic)

    # Publish / subscribe ----------------------------------------------------------------
    def _check_open(self, action: str) -> None:
        if not self._open:
            state = "closed" if self._closed else "not entered yet"
            raise BusConnectionError(
                self.endpoint,
                f"cannot {action}: the bus is {state}",
                hint="use it inside `async with`",
            )

    async def publish(
        self,
        topic: str,
        payload: bytes,
        *,
        retain: bool = False,
        timeout: float,
        sender: Sender | None = None,
    ) -> None:
        validate_topic(topic)
        self._check_open(f"publish to {topic!r}")
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            if not self._connected:
                await self._wait_to_publish(topic, deadline - loop.time(), timeout)
            client = self._client
            assert client is not None  # connected implies a client
            # Sealed here, with no await before the client queues it: sequence numbers go
            # out in the order they were drawn.
            sealed = self._seal(topic, bytes(payload), retain=retain, sender=sender)
            try:
                await _bounded(
                    client.publish(topic, sealed, qos=self.qos, retain=retain, timeout=math.inf),
                    max(deadline - loop.time(), 0.001),
                )
                if retain and self.will is not None and topic == self.will.topic:
                    self._will_topic_retained = (bytes(payload), sender)
                break
            except MqttCodeError as exc:
                # The connection died under us before the runner noticed: wait for it to
                # notice (and maybe reconnect) within what is left of the timeout.
                self.last_error = str(exc)
                dead_client = client
                await self._wait_to_publish(
                    topic,
                    deadline - loop.time(),
                    timeout,
                    lambda: self._client is not dead_client,  # noqa: B023 (used at once)
                )
            except aiomqtt.MqttError as exc:
                raise BusConnectionError(
                    self.endpoint,
                    f"publishing to {topic!r} was not acknowledged ({exc})",
                    hint="the broker is slow or the connection is dying; drop this message "
                    "or publish again later",
                ) from exc
        self.published += 1

    async def _wait_to_publish(
        self,
        topic: str,
        remaining_s: float,
        timeout: float,
        changed: Callable[[], bool] | None = None,
    ) -> None:
        def ready() -> bool:
            return self._closed or (self._connected and (changed is None or changed()))

        try:
            await self._wait_until(ready, max(remaining_s, 0.0), f"publish to {topic!r}")
        except BusTimeoutError:
            raise BusConnectionError(
                self.endpoint,
                f"not connected; gave up publishing to {topic!r} after {timeout:g} s "
                f"(last error: {self.last_error or 'none'})",
                hint="the bus keeps reconnecting in the background; drop this message "
                "or publish again later",
            ) from None
        self._check_open(f"publish to {topic!r}")

    async def _broker_subscribe(self, client: aiomqtt.Client, pattern: str, timeout: float) -> None:
        try:
            result = await _bounded(
                client.subscribe(pattern, qos=self.qos, timeout=math.inf), timeout
            )
        except MqttCodeError as exc:
            # Not connected any more: the runner subscribes again after reconnecting.
            logger.debug("subscription to %r deferred to the next connection: %s", pattern, exc)
            return
        except aiomqtt.MqttError:
            if self._client is not client:
                return  # the connection dropped meanwhile; resubscribed on reconnect
            raise BusTimeoutError(
                f"broker acknowledgement of the subscription to {pattern!r}",
                timeout,
                hint=f"the broker at {self.endpoint} is connected but slow or stuck",
            ) from None
        if any(getattr(code, "is_failure", False) or code == 0x80 for code in result):
            raise BusConnectionError(
                self.endpoint,
                f"the broker refused the subscription to {pattern!r}",
                hint="check the broker's access control list for this user",
            )

    @contextlib.asynccontextmanager
    async def _subscription(
        self, pattern: str, queue_size: int | None, timeout: float | None
    ) -> AsyncIterator[Subscription]:
        validate_pattern(pattern)
        self._check_open(f"subscribe to {pattern!r}")
        subscription = Subscription(
            pattern, queue_size=queue_size or self.queue_size, endpoint=self.endpoint
        )
        self._subscriptions.append(subscription)
        self._patterns[pattern] += 1
        try:
            client = self._client
            if self._patterns[pattern] == 1 and client is not None:
                await self._broker_subscribe(
                    client, pattern, timeout if timeout is not None else self.subscribe_timeout_s
                )
            yield subscription
        finally:
            subscription.close()
            with contextlib.suppress(ValueError):
                self._subscriptions.remove(subscription)
            if self._patterns.get(pattern, 0) > 0:
                self._patterns[pattern] -= 1
                if self._patterns[pattern] == 0:
                    del self._patterns[pattern]
                    await self._broker_unsubscribe(pattern)

    async def _broker_unsubscribe(self, pattern: str) -> None:
        client = self._client
        if client is None or not self._open:
            return
        try:
            await _bounded(client.unsubscribe(pattern, timeout=math.inf), self.subscribe_timeout_s)
        except aiomqtt.MqttError as exc:
            # Harmless: local matching ignores messages no subscription wants.
            logger.debug("unsubscribing from %r failed: %s", pattern, exc)

    def subscribe(
        self, pattern: str, *, queue_size: int | None = None, timeout: float | None = None
    ) -> contextlib.AbstractAsyncContextManager[Subscription]:
        return self._subscription(pattern, queue_size, timeout)

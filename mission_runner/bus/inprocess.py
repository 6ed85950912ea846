"""In-process bus: every vehicle task of one event loop talks through shared queues.

The default bus: no broker, no sockets. The numeric simulator and scenario tests run all
vehicle controllers in one process on it. An optional ``LinkModel`` delays and drops
deliveries (seeded, and timed by an injected ``Clock``) so tests can check step alignment
under a bad network deterministically.

Semantics match ``MqttBus`` with QoS 0: MQTT wildcard patterns (``topic_matches``),
retained messages handed to new subscribers, per-subscription drop-oldest queues. Messages are
sealed and opened as on MQTT (``mission_runner.bus.auth``), with a random key of the process
unless one is given: nothing outside the process can reach this bus, but the same code path
runs.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import heapq
import itertools
import logging
import math
import random
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Self

from mission_runner.bus.auth import AuthPolicy, BusKey, MessageAuth, Sender
from mission_runner.bus.base import DEFAULT_QUEUE_SIZE, Bus, BusClient, Routes, Subscription
from mission_runner.bus.errors import BusConnectionError
from mission_runner.bus.topics import topic_matches, validate_pattern, validate_topic
from mission_runner.clock import Clock, MonotonicClock

logger = logging.getLogger(__name__)

ENDPOINT = "in-process"


@dataclass(frozen=True, slots=True)
class LinkModel:
    """A lossy, late network between every publisher and every subscription.

    Each delivery of a message to a matching subscription is dropped with probability
    ``loss_probability``, otherwise delivered ``latency_s + U(0, jitter_s)`` seconds after
    publishing, on the bus's clock. The draws for the n-th delivery on a topic to a
    subscription depend only on ``seed``, the topic, n, the subscription's pattern and the
    client it belongs to (:meth:`InProcessBus.as_sender`), never on how the publishers' or
    subscribers' tasks interleave, so a run is reproducible. Unless ``reorder`` is True, a
    message never overtakes an earlier one on the same topic to the same subscription (MQTT
    keeps a publisher's order per topic); messages of different topics, i.e. of different
    vehicles, may overtake.
    """

    latency_s: float = 0.0
    jitter_s: float = 0.0
    loss_probability: float = 0.0
    seed: int = 0
    reorder: bool = False

    def __post_init__(self) -> None:
        for name in ("latency_s", "jitter_s"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0.0:
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        if not 0.0 <= self.loss_probability <= 1.0:
            raise ValueError(f"loss_probability must be in [0, 1], got {self.loss_probability!r}")

    @property
    def delays(self) -> bool:
        """Whether deliveries are late at all (else they are immediate)."""
        return self.latency_s > 0.0 or self.jitter_s > 0.0


class InProcessBus(Bus):
    """A bus inside one event loop (see the module docstring).

    ``publish`` never waits: delivery is immediate (or scheduled by the link model) and a
    full subscription queue drops its oldest message. ``timeout`` is accepted for interface
    compatibility. Counters: ``published``, ``lost`` (deliveries the link model dropped).
    """

    endpoint = ENDPOINT

    def __init__(
        self,
        *,
        link: LinkModel | None = None,
        clock: Clock | None = None,
        queue_size: int = DEFAULT_QUEUE_SIZE,
        key: BusKey | None = None,
        sender: Sender | None = None,
        auth_policy: AuthPolicy | None = None,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.auth = MessageAuth(
            key or BusKey.generate(), auth_policy, endpoint=ENDPOINT, wall_clock=wall_clock
        )
        self.sender = sender
        self.link = link
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        self.queue_size = queue_size
        self.published = 0
        self.lost = 0
        self._subscriptions = Routes()
        # Which client made each subscription, and how many deliveries each (client, pattern,
        # topic) has had: the link model's draws are keyed on them.
        self._clients: dict[Subscription, str] = {}
        self._deliveries: collections.Counter[tuple[str, str, str]] = collections.Counter()
        self._retained: dict[str, bytes] = {}
        self._open = False
        self._closed = False
        # What the bus owns while entered (the delivery task's group), unwound on exit.
        self._stack = contextlib.AsyncExitStack()
        self._task_group: asyncio.TaskGroup | None = None
        # Delayed deliveries: (due time, publish sequence, subscription, topic, payload).
        self._pending: list[tuple[float, int, Subscription, str, bytes]] = []
        self._sequence = itertools.count()
        # Due time of the latest delivery per (subscription, topic), to keep their order.
        self._last_due: dict[tuple[Subscription, str], float] = {}
        self._scheduled = asyncio.Event()
        self._sleeper: asyncio.Task[None] | None = None
        self._sleeping_until = math.inf

    async def __aenter__(self) -> Self:
        if self._open or self._closed:
            raise RuntimeError("an InProcessBus can be entered only once")
        async with contextlib.AsyncExitStack() as stack:
            stack.callback(self._pending.clear)
            if self.link is not None and self.link.delays:
                self._task_group = await stack.enter_async_context(asyncio.TaskGroup())
                delivery = self._task_group.create_task(
                    self._deliver_late(), name="in-process bus delivery"
                )
                # The delivery loop only ends by cancellation; messages still in flight are
                # lost, as they would be in a network that goes down.
                stack.callback(delivery.cancel)
            stack.callback(self._close_subscriptions)
            self._stack = stack.pop_all()
        self._open = True
        return self

    def _check_open(self, action: str) -> None:
        if not self._open:
            state = "closed" if self._closed else "not entered yet"
            raise BusConnectionError(
                ENDPOINT, f"cannot {action}: the bus is {state}", hint="use it inside `async with`"
            )

    @property
    def in_flight(self) -> int:
        """Deliveries delayed by the link model and not yet handed to their subscription."""
        return len(self._pending)

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
        sealed = self._seal(topic, bytes(payload), retain=retain, sender=sender)
        if not sealed:
            # MQTT's "clear the retained value": no message, so nothing to open or deliver (a
            # receiver drops an empty payload, see MessageAuth.open).
            if retain:
                self._retained.pop(topic, None)
            self.published += 1
            return
        # One receiver (this bus) opens each message once, as an MQTT client does on arrival;
        # what is stored and delivered is the checked body.
        opened = self.auth.open(topic, sealed)
        if opened is None:
            return
        payload = opened
        self.published += 1
        if retain:
            self._retained[topic] = payload
        for subscription in self._subscriptions.matching(topic):
            self._deliver(subscription, topic, payload)

    def _deliver(self, subscription: Subscription, topic: str, payload: bytes) -> None:
        link = self.link
        if link is None:
            subscription.offer(topic, payload)
            return
        client = self._clients.get(subscription, "")
        n = self._deliveries[client, subscription.pattern, topic]
        self._deliveries[client, subscription.pattern, topic] = n + 1
        draws = random.Random(f"{link.seed}/{client}/{subscription.pattern}/{topic}/{n}")
        lost = draws.random() < link.loss_probability
        jitter_s = draws.uniform(0.0, link.jitter_s)
        if lost:
            self.lost += 1
            return
        if not link.delays:
            subscription.offer(topic, payload)
            return
        due_s = self.clock.now_s() + link.latency_s + jitter_s
        if not link.reorder:
            key = (subscription, topic)
            due_s = max(due_s, self._last_due.get(key, -math.inf))
            self._last_due[key] = due_s
        heapq.heappush(self._pending, (due_s, next(self._sequence), subscription, topic, payload))
        self._scheduled.set()
        if due_s < self._sleeping_until and self._sleeper is not None:
            # The delivery loop sleeps until a later message; wake it to reschedule.
            self._sleeper.cancel()

    async def _deliver_late(self) -> None:
        while True:
            now_s = self.clock.now_s()
            while self._pending and self._pending[0][0] <= now_s:
                _, _, subscription, topic, payload = heapq.heappop(self._pending)
                subscription.offer(topic, payload)
            if not self._pending:
                self._scheduled.clear()
                await self._scheduled.wait()
                continue
            self._sleeping_until = self._pending[0][0]
            assert self._task_group is not None
            sleeper = self._task_group.create_task(
                self.clock.sleep(self._sleeping_until - now_s), name="in-process bus link delay"
            )
            self._sleeper = sleeper
            try:
                await sleeper
            except asyncio.CancelledError:
                # _deliver cancels the sleeper to wake this loop for an earlier message; a
                # cancellation of this loop itself (pending on its task) goes on.
                current = asyncio.current_task()
                if current is None or current.cancelling():
                    raise
            finally:
                sleeper.cancel()
                self._sleeper = None
                self._sleeping_until = math.inf

    @contextlib.asynccontextmanager
    async def _subscription(
        self, pattern: str, queue_size: int | None, client_id: str = ""
    ) -> AsyncIterator[Subscription]:
        validate_pattern(pattern)
        self._check_open(f"subscribe to {pattern!r}")
        subscription = Subscription(
            pattern, queue_size=queue_size or self.queue_size, endpoint=ENDPOINT
        )
        for topic, payload in self._retained.items():
            if topic_matches(pattern, topic):
                subscription.offer(topic, payload)
        self._subscriptions.append(subscription)
        self._clients[subscription] = client_id
        try:
            yield subscription
        finally:
            subscription.close()
            with contextlib.suppress(ValueError):
                self._subscriptions.remove(subscription)
            self._clients.pop(subscription, None)
            for key in [key for key in self._last_due if key[0] is subscription]:
                del self._last_due[key]

    def subscribe(
        self, pattern: str, *, queue_size: int | None = None, timeout: float | None = None
    ) -> contextlib.AbstractAsyncContextManager[Subscription]:
        return self._subscription(pattern, queue_size)

    def as_sender(self, sender: Sender) -> InProcessClient:
        """This bus, publishing as ``sender`` (one member of the swarm of this process), whose
        subscriptions are ``sender``'s own to the link model, as one MQTT client's are."""
        return InProcessClient(self, sender)


class InProcessClient(BusClient):
    """One member of an :class:`InProcessBus` (a vehicle's controller, say): it meets its own
    losses and delays, drawn the same whatever order the members subscribe in."""

    bus: InProcessBus

    def subscribe(
        self, pattern: str, *, queue_size: int | None = None, timeout: float | None = None
    ) -> contextlib.AbstractAsyncContextManager[Subscription]:
        return self.bus._subscription(pattern, queue_size, str(self.sender))

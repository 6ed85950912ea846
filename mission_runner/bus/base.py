"""The bus interface every implementation offers, and the subscription both share.

A bus moves ``(topic, payload)`` pairs between the tasks of a mission: one vehicle
controller per vehicle, sensor drivers, the ground station. ``InProcessBus`` does it inside
one event loop; ``MqttBus`` through an MQTT broker. Both:

- are async context managers that own their background tasks;
- publish with a bounded wait (``timeout=`` is required) that ends in a typed error;
- hand each subscription the messages whose topic matches its MQTT pattern (``+``, ``#``),
  in arrival order, through a bounded queue that drops the oldest message when a slow
  consumer falls behind (counted in ``Subscription.dropped``), so a publisher never blocks
  on a slow subscriber and memory stays bounded.

Every payload is sealed on the way out and opened on the way in (``mission_runner.bus.auth``):
a subscription only ever sees message bodies that carried a valid signature of a sender allowed
on their topic, fresh and not seen before. A bus signs as its ``sender``; a bus that several
senders share (one process running the whole swarm in-process) hands each its own
``as_sender`` view.

Usage::

    async with bus.subscribe(topics.all_steps()) as steps:
        await bus.publish_message(topics.step(1), message, timeout=0.05)
        topic, step = await steps.receive_message(StepMessage, timeout=0.125)
"""

from __future__ import annotations

import abc
import asyncio
import collections
import contextlib
import logging
from collections.abc import AsyncIterator, Iterator
from contextlib import AbstractAsyncContextManager
from types import TracebackType
from typing import Generic, Self, TypeVar

from mission_runner.bus.auth import AuthCounters, MessageAuth, Sender
from mission_runner.bus.errors import BusConnectionError, BusTimeoutError, MessageDecodeError
from mission_runner.bus.messages import Message
from mission_runner.bus.topics import MATCH_CACHE_SIZE, topic_matches

logger = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)

#: Payloads whose decoded message is remembered (:data:`_decoded`).
DECODED_CACHE_SIZE = 256


class _DecodedMessages:
    """``message_type.from_payload(payload)``, remembered for the last ``size`` payloads: the
    in-process bus hands one payload to every subscription to its topic (a step message to each
    vehicle), and decoding and validating it again for each is most of what receiving costs the
    controllers. A message is deeply immutable (a frozen dataclass of numbers, strings, enums and
    tuples), so one decoded message can go to all. A publisher leaves the message it encoded
    (:meth:`remember`), so that a receiver in its own process does not decode it at all: the
    payload is that message's own encoding, which decodes to an equal message. Errors are not
    remembered: each subscription counts its own."""

    def __init__(self, size: int) -> None:
        self._size = size
        self._messages: dict[tuple[type[Message], bytes], Message] = {}

    def __call__(self, message_type: type[Message], payload: bytes) -> Message:
        found = self._messages.get((message_type, payload))
        if found is None:
            found = message_type.from_payload(payload)
            self.remember(found, payload)
        return found

    def remember(self, message: Message, payload: bytes) -> None:
        """``message`` is what ``payload`` decodes to (it is ``message.to_payload()``)."""
        messages = self._messages
        if len(messages) >= self._size:
            del messages[next(iter(messages))]  # the oldest: a payload's receivers come at once
        messages[type(message), payload] = message


_decoded = _DecodedMessages(DECODED_CACHE_SIZE)


DEFAULT_QUEUE_SIZE = 256
"""Messages a subscription holds before dropping the oldest: 16 vehicles x 8 Hz x 2 s."""


class Subscription:
    """Messages matching ``pattern``, oldest first, in a bounded drop-oldest queue.

    Made by ``Bus.subscribe``; valid inside its ``async with`` block. Iterating with
    ``async for topic, payload in subscription`` ends when the subscription or its bus
    closes. ``receive`` waits at most ``timeout`` seconds.

    Counters: ``received`` (messages that matched), ``dropped`` (oldest messages discarded
    because the queue was full), ``decode_errors`` (payloads ``receive_message`` skipped).
    """

    def __init__(self, pattern: str, *, queue_size: int, endpoint: str) -> None:
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.pattern = pattern
        self.queue_size = queue_size
        self.received = 0
        self.dropped = 0
        self.decode_errors = 0
        self._endpoint = endpoint
        self._items: collections.deque[tuple[str, bytes]] = collections.deque()
        self._nonempty = asyncio.Event()
        self._closed = False

    def __repr__(self) -> str:
        return (
            f"<Subscription {self.pattern!r} queued={len(self._items)} "
            f"received={self.received} dropped={self.dropped}>"
        )

    @property
    def closed(self) -> bool:
        """Whether no more messages will arrive (subscription exited or bus closed)."""
        return self._closed

    def __len__(self) -> int:
        """Messages waiting to be received."""
        return len(self._items)

    def offer(self, topic: str, payload: bytes) -> None:
        """Queue a message (bus side). Never blocks: drops the oldest when full."""
        if self._closed:
            return
        if len(self._items) >= self.queue_size:
            self._items.popleft()
            self.dropped += 1
            if self.dropped == 1 or self.dropped % 1000 == 0:
                logger.warning(
                    "subscription %r is not keeping up: dropped %d oldest message(s)",
                    self.pattern,
                    self.dropped,
                )
        self._items.append((topic, payload))
        self.received += 1
        self._nonempty.set()

    def close(self) -> None:
        """Stop accepting messages and wake waiting receivers (bus side)."""
        self._closed = True
        self._nonempty.set()

    def poll(self) -> tuple[str, bytes] | None:
        """The oldest queued message, or None if none is queued. Never waits."""
        if not self._items:
            return None
        return self._items.popleft()

    def drain_messages(self, message_type: type[M]) -> list[tuple[str, M]]:
        """Every queued message decoded as ``message_type``, oldest first. Never waits.

        For a controller that collects what arrived by a step's deadline. Payloads that do
        not decode are logged, counted in ``decode_errors`` and skipped.
        """
        drained: list[tuple[str, M]] = []
        while self._items:
            topic, payload = self._items.popleft()
            decoded = self._decode(message_type, topic, payload)
            if decoded is not None:
                drained.append((topic, decoded))
        return drained

    async def _next(self) -> tuple[str, bytes] | None:
        """The oldest message, waiting as long as needed; None once closed and drained."""
        while not self._items:
            if self._closed:
                return None
            self._nonempty.clear()
            await self._nonempty.wait()
        return self._items.popleft()

    async def receive(self, *, timeout: float) -> tuple[str, bytes]:
        """The oldest ``(topic, payload)``, waiting at most ``timeout`` seconds.

        Raises BusTimeoutError if nothing arrives in time and BusConnectionError if the
        subscription is closed and drained.
        """
        try:
            async with asyncio.timeout(timeout):
                item = await self._next()
        except TimeoutError:
            raise BusTimeoutError(
                f"receive on {self.pattern!r}",
                timeout,
                hint="no matching message arrived; the publishers may be silent",
            ) from None
        if item is None:
            raise BusConnectionError(self._endpoint, f"subscription {self.pattern!r} is closed")
        return item

    async def receive_message(self, message_type: type[M], *, timeout: float) -> tuple[str, M]:
        """The oldest message decoded as ``message_type``, within ``timeout`` seconds overall.

        Payloads that do not decode are logged, counted in ``decode_errors`` and skipped.
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            try:
                topic, payload = await self.receive(timeout=max(deadline - loop.time(), 0.0))
            except BusTimeoutError:
                raise BusTimeoutError(
                    f"receive of a {message_type.__name__} on {self.pattern!r}", timeout
                ) from None
            decoded = self._decode(message_type, topic, payload)
            if decoded is not None:
                return topic, decoded

    def _decode(self, message_type: type[M], topic: str, payload: bytes) -> M | None:
        if not payload:
            return None  # MQTT's "retained value cleared": no message, not an error
        try:
            if type(payload) is bytes:
                decoded: Message = _decoded(message_type, payload)
                return decoded  # type: ignore[return-value]  # of message_type, as cached
            return message_type.from_payload(payload)
        except MessageDecodeError as exc:
            self.decode_errors += 1
            logger.warning("skipping a message on %s: %s", topic, exc)
            return None

    def __aiter__(self) -> AsyncIterator[tuple[str, bytes]]:
        return self

    async def __anext__(self) -> tuple[str, bytes]:
        item = await self._next()
        if item is None:
            raise StopAsyncIteration
        return item

    def messages(self, message_type: type[M]) -> AsyncIterator[tuple[str, M]]:
        """Iterate ``(topic, message)`` decoded as ``message_type``, skipping bad payloads."""
        return _TypedMessages(self, message_type)


class _TypedMessages(Generic[M]):
    def __init__(self, subscription: Subscription, message_type: type[M]) -> None:
        self._subscription = subscription
        self._message_type = message_type

    async def __anext__(self) -> tuple[str, M]:
        while True:
            item = await self._subscription._next()
            if item is None:
                raise StopAsyncIteration
            decoded = self._subscription._decode(self._message_type, *item)
            if decoded is not None:
                return item[0], decoded

    def __aiter__(self) -> Self:
        return self


class Routes:
    """A bus's live subscriptions, and which of them each topic reaches.

    The subscriptions that match a topic are worked out once and remembered until a subscription
    comes or goes: a swarm publishes the same few topics every step to many subscriptions, and
    matching each against every pattern on every publish grew with the swarm squared. At most
    ``MATCH_CACHE_SIZE`` topics are remembered (a flood of made-up topics only starts it over).
    """

    def __init__(self) -> None:
        self._subscriptions: list[Subscription] = []
        self._by_topic: dict[str, tuple[Subscription, ...]] = {}

    def __iter__(self) -> Iterator[Subscription]:
        return iter(list(self._subscriptions))

    def __len__(self) -> int:
        return len(self._subscriptions)

    def append(self, subscription: Subscription) -> None:
        self._subscriptions.append(subscription)
        self._by_topic.clear()

    def remove(self, subscription: Subscription) -> None:
        """Forget ``subscription``; ValueError if it is not here (as ``list.remove``)."""
        self._subscriptions.remove(subscription)
        self._by_topic.clear()

    def clear(self) -> None:
        self._subscriptions.clear()
        self._by_topic.clear()

    def matching(self, topic: str) -> tuple[Subscription, ...]:
        """The subscriptions whose pattern matches ``topic``, in subscription order."""
        found = self._by_topic.get(topic)
        if found is None:
            found = tuple(s for s in self._subscriptions if topic_matches(s.pattern, topic))
            if len(self._by_topic) >= MATCH_CACHE_SIZE:
                self._by_topic.clear()
            self._by_topic[topic] = found
        return found


class Bus(abc.ABC):
    """A publish/subscribe message bus with MQTT topic semantics.

    Use as ``async with bus:``; publishing or subscribing outside that block raises
    BusConnectionError.
    """

    endpoint: str
    """Where the bus connects, for error messages (``"host:port"`` or ``"in-process"``)."""

    auth: MessageAuth
    """Seals what this bus publishes and opens what it receives; ``auth.counters`` says how
    many received messages were accepted and dropped, by reason."""

    sender: Sender | None
    """Whom this bus signs as; None: the owner of each topic (``Sender.for_topic``), for a bus
    that speaks for the whole swarm of one process."""

    _subscriptions: Routes
    _open: bool
    _closed: bool
    _stack: contextlib.AsyncExitStack
    """What entering set up (task group, tasks to cancel, subscriptions to close), in order."""

    def _close_subscriptions(self) -> None:
        """Mark the bus closed and end every live subscription (their iterations stop)."""
        self._open = False
        self._closed = True
        for subscription in self._subscriptions:
            subscription.close()
        self._subscriptions.clear()

    @abc.abstractmethod
    async def __aenter__(self) -> Self:
        """Start the bus; what it owns goes on ``_stack``, unwound if start-up fails."""

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self._stack.__aexit__(exc_type, exc, tb)

    @property
    def auth_counters(self) -> AuthCounters:
        """Received messages accepted and dropped (forged, replayed, ...), by reason."""
        return self.auth.counters

    def _seal(self, topic: str, payload: bytes, *, retain: bool, sender: Sender | None) -> bytes:
        """``payload`` signed as ``sender`` (else the bus's sender, else the topic's owner)."""
        signer = sender or self.sender or Sender.for_topic(topic)
        return self.auth.seal(signer, topic, payload, retain=retain)

    def as_sender(self, sender: Sender) -> BusClient:
        """This bus, publishing as ``sender``: one member's view of a shared bus."""
        return BusClient(self, sender)

    @abc.abstractmethod
    async def publish(
        self,
        topic: str,
        payload: bytes,
        *,
        retain: bool = False,
        timeout: float,
        sender: Sender | None = None,
    ) -> None:
        """Publish ``payload`` on ``topic`` (no wildcards), waiting at most ``timeout`` s.

        ``retain`` asks the bus to keep the payload as the topic's last value, handed to
        later subscribers; an empty retained payload clears it. ``sender`` signs instead of
        the bus's own sender. Raises BusConnectionError if the message could not be handed
        over in time; the message is then dropped.
        """

    @abc.abstractmethod
    def subscribe(
        self, pattern: str, *, queue_size: int | None = None, timeout: float | None = None
    ) -> AbstractAsyncContextManager[Subscription]:
        """A context manager yielding a ``Subscription`` to ``pattern`` (MQTT wildcards).

        Messages published after entering are delivered. ``timeout`` bounds the wait for
        the broker's acknowledgement (the bus's default when None); ``queue_size`` bounds
        the subscription's queue (the bus's default when None).
        """

    async def publish_message(
        self,
        topic: str,
        message: Message,
        *,
        retain: bool = False,
        timeout: float,
        sender: Sender | None = None,
    ) -> None:
        """Encode ``message`` and publish it (see ``publish``)."""
        payload = message.to_payload()
        _decoded.remember(message, payload)
        await self.publish(topic, payload, retain=retain, timeout=timeout, sender=sender)


class BusClient:
    """One sender's view of a bus (``Bus.as_sender``): publishes signed as ``sender``,
    subscribes through the bus. Has what a controller needs of a bus."""

    def __init__(self, bus: Bus, sender: Sender) -> None:
        self.bus = bus
        self.sender = sender

    def __repr__(self) -> str:
        return f"<BusClient {self.sender} on {self.bus!r}>"

    @property
    def auth_counters(self) -> AuthCounters:
        return self.bus.auth_counters

    async def publish(
        self, topic: str, payload: bytes, *, retain: bool = False, timeout: float
    ) -> None:
        await self.bus.publish(topic, payload, retain=retain, timeout=timeout, sender=self.sender)

    async def publish_message(
        self, topic: str, message: Message, *, retain: bool = False, timeout: float
    ) -> None:
        await self.bus.publish_message(
            topic, message, retain=retain, timeout=timeout, sender=self.sender
        )

    def subscribe(
        self, pattern: str, *, queue_size: int | None = None, timeout: float | None = None
    ) -> AbstractAsyncContextManager[Subscription]:
        return self.bus.subscribe(pattern, queue_size=queue_size, timeout=timeout)

"""The in-process bus: routing, retained messages, bounded queues and the link model."""

from __future__ import annotations

import asyncio
import contextlib

import pytest

from mission_runner.bus import (
    BusConnectionError,
    BusTimeoutError,
    InProcessBus,
    LinkModel,
    ManualClock,
    Sender,
    StepMessage,
    TopicError,
    Topics,
    VehicleStatus,
)

TOPICS = Topics.for_mission("test")
T_S = 0.125  # the paper's step length


def step(vehicle_id: int, k: int) -> StepMessage:
    return StepMessage(
        vehicle_id=vehicle_id,
        step=k,
        time_s=k * T_S,
        phase_rad=0.1 * vehicle_id,
        odometry_north_m=0.1 * k,
        odometry_east_m=0.0,
    )


@pytest.mark.asyncio
async def test_published_message_reaches_a_matching_subscriber() -> None:
    async with InProcessBus() as bus, bus.subscribe(TOPICS.all_steps()) as steps:
        await bus.publish_message(TOPICS.step(2), step(2, 7), timeout=0.1)
        topic, message = await steps.receive_message(StepMessage, timeout=1.0)
    assert topic == TOPICS.step(2)
    assert message == step(2, 7)


@pytest.mark.asyncio
async def test_routing_follows_wildcards_and_copies_to_every_subscription() -> None:
    async with (
        InProcessBus() as bus,
        bus.subscribe(TOPICS.all_steps()) as steps,
        bus.subscribe(TOPICS.everything()) as everything,
        bus.subscribe(TOPICS.all_status()) as status,
    ):
        for vehicle_id in (1, 2, 3):
            await bus.publish_message(TOPICS.step(vehicle_id), step(vehicle_id, 0), timeout=0.1)
        await bus.publish(TOPICS.control(), b"x", timeout=0.1)
        assert [steps.poll()[0] for _ in range(3)] == [TOPICS.step(i) for i in (1, 2, 3)]
        assert steps.poll() is None
        assert len(everything) == 4
        assert status.poll() is None
        assert bus.published == 4


@pytest.mark.asyncio
async def test_every_subscription_gets_the_one_message_decoded_once() -> None:
    # One payload to four vehicles' subscriptions: decoded and validated once, not four times
    # (a message is immutable, so one object serves all).
    async with InProcessBus() as bus, contextlib.AsyncExitStack() as stack:
        subscriptions = [
            await stack.enter_async_context(bus.subscribe(TOPICS.all_steps())) for _ in range(4)
        ]
        await bus.publish(TOPICS.step(3), step(3, 11).to_payload(), timeout=0.1)
        received = [
            (await subscription.receive_message(StepMessage, timeout=1.0))[1]
            for subscription in subscriptions
        ]
    assert received[0] == step(3, 11)
    assert all(message is received[0] for message in received)


@pytest.mark.asyncio
async def test_a_published_message_reaches_its_receivers_without_being_decoded() -> None:
    # The publisher's own message is what its payload decodes to (the round trip is exact,
    # tests/bus/test_messages.py): receivers in its process get that object, checked seal and all.
    sent = step(3, 12)
    async with InProcessBus() as bus, contextlib.AsyncExitStack() as stack:
        subscriptions = [
            await stack.enter_async_context(bus.subscribe(TOPICS.all_steps())) for _ in range(3)
        ]
        await bus.publish_message(TOPICS.step(3), sent, timeout=0.1)
        received = [
            (await subscription.receive_message(StepMessage, timeout=1.0))[1]
            for subscription in subscriptions
        ]
        forged = await stack.enter_async_context(bus.subscribe(TOPICS.all_steps()))
        await bus.as_sender(Sender.vehicle(2)).publish_message(
            TOPICS.step(3), step(3, 13), timeout=0.1
        )
        assert forged.poll() is None  # the seal is still checked: vehicle 2 cannot speak for 3
    assert all(message is sent for message in received)


@pytest.mark.asyncio
async def test_retained_message_is_handed_to_later_subscribers_until_cleared() -> None:
    status = VehicleStatus(3, 1.0, "following", 8, True)
    async with InProcessBus() as bus:
        await bus.publish_message(TOPICS.status(3), status, retain=True, timeout=0.1)
        await bus.publish_message(TOPICS.step(3), step(3, 8), timeout=0.1)  # not retained
        async with bus.subscribe(TOPICS.everything()) as late:
            topic, received = await late.receive_message(VehicleStatus, timeout=1.0)
            assert (topic, received) == (TOPICS.status(3), status)
            assert late.poll() is None
        await bus.publish(TOPICS.status(3), b"", retain=True, timeout=0.1)
        async with bus.subscribe(TOPICS.all_status()) as later:
            assert later.poll() is None


@pytest.mark.asyncio
async def test_full_queue_drops_the_oldest_and_never_blocks_the_publisher() -> None:
    async with InProcessBus(queue_size=3) as bus, bus.subscribe(TOPICS.all_steps()) as steps:
        for k in range(5):
            await bus.publish_message(TOPICS.step(1), step(1, k), timeout=0.0)
        assert steps.dropped == 2
        assert steps.received == 5
        received = [StepMessage.from_payload(steps.poll()[1]).step for _ in range(len(steps))]
    assert received == [2, 3, 4]


@pytest.mark.asyncio
async def test_queue_size_can_be_chosen_per_subscription() -> None:
    async with InProcessBus(queue_size=100) as bus, bus.subscribe("a", queue_size=1) as sub:
        await bus.publish("a", b"1", timeout=0.1)
        await bus.publish("a", b"2", timeout=0.1)
        assert (len(sub), sub.dropped) == (1, 1)


@pytest.mark.asyncio
async def test_receive_times_out_with_an_error_naming_the_pattern() -> None:
    async with InProcessBus() as bus, bus.subscribe(TOPICS.all_steps()) as steps:
        with pytest.raises(BusTimeoutError, match=r"vehicle/\+/step.*0.01 s") as raised:
            await steps.receive(timeout=0.01)
    assert raised.value.timeout_s == 0.01


@pytest.mark.asyncio
async def test_receive_message_skips_and_counts_bad_payloads() -> None:
    async with InProcessBus() as bus, bus.subscribe(TOPICS.all_steps()) as steps:
        await bus.publish(TOPICS.step(1), b"not json", timeout=0.1)
        await bus.publish(TOPICS.step(1), b'{"vehicle_id": 1}', timeout=0.1)
        await bus.publish_message(TOPICS.step(1), step(1, 5), timeout=0.1)
        _, message = await steps.receive_message(StepMessage, timeout=1.0)
        assert message.step == 5
        assert steps.decode_errors == 2
        with pytest.raises(BusTimeoutError, match="StepMessage"):
            await steps.receive_message(StepMessage, timeout=0.01)


@pytest.mark.asyncio
async def test_typed_iteration_ends_when_the_bus_closes() -> None:
    bus = InProcessBus()
    received: list[int] = []
    async with bus, bus.subscribe(TOPICS.all_steps()) as steps:
        await bus.publish(TOPICS.step(1), b"garbage", timeout=0.1)
        for k in range(3):
            await bus.publish_message(TOPICS.step(1), step(1, k), timeout=0.1)
        await bus.__aexit__(None, None, None)  # close while the subscription is live
        async for _, message in steps.messages(StepMessage):
            received.append(message.step)
        assert steps.closed
        with pytest.raises(BusConnectionError, match="closed"):
            await steps.receive(timeout=1.0)
    assert received == [0, 1, 2]
    assert steps.decode_errors == 1


@pytest.mark.asyncio
async def test_raw_iteration_yields_topic_and_payload() -> None:
    bus = InProcessBus()
    async with bus, bus.subscribe("a/#") as sub:
        await bus.publish("a/b", b"1", timeout=0.1)
        await bus.publish("a", b"2", timeout=0.1)
        await bus.__aexit__(None, None, None)
        assert [item async for item in sub] == [("a/b", b"1"), ("a", b"2")]


@pytest.mark.asyncio
async def test_using_a_closed_or_unopened_bus_is_a_connection_error() -> None:
    bus = InProcessBus()
    with pytest.raises(BusConnectionError, match="not entered"):
        await bus.publish("a", b"", timeout=0.1)
    async with bus:
        pass
    with pytest.raises(BusConnectionError, match="closed"):
        await bus.publish("a", b"", timeout=0.1)
    with pytest.raises(BusConnectionError, match="closed"):
        async with bus.subscribe("a"):
            pass


@pytest.mark.asyncio
async def test_exited_subscription_gets_nothing_more() -> None:
    async with InProcessBus() as bus:
        async with bus.subscribe("a") as sub:
            pass
        await bus.publish("a", b"1", timeout=0.1)
        assert sub.closed
        assert len(sub) == 0


@pytest.mark.asyncio
async def test_routes_follow_subscriptions_that_come_and_go_between_publishes() -> None:
    # The bus remembers which subscriptions a topic reaches: a subscription made or ended after
    # that topic was first routed must still be (or no longer be) reached.
    async with InProcessBus() as bus, bus.subscribe(TOPICS.step(1)) as one:
        await bus.publish_message(TOPICS.step(1), step(1, 0), timeout=0.1)
        async with bus.subscribe(TOPICS.all_steps()) as every:
            await bus.publish_message(TOPICS.step(1), step(1, 1), timeout=0.1)
            assert len(every) == 1
        await bus.publish_message(TOPICS.step(1), step(1, 2), timeout=0.1)
        assert len(one) == 3
        assert len(every) == 1


@pytest.mark.asyncio
async def test_wildcards_are_refused_on_publish_and_checked_on_subscribe() -> None:
    async with InProcessBus() as bus:
        with pytest.raises(TopicError):
            await bus.publish("a/+", b"", timeout=0.1)
        with pytest.raises(TopicError):
            async with bus.subscribe("a/#/b"):
                pass


class TestLinkModel:
    def test_parameters_are_validated(self) -> None:
        with pytest.raises(ValueError, match="latency_s"):
            LinkModel(latency_s=-1.0)
        with pytest.raises(ValueError, match="loss_probability"):
            LinkModel(loss_probability=1.5)

    @pytest.mark.asyncio
    async def test_latency_is_timed_by_the_injected_clock(self) -> None:
        clock = ManualClock()
        link = LinkModel(latency_s=0.1)
        async with InProcessBus(link=link, clock=clock) as bus, bus.subscribe("a") as sub:
            await bus.publish("a", b"late", timeout=0.1)
            await clock.advance(0.099)
            assert sub.poll() is None
            assert bus.in_flight == 1
            await clock.advance(0.001)
            assert await sub.receive(timeout=1.0) == ("a", b"late")
            assert bus.in_flight == 0

    @pytest.mark.asyncio
    async def test_a_message_due_sooner_is_not_held_behind_a_later_one(self) -> None:
        # With reorder=True, B (published after A) may be due before A. The delivery loop
        # is then already asleep until A's due time and must wake up early for B.
        clock = ManualClock()
        link = LinkModel(jitter_s=1.0, seed=3, reorder=True)
        overtakes = 0
        async with InProcessBus(link=link, clock=clock) as bus, bus.subscribe("#") as sub:
            for _ in range(10):
                await bus.publish("a", b"A", timeout=0.1)
                await clock.advance(0.0)  # the loop now sleeps until A is due
                await bus.publish("b", b"B", timeout=0.1)
                arrival_s: dict[str, float] = {}
                while len(arrival_s) < 2:
                    await clock.advance(0.01)
                    while (item := sub.poll()) is not None:
                        arrival_s[item[0]] = clock.now_s()
                overtakes += arrival_s["b"] < arrival_s["a"]
        assert overtakes > 0

    @pytest.mark.asyncio
    async def test_without_reorder_each_subscription_keeps_publish_order(self) -> None:
        clock = ManualClock()
        link = LinkModel(latency_s=0.05, jitter_s=0.5, seed=11)
        async with InProcessBus(link=link, clock=clock) as bus, bus.subscribe("#") as sub:
            for k in range(50):
                await bus.publish_message(TOPICS.step(1), step(1, k), timeout=0.1)
                await clock.advance(0.01)
            await clock.advance(1.0)
            steps = [StepMessage.from_payload(sub.poll()[1]).step for _ in range(len(sub))]
        assert steps == list(range(50))

    @pytest.mark.asyncio
    async def test_a_failing_clock_stops_the_bus_and_surfaces_at_exit(self) -> None:
        class BrokenClock(ManualClock):
            async def sleep(self, seconds: float) -> None:
                raise OSError("clock source gone")

        link = LinkModel(latency_s=0.1)
        with pytest.RaisesGroup(pytest.RaisesExc(OSError, match="clock source gone")):
            async with InProcessBus(link=link, clock=BrokenClock()) as bus, bus.subscribe("a"):
                await bus.publish("a", b"late", timeout=0.1)
                await asyncio.sleep(1.0)  # the delivery loop's failure cancels this

    @staticmethod
    async def run_lossy_exchange(
        seed: int, order: tuple[int, ...] = (1, 2, 3, 4)
    ) -> list[tuple[int, int, int]]:
        """Four vehicles, each its own client of the bus, broadcast 40 steps over a lossy,
        jittery link; they subscribe and publish in ``order``.

        Returns (receiver, sender, step) in arrival order.
        """
        clock = ManualClock()
        link = LinkModel(latency_s=0.02, jitter_s=0.2, loss_probability=0.2, seed=seed)
        vehicles = (1, 2, 3, 4)
        arrivals: list[tuple[int, int, int]] = []
        async with InProcessBus(link=link, clock=clock) as bus:
            subs = {
                v: bus.as_sender(Sender.vehicle(v)).subscribe(TOPICS.all_steps()) for v in order
            }
            entered = {v: await subs[v].__aenter__() for v in order}
            for k in range(40):
                for v in order:
                    await bus.publish_message(TOPICS.step(v), step(v, k), timeout=0.1)
                await clock.advance(T_S)
                for v in vehicles:
                    while (item := entered[v].poll()) is not None:
                        message = StepMessage.from_payload(item[1])
                        arrivals.append((v, message.vehicle_id, message.step))
            for v in vehicles:
                await subs[v].__aexit__(None, None, None)
            assert bus.lost + len(arrivals) + bus.in_flight == 40 * 4 * 4
        return arrivals

    @pytest.mark.asyncio
    async def test_same_seed_same_network(self) -> None:
        first = await self.run_lossy_exchange(seed=7)
        assert first == await self.run_lossy_exchange(seed=7)
        assert first != await self.run_lossy_exchange(seed=8)

    @pytest.mark.asyncio
    async def test_the_network_does_not_depend_on_who_subscribes_or_publishes_first(self) -> None:
        # Concurrent controllers subscribe and publish in whatever order their tasks run.
        first = await self.run_lossy_exchange(seed=7)
        assert sorted(first) == sorted(await self.run_lossy_exchange(seed=7, order=(3, 1, 4, 2)))

    @pytest.mark.asyncio
    async def test_lossy_link_loses_about_the_asked_fraction_and_never_duplicates(self) -> None:
        arrivals = await self.run_lossy_exchange(seed=7)
        assert len(arrivals) == len(set(arrivals))
        delivered = len(arrivals) / (40 * 4 * 4)
        assert 0.7 < delivered < 0.85  # 20 % loss, minus a few still in flight at the end
        # Late messages keep their step index: a receiver sees each sender's steps in order.
        for receiver in (1, 2, 3, 4):
            for sender in (1, 2, 3, 4):
                steps = [k for r, s, k in arrivals if (r, s) == (receiver, sender)]
                assert steps == sorted(steps)


class TestManualClock:
    @pytest.mark.asyncio
    async def test_sleepers_wake_in_due_order_at_their_due_time(self) -> None:
        clock = ManualClock()
        woke: list[tuple[str, float]] = []

        async def sleeper(name: str, seconds: float) -> None:
            await clock.sleep(seconds)
            woke.append((name, clock.now_s()))

        async with asyncio.TaskGroup() as group:
            group.create_task(sleeper("late", 0.3))
            group.create_task(sleeper("early", 0.1))
            await clock.advance(0.0)
            assert clock.pending_sleepers == 2
            await clock.advance(0.2)
            assert woke == [("early", 0.1)]
            await clock.advance(0.2)
        assert woke == [("early", 0.1), ("late", 0.3)]
        assert clock.now_s() == pytest.approx(0.4)

    @pytest.mark.asyncio
    async def test_time_never_goes_back(self) -> None:
        with pytest.raises(ValueError, match="back"):
            await ManualClock().advance(-1.0)

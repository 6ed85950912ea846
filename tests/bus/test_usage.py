"""The controller pattern of the package docstring, run on a lossy in-process network.

Each vehicle, every step k: broadcast its own step-k message (dropped if the bus cannot
take it in time), wait until the step's collection deadline, take what arrived, note when
each neighbour was last heard, and use only neighbours' step-k messages; with nobody heard
for the silence timeout it holds.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass, field

import pytest

from mission_runner.bus import (
    Bus,
    BusConnectionError,
    Clock,
    InProcessBus,
    LinkModel,
    ManualClock,
    StepMessage,
    Topics,
)

T_S = 0.125
SILENCE_S = 3 * T_S
TOPICS = Topics.for_mission("usage")


@dataclass
class Log:
    aligned: dict[int, set[int]] = field(default_factory=dict)  # step -> senders used
    held_steps: list[int] = field(default_factory=list)
    silent: dict[int, list[int]] = field(default_factory=dict)  # step -> silent senders


async def vehicle(
    bus: Bus, vehicle_id: int, clock: Clock, steps: int, log: Log, *, stop_at: int | None
) -> None:
    started_s = clock.now_s()
    last_heard_s: dict[int, float] = {}
    async with bus.subscribe(TOPICS.all_steps()) as neighbours:
        for k in range(steps):
            if stop_at is not None and k >= stop_at:
                return  # this vehicle is lost
            own = StepMessage(vehicle_id, k, clock.now_s(), 0.0, 0.1 * k, 0.0)
            with contextlib.suppress(BusConnectionError):
                await bus.publish_message(TOPICS.step(vehicle_id), own, timeout=T_S / 4)
            await clock.sleep(T_S / 2)  # collection deadline of step k
            step_k: dict[int, StepMessage] = {}
            for _, message in neighbours.drain_messages(StepMessage):
                if message.vehicle_id == vehicle_id:
                    continue
                last_heard_s[message.vehicle_id] = clock.now_s()
                if message.step == k:
                    step_k[message.vehicle_id] = message
            now_s = clock.now_s()
            log.silent[k] = sorted(v for v, t_s in last_heard_s.items() if now_s - t_s > SILENCE_S)
            if now_s - max(last_heard_s.values(), default=started_s) > SILENCE_S:
                log.held_steps.append(k)  # nobody fresh: hold position
            else:
                log.aligned[k] = set(step_k)  # late or lost neighbours are simply absent
            await clock.sleep(T_S / 2)


async def fly(link: LinkModel, steps: int, stop_at: dict[int, int]) -> dict[int, Log]:
    clock = ManualClock()
    logs = {vehicle_id: Log() for vehicle_id in (1, 2, 3, 4)}
    async with InProcessBus(link=link, clock=clock) as bus, asyncio.TaskGroup() as group:
        tasks = [
            group.create_task(vehicle(bus, v, clock, steps, logs[v], stop_at=stop_at.get(v)))
            for v in logs
        ]
        while not all(task.done() for task in tasks):
            await clock.advance(T_S / 4)
    return logs


@pytest.mark.asyncio
async def test_vehicles_use_only_same_step_messages_and_tolerate_loss() -> None:
    # Deliveries take 10-50 ms, within the 62.5 ms collection deadline; 10 % are lost.
    link = LinkModel(latency_s=0.01, jitter_s=0.04, loss_probability=0.1, seed=5)
    logs = await fly(link, steps=80, stop_at={})
    for vehicle_id, log in logs.items():
        assert log.held_steps == []
        used = [len(senders) for senders in log.aligned.values()]
        assert 2.5 < sum(used) / len(used) < 2.9  # 3 neighbours x 90 %
        assert all(vehicle_id not in senders for senders in log.aligned.values())


@pytest.mark.asyncio
async def test_messages_later_than_the_deadline_are_left_out_not_misattributed() -> None:
    # Deliveries take 10-110 ms: those past the 62.5 ms deadline belong to step k but
    # arrive during step k + 1, where the step index keeps them from being used.
    link = LinkModel(latency_s=0.01, jitter_s=0.1, seed=5)
    logs = await fly(link, steps=80, stop_at={})
    used = [len(senders) for log in logs.values() for senders in log.aligned.values()]
    assert 1.2 < sum(used) / len(used) < 2.0  # about 3 x 52.5 / 100


@pytest.mark.asyncio
async def test_a_lost_vehicle_goes_silent_for_the_others() -> None:
    link = LinkModel(latency_s=0.01, seed=1)
    logs = await fly(link, steps=40, stop_at={4: 20})
    for vehicle_id in (1, 2, 3):
        log = logs[vehicle_id]
        assert 4 not in log.silent[22]  # within the 3-step silence timeout
        assert all(log.silent[k] == [4] for k in range(24, 40))
        assert all(log.aligned[k] == {1, 2, 3} - {vehicle_id} for k in range(24, 40))


@pytest.mark.asyncio
async def test_everyone_alone_holds() -> None:
    link = LinkModel(loss_probability=1.0, seed=1)  # the network is gone
    logs = await fly(link, steps=10, stop_at={})
    assert logs[1].held_steps == list(range(3, 10))  # silent after 3 steps of nothing

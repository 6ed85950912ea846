"""Step alignment bookkeeping: what a vehicle heard for step k, and who is still a member."""

import asyncio

import pytest

from mission_runner.bus import RangeSet, StepMessage, TargetObservation
from mission_runner.runner.inbox import StepInbox

T = 0.125


def step_of(time_s):
    k = round(time_s / T)
    return k if abs(time_s - k * T) <= T / 4 else None


def inbox(senses_target=False, timeout=3):
    return StepInbox(
        1, [1, 2, 3], senses_target=senses_target, step_of=step_of, member_timeout_steps=timeout
    )


def step(vehicle, k):
    return StepMessage(vehicle, k, k * T, 0.1 * vehicle, 1.0, 2.0)


def ranges(k, *peers):
    return RangeSet(1, k * T, tuple((peer, 5.0 + peer) for peer in peers), step=k)


def test_step_is_complete_with_every_members_message_and_range():
    box = inbox()
    box.add_step(step(2, 0))
    box.add_ranges(ranges(0, 2, 3))
    assert not box.complete(0)
    box.add_step(step(3, 0))
    assert box.complete(0)
    data = box.take(0)
    assert set(data.neighbours) == {2, 3}
    assert data.ranges_m == {2: 7.0, 3: 8.0}
    assert data.members == {1, 2, 3}


@pytest.mark.parametrize("peers", [(2,), ()])
def test_a_partial_or_empty_range_set_is_the_whole_round(peers):
    """A range that dropped out never comes: once the set is in, the step waits for no range,
    only for the neighbours' messages."""
    box = inbox()
    box.add_step(step(2, 0))
    box.add_step(step(3, 0))
    assert not box.own_ranges_in(0) and not box.complete(0)
    box.add_ranges(ranges(0, *peers))
    assert box.own_ranges_in(0) and box.complete(0)
    assert box.take(0).ranges_m == {peer: 5.0 + peer for peer in peers}


def test_late_messages_are_discarded_never_applied_to_another_step():
    box = inbox()
    box.take(0)
    box.add_step(step(2, 0))  # step 0 is closed
    box.add_ranges(RangeSet(1, 0.0, ((2, 3.0),), step=0))
    assert box.discarded_late == 2
    assert box.take(1).neighbours == {}


def test_ranges_without_a_step_are_aligned_by_timestamp():
    box = inbox()
    box.add_ranges(RangeSet(1, 2 * T + 0.01, ((2, 4.0),)))  # within T/4 of t_2
    box.add_ranges(RangeSet(1, 2 * T + 0.05, ((3, 4.0),)))  # between boundaries: dropped
    box.take(0)
    box.take(1)
    assert box.take(2).ranges_m == {2: 4.0}


def test_other_vehicles_ranges_and_own_messages_are_ignored():
    box = inbox()
    box.add_step(step(1, 0))
    box.add_ranges(RangeSet(2, 0.0, ((3, 1.0),), step=0))
    box.add_target(TargetObservation(2, 0.0, 3.0, 0.8, 0.0))
    data = box.take(0)
    assert data.neighbours == {} and data.ranges_m == {} and data.target is None


def test_silent_neighbour_leaves_after_the_timeout_and_returns_when_heard():
    box = inbox(timeout=3)
    for k in range(5):
        box.add_step(step(2, k))
        data = box.take(k)
    assert data.members == {1, 2}  # 3 unheard since k = 0: out after 3 steps
    box.add_step(step(3, 5))
    assert box.take(5).members == {1, 2, 3}


def test_target_sensing_vehicle_waits_for_its_observation():
    box = inbox(senses_target=True)
    for vehicle in (2, 3):
        box.add_step(step(vehicle, 0))
    box.add_ranges(ranges(0, 2, 3))
    assert not box.complete(0)
    box.add_target(TargetObservation(1, 0.0, 4.0, 0.8, 0.0))
    assert box.complete(0)


@pytest.mark.asyncio
async def test_wait_complete_wakes_on_arrival_and_gives_up_at_the_deadline():
    box = inbox()
    assert await box.wait_complete(0, timeout_s=0.01) is False

    async def deliver():
        box.add_step(step(2, 0))
        box.add_step(step(3, 0))
        box.add_ranges(ranges(0, 2, 3))

    waiter = asyncio.create_task(box.wait_complete(0, timeout_s=5.0))
    await asyncio.sleep(0)
    await deliver()
    assert await waiter is True


def test_a_neighbour_that_is_always_late_rejoins_and_is_waited_for_again():
    box = inbox(timeout=3)
    for k in range(6):  # vehicle 3 silent: it leaves
        box.add_step(step(2, k))
        data = box.take(k)
    assert 3 not in data.members
    box.add_step(step(2, 6))
    data = box.take(6)
    box.add_step(step(3, 6))  # late for step 6, but alive
    assert 3 in box.members()
    box.add_step(step(2, 7))
    box.add_ranges(ranges(7, 2, 3))
    assert not box.complete(7)  # now waited for
    box.add_step(step(3, 7))
    assert box.complete(7)

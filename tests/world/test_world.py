"""The world around emulated vehicles: UWB ranging and the target tracker on the bus."""

import asyncio
import logging
import math
from typing import NamedTuple

import numpy as np
import pytest

from mission_runner.bus import (
    BusConnectionError,
    InProcessBus,
    RangeSet,
    TargetObservation,
    Topics,
)
from mission_runner.config import CirclePath, EventConfig, SensorConfig
from mission_runner.world import World
from sitl.config import ClockConfig, EmulatorConfig
from sitl.emulator import Emulator
from tests.sitl.helpers import free_port_config

pytestmark = pytest.mark.asyncio

STEP_S = 0.125
TOPICS = Topics("enclosing/world-test")


class Ranged(NamedTuple):
    """One range of a published set."""

    vehicle_id: int
    peer_id: int
    time_s: float
    range_m: float
    step: int | None


def each_range(sets):
    return [
        Ranged(m.vehicle_id, peer, m.time_s, range_m, m.step)
        for m in sets
        for peer, range_m in m.ranges_m
    ]


def emulator_config(n=3, rate_hz=200.0):
    return EmulatorConfig(
        vehicles=n,
        ports=free_port_config(n, gcs=False),
        clock=ClockConfig(mode="lockstep"),
        physics={"rate_hz": rate_hz},
        placement={"positions": [{"north_m": 4.0 * i, "east_m": 0.0} for i in range(n)]},
    )


async def collect(
    sensors, *, seconds, senses=(True, False, False), faults=(), wrap=None, rate_hz=200.0
):
    """Run the world for ``seconds`` and return every range (of every set) and target message
    published, the world, and the range sets. ``wrap(bus)``: what the world publishes through
    instead of the bus itself."""
    path = CirclePath(kind="circle", center_m=[0.0, 10.0], radius_m=2.0, period_s=20.0)
    async with (
        Emulator(emulator_config(rate_hz=rate_hz)) as emulator,
        InProcessBus() as bus,
        bus.subscribe(TOPICS.all_ranges(), queue_size=100_000) as ranges,
        bus.subscribe(TOPICS.all_targets(), queue_size=100_000) as targets,
        World(
            emulator,
            bus=bus if wrap is None else wrap(bus),
            topics=TOPICS,
            vehicle_ids=[1, 2, 3],
            senses_target=senses,
            target_path=path,
            target_altitude_m=0.0,
            sensors=sensors,
            step_s=STEP_S,
            seed=4,
            # In lockstep with no vehicle to wait for, the emulator runs as fast as it can and
            # leaves the publisher steps behind: every step's measurements are wanted here.
            stale_after_steps=None,
        ) as world,
    ):
        for fault in faults:
            world.fail_sensor(*fault)
        steps = round(seconds / STEP_S)
        world.start(math.ceil(emulator.time_s / STEP_S) * STEP_S, steps=steps)
        await emulator.run_for(seconds + STEP_S)
        async with asyncio.timeout(10):
            await world.drained()
        sets = [m for _, m in ranges.drain_messages(RangeSet)]
        return (
            each_range(sets),
            [m for _, m in targets.drain_messages(TargetObservation)],
            world,
            sets,
        )


@pytest.mark.slow  # 40 s of ranges for a noise statistic
async def test_ranges_are_sampled_at_step_boundaries_with_the_configured_noise():
    ranges, _, world, _ = await collect(SensorConfig(range_noise_std_m=0.1), seconds=40)
    start = world.start_s
    steps = {m.step for m in ranges}
    assert len(steps) >= 300
    for message in ranges:
        assert message.time_s == pytest.approx(start + message.step * STEP_S, abs=1e-9)
    # Vehicles sit 4 m apart on the ground: the noise is the difference to the true distance.
    errors = np.array([m.range_m - 4.0 * abs(m.vehicle_id - m.peer_id) for m in ranges])
    assert errors.std() == pytest.approx(0.1, rel=0.1)
    assert abs(errors.mean()) < 0.01


EXCHANGING = SensorConfig(
    range_noise_std_m=0.05,
    range_bias_std_m=0.1,
    range_outlier_probability=0.1,
    range_nlos_duration_s=2.0,
    range_exchange_s=STEP_S / 2,
)


async def test_both_ends_of_a_pair_read_one_exchange():
    """One exchange per pair on the emulator's clock: vehicle i's range of j at step k is j's of
    i, bit for bit; the airtime ranges two of the three pairs a step, and each vehicle's ranges
    of a step go out in one set. (Exact at every step: 5 s show it as well as 30.)"""
    ranges, _, world, sets = await collect(EXCHANGING, seconds=5)
    read = {(m.step, m.vehicle_id, m.peer_id): m.range_m for m in ranges}
    assert all(read.get((k, j, i)) == value for (k, i, j), value in read.items())
    steps = len(world.samples)
    assert len(read) == 4 * steps  # two exchanges a step, each read at both ends
    assert sorted((m.step, m.vehicle_id) for m in sets) == [
        (k, i) for k in range(steps) for i in (1, 2, 3)
    ]


@pytest.mark.slow  # 30 s of ranges for a statistic of bursts; the exchange itself is above
async def test_a_pairs_errors_last_and_come_in_bursts():
    """A pair's bias stays; NLOS comes in bursts."""
    ranges, _, world, _ = await collect(EXCHANGING, seconds=30)
    read = {(m.step, m.vehicle_id, m.peer_id): m.range_m for m in ranges}
    steps = len(world.samples)
    error = {key: value - 4.0 * abs(key[1] - key[2]) for key, value in read.items()}
    long = [key for key, value in error.items() if value > 0.3 + 0.25]  # in a burst
    assert long
    # A pair in a burst at step k is, most often, still in it when next ranged (3 steps on).
    again = [error.get((k + 3, i, j), 0.0) > 0.55 for k, i, j in long if k + 3 < steps]
    assert np.mean(again) > 0.6


DROPPING = SensorConfig(range_dropout_probability=0.2, range_max_m=6.0)


async def test_beyond_the_maximum_range_nothing_and_every_set_goes_out():
    ranges, _, world, sets = await collect(DROPPING, seconds=5)
    steps = len(world.samples)
    # 1-2, 2-1, 2-3, 3-2 are within 6 m; 1-3, 3-1 (8 m) never are.
    assert {(m.vehicle_id, m.peer_id) for m in ranges} == {(1, 2), (2, 1), (2, 3), (3, 2)}
    # Every vehicle's set goes out every step, empty when its only range dropped out: its
    # controller then knows none is coming.
    assert len(sets) == 3 * steps
    assert any(not m.ranges_m for m in sets)


@pytest.mark.slow  # 30 s of ranges for a dropout rate within 4 %
async def test_dropouts_at_their_probability():
    ranges, _, world, sets = await collect(DROPPING, seconds=30)
    pairs_per_step = 4
    steps = len(world.samples)
    assert len(ranges) / (steps * pairs_per_step) == pytest.approx(0.8, abs=0.04)
    empty = [m.vehicle_id for m in sets if not m.ranges_m]
    assert empty.count(1) / steps == pytest.approx(0.2, abs=0.04)  # its one range dropped
    assert empty.count(2) < empty.count(1)  # both of its ranges dropped


async def test_target_observations_only_for_sensing_vehicles():
    _, targets, world, _ = await collect(SensorConfig(), seconds=5, senses=(False, True, False))
    assert targets and {t.vehicle_id for t in targets} == {2}
    first = targets[0]
    expected = np.hypot(
        4.0 - world.target_position(first.time_s)[0], 0.0 - world.target_position(first.time_s)[1]
    )
    assert first.range_m == pytest.approx(expected, abs=1e-6)
    speed = 2 * math.pi * 2.0 / 20.0
    assert math.hypot(first.velocity_north_m_s, first.velocity_east_m_s) == pytest.approx(
        speed, rel=1e-3
    )


class InFlight:
    """Hands each message on to ``bus`` a loop turn later, noting the order and how many
    were in flight at once."""

    def __init__(self, bus):
        self.bus, self.order, self.in_flight, self.most = bus, [], 0, 0

    async def publish_message(self, topic, message, *, timeout):
        self.order.append(message)
        self.in_flight += 1
        self.most = max(self.most, self.in_flight)
        try:
            await asyncio.sleep(0)
            await self.bus.publish_message(topic, message, timeout=timeout)
        finally:
            self.in_flight -= 1


@pytest.mark.parametrize("rate_hz", [200.0, 40.0])
async def test_a_steps_measurements_go_out_at_once_target_observations_first(rate_hz):
    """The sensing vehicle's step waits for its observation, its neighbours' for its message:
    one after the other, the observation (last) came 35-65 ms after t_k on a loaded machine.
    At 40 Hz a lockstep batch of steps spans two of T = 0.125 s: a step's messages still go out
    alone, before the next step is sampled (it ends the batch)."""
    wrapped = []
    ranges, targets, _, sets = await collect(
        SensorConfig(),
        seconds=3,
        wrap=lambda bus: wrapped.append(InFlight(bus)) or wrapped[0],
        rate_hz=rate_hz,
    )
    (bus,) = wrapped
    per_step = 1 + 3  # vehicle 1's observation and the three vehicles' range sets
    assert len(targets) >= 20 and len(ranges) == 6 * len(targets) == 2 * len(sets)
    assert bus.most == per_step
    firsts = [bus.order[i] for i in range(0, len(bus.order), per_step)]
    assert all(isinstance(m, TargetObservation) for m in firsts)


class Outage:
    """Refuses what is published for the first ``steps`` steps' measurements."""

    def __init__(self, bus, steps):
        self.bus, self.steps, self.start_s = bus, steps, None

    async def publish_message(self, topic, message, *, timeout):
        self.start_s = message.time_s if self.start_s is None else self.start_s
        if message.time_s < self.start_s + self.steps * STEP_S - 1e-9:
            raise BusConnectionError("broker", "not connected")
        await self.bus.publish_message(topic, message, timeout=timeout)


async def test_a_bus_outage_is_one_warning_and_a_count_not_a_line_per_message(caplog):
    """A line per message (13 a step with four vehicles, a message a range) filled the stderr
    pipe of an ``emulate`` process nobody read until the end, and its event loop (the emulator
    with it) stopped."""
    caplog.set_level(logging.INFO, logger="mission_runner.world.world")
    wrapped = []
    _, targets, world, sets = await collect(
        SensorConfig(), seconds=3, wrap=lambda bus: wrapped.append(Outage(bus, 8)) or wrapped[0]
    )
    assert world.dropped == 8 * 4 and world.published == len(sets) + len(targets) > 0
    lines = [r for r in caplog.records if r.name == "mission_runner.world.world"]
    assert [r.levelname for r in lines] == ["WARNING", "INFO"]
    assert "publishing again (32 dropped)" in lines[1].getMessage()


class SlowAcknowledgement:
    """Step 3's messages are handed on, then acknowledged only once a later step's have been
    handed on too (a broker slow to acknowledge one step)."""

    def __init__(self, bus):
        self.bus, self.start_s, self.later = bus, None, asyncio.Event()

    async def publish_message(self, topic, message, *, timeout):
        self.start_s = message.time_s if self.start_s is None else self.start_s
        step = round((message.time_s - self.start_s) / STEP_S)
        await self.bus.publish_message(topic, message, timeout=timeout)
        if step > 3:
            self.later.set()
        elif step == 3:
            try:
                async with asyncio.timeout(timeout):
                    await self.later.wait()
            except TimeoutError:
                raise BusConnectionError("broker", "not acknowledged in time") from None


async def test_a_step_slow_to_be_acknowledged_does_not_hold_the_next_steps_back():
    """Each step waited for the one before it to be acknowledged: a broker starved for one
    step's acknowledgement delayed every later step's measurements past the vehicles'
    deadlines (and this step, waited for in vain, was counted as dropped)."""
    wrapped = []
    _, targets, world, sets = await collect(
        SensorConfig(),
        seconds=2,
        wrap=lambda bus: wrapped.append(SlowAcknowledgement(bus)) or wrapped[0],
    )
    assert wrapped[0].later.is_set()
    assert world.dropped == 0 and world.published == len(sets) + len(targets) == 4 * 16


async def test_a_failed_uwb_stops_every_range_from_and_to_it():
    faults = [(1, "uwb", 0.0, None)]  # vehicle index 1 (id 2) from the start
    ranges, _, _, sets = await collect(SensorConfig(), seconds=3, faults=faults)
    assert ranges and all(2 not in (m.vehicle_id, m.peer_id) for m in ranges)
    assert {m.vehicle_id for m in sets} == {1, 3}  # its radio down: no set at all


async def test_trackers_say_not_seen_beyond_range_when_hidden_and_at_a_miss():
    from mission_runner.sensors import UwbRanging
    from mission_runner.world import step_measurements

    topics = Topics("unit")
    positions = np.array([[1.0, 0.0, -5.0], [6.0, 0.0, -5.0], [0.0, 2.0, -5.0], [0.0, 3.0, -5.0]])

    def observations(sensors, hidden=(False, False, False, False), tracking=(True,) * 4):
        measured = step_measurements(
            3,
            1.5,
            ids=[1, 2, 3, 4],
            topics=topics,
            positions_m=positions,
            ranging=np.zeros(4, dtype=bool),
            tracking=np.array(tracking),
            target_hidden=np.array(hidden),
            target_m=[0.0, 0.0],
            target_velocity_m_s=[0.8, 0.0],
            sensors=sensors,
            rng=np.random.default_rng(0),
            uwb=UwbRanging(sensors, 4, 0.5),
        )
        return {m.vehicle_id: m for _, m in measured if isinstance(m, TargetObservation)}

    # Within 4 m: seen (horizontal range, velocity); beyond: an explicit "not seen".
    seen = observations(SensorConfig(target_sensing_range_m=4.0))
    assert {i: o.seen for i, o in seen.items()} == {1: True, 2: False, 3: True, 4: True}
    assert seen[1].range_m == pytest.approx(1.0)
    assert (seen[1].velocity_north_m_s, seen[1].velocity_east_m_s) == (0.8, 0.0)
    assert seen[2].range_m is None and seen[2].velocity_north_m_s is None
    # Occluded: "not seen" too; a vehicle without a working tracker reports nothing.
    hidden = observations(SensorConfig(), hidden=(True, False, False, False), tracking=(1, 1, 1, 0))
    assert {i: o.seen for i, o in hidden.items()} == {1: False, 2: True, 3: True}
    # Random misses: every tracker misses when the probability is (almost) 1.
    missed = observations(SensorConfig(target_dropout_probability=0.999999))
    assert not any(o.seen for o in missed.values()) and len(missed) == 4


async def test_a_set_per_ranging_vehicle_empty_when_the_airtime_left_it_out():
    """One exchange a step: at step k one pair ranges, and the two other working radios say
    they ranged nothing (an empty set); a radio that is down sends no set."""
    from mission_runner.sensors import UwbRanging, range_schedule
    from mission_runner.world import step_measurements

    sensors = SensorConfig(range_exchange_s=0.5)
    positions = np.array([[4.0 * i, 0.0, -5.0] for i in range(4)])
    uwb = UwbRanging(sensors, 4, 0.5)
    ranging = np.array([True, True, True, False])
    empty = 0
    for k in range(6):
        measured = step_measurements(
            k,
            0.5 * k,
            ids=[1, 2, 3, 4],
            topics=TOPICS,
            positions_m=positions,
            ranging=ranging,
            tracking=np.zeros(4, dtype=bool),
            target_m=[0.0, 0.0],
            target_velocity_m_s=[0.0, 0.0],
            sensors=sensors,
            rng=np.random.default_rng(k),
            uwb=uwb,
        )
        sets = {m.vehicle_id: m for _, m in measured}
        assert [topic for topic, _ in measured] == [TOPICS.ranges(i) for i in (1, 2, 3)]
        carried = range_schedule(4, sensors, 0.5, k) & ranging[:, None] & ranging[None, :]
        for i in (1, 2, 3):
            peers = [j + 1 for j in np.flatnonzero(carried[i - 1])]
            assert [peer for peer, _ in sets[i].ranges_m] == peers
            assert sets[i].step == k and sets[i].time_s == 0.5 * k
        empty += sum(not m.ranges_m for m in sets.values())
    # Six steps, one pair each: a working radio outside the step's pair has an empty set, and
    # the three pairs with vehicle 4 (down) left even their other end with nothing.
    assert empty == 3 * 1 + 3 * 3


async def test_the_scenarios_events_happen_at_their_step_on_the_emulators_clock():
    # A vehicle-process world: its mission clock is UNIX time, the emulator's its own seconds.
    offset_s = 1.7e9
    events = [
        EventConfig(kind="vehicle_lost", vehicle=2, at_step=8),
        EventConfig(kind="taken_over", vehicle=3, at_step=4, mode="land"),
    ]
    path = CirclePath(kind="circle", center_m=[0.0, 10.0], radius_m=2.0, period_s=20.0)
    async with (
        Emulator(emulator_config()) as emulator,
        InProcessBus() as bus,
        World(
            emulator,
            bus=bus,
            topics=TOPICS,
            vehicle_ids=[1, 2, 3],
            senses_target=(True, False, False),
            target_path=path,
            target_altitude_m=0.0,
            sensors=SensorConfig(),
            step_s=STEP_S,
            time_offset_s=offset_s,
            events=events,
        ) as world,
    ):
        start_s = math.ceil(emulator.time_s / STEP_S) * STEP_S + STEP_S
        world.start(offset_s + start_s)
        await emulator.run_for(2.0)
    happened = {(index, what): time_s for time_s, index, what in emulator.events}
    assert happened[1, "killed"] == pytest.approx(start_s + 8 * STEP_S, abs=0.006)
    taken = [time_s for (index, what), time_s in happened.items() if index == 2]
    assert taken == [pytest.approx(start_s + 4 * STEP_S, abs=0.006)]


def ring_of_four_measured(graph, seed=5):
    """Step 7's range sets of four vehicles on a line 4 m apart, with noise, pair biases and
    dropouts, every radio working, ``graph`` the pairs scheduled (None: every pair)."""
    from mission_runner.sensors import UwbRanging
    from mission_runner.world import step_measurements

    sensors = SensorConfig(
        range_noise_std_m=0.05, range_bias_std_m=0.1, range_dropout_probability=0.2
    )
    positions = np.array([[4.0 * i, 0.0, -5.0] for i in range(4)])
    uwb = UwbRanging(sensors, 4, STEP_S)
    rng = np.random.default_rng(seed)
    for k in range(8):
        measured = step_measurements(
            k,
            k * STEP_S,
            ids=[1, 2, 3, 4],
            topics=TOPICS,
            positions_m=positions,
            ranging=np.ones(4, dtype=bool),
            tracking=np.zeros(4, dtype=bool),
            target_m=[0.0, 0.0],
            target_velocity_m_s=[0.0, 0.0],
            sensors=sensors,
            rng=rng,
            uwb=uwb,
            graph=graph,
        )
    return {(m.vehicle_id, peer): r for _, m in measured for peer, r in m.ranges_m}


async def test_a_sparse_graph_ranges_its_edges_only_with_the_complete_graphs_draws():
    from mission_runner.enclosing.graph import ring_graph

    everyone = ring_of_four_measured(None)
    ring = ring_of_four_measured(ring_graph(4))
    edges = {(i + 1, j + 1) for i, j in zip(*np.nonzero(ring_graph(4)), strict=True)}
    assert set(ring) <= edges and len(ring) >= 4  # 0.2 dropouts: some edges read nothing
    # One draw per pair either way: what an edge reads does not depend on who else ranges.
    assert ring == {pair: r for pair, r in everyone.items() if pair in edges}
    assert set(everyone) - edges  # the complete graph ranged the non-edges too


async def test_a_ring_is_ranged_over_its_edges_and_closes_over_a_vehicle_lost():
    from mission_runner.enclosing.graph import ring_graph
    from mission_runner.wiring import RangingGraph

    graph = ring_graph(4)
    frame = graph.copy()
    frame[0, 2] = frame[2, 0] = True  # the edge that closes the ring over vehicle index 1
    path = CirclePath(kind="circle", center_m=[0.0, 10.0], radius_m=2.0, period_s=20.0)
    config = emulator_config(n=4)
    async with (
        Emulator(config) as emulator,
        InProcessBus() as bus,
        bus.subscribe(TOPICS.all_ranges(), queue_size=100_000) as ranges,
        World(
            emulator,
            bus=bus,
            topics=TOPICS,
            vehicle_ids=[1, 2, 3, 4],
            senses_target=(True, False, False, False),
            target_path=path,
            target_altitude_m=0.0,
            sensors=SensorConfig(range_noise_std_m=0.01),
            step_s=STEP_S,
            stale_after_steps=None,
            events=[EventConfig(kind="vehicle_lost", vehicle=2, at_step=8)],
            ranging=RangingGraph(graph=graph, ring=True, frame=frame),
        ) as world,
    ):
        world.start(math.ceil(emulator.time_s / STEP_S) * STEP_S, steps=16)
        await emulator.run_for(17 * STEP_S)
        async with asyncio.timeout(10):
            await world.drained()
        sets = [m for _, m in ranges.drain_messages(RangeSet)]
    pairs = {k: set() for k in range(16)}
    for ranged in each_range(sets):
        pairs[ranged.step].add(frozenset((ranged.vehicle_id, ranged.peer_id)))
    ring = {frozenset(p) for p in ({1, 2}, {2, 3}, {3, 4}, {4, 1})}
    closed = {frozenset(p) for p in ({1, 3}, {3, 4}, {4, 1})}
    # Killed at t_8, after its radio's round of step 8: the ring closes from step 9 on.
    assert all(pairs[k] == ring for k in range(9)), pairs
    assert all(pairs[k] == closed for k in range(9, 16)), pairs

"""The range aid (a simulation aid for vehicles without UWB) against emulated PX4 vehicles, from
their GPS on the GCS link or from their SIH-like ground-truth stream, publishing over a real
mosquitto once the ground station's start arrives."""

import asyncio
import math
import time
from typing import NamedTuple

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from mission_runner.bus import (
    BusTimeoutError,
    ControlCommand,
    MissionControl,
    MqttBus,
    RangeSet,
    Sender,
    TargetObservation,
    VehicleStatus,
)
from mission_runner.checks import validate_scenario
from mission_runner.runner.errors import RunnerError
from mission_runner.runner.ranges import (
    MAX_WAIT_S,
    RangeStats,
    VisionSettings,
    _Positions,
    _publish_step,
    run_range_provider,
)
from mission_runner.sensors import UwbRanging
from sitl.config import ClockConfig, EmulatorConfig
from sitl.emulator import Emulator
from tests.mosquitto import bus_test_key
from tests.sitl.helpers import free_port_config, free_truth_stream

from .flying import load

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.asyncio]

STEP_S = 0.125
PLACES = [(0.0, 0.0), (3.0, 4.0), (-6.0, 8.0)]


def scenario(broker):
    data = load("paper_tracking_flyable").model_dump(mode="json")
    data["vehicles"] = data["vehicles"][:3]
    for vehicle, (north, east) in zip(data["vehicles"], PLACES, strict=True):
        vehicle["initial_position_m"] = [north, east]
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    return validate_scenario(data)


async def fly_aid(
    mosquitto,
    *,
    source,
    truth=False,
    truth_rate_hz=100.0,
    vision=None,
    seen=None,
    clock_rate=None,
    kill_after_start_s=None,
    start_in_s=2.0,
    steps=8,
    done=(1, 2, 3),
    during=None,
):
    """Run the aid for 8 steps against three parked emulated vehicles; returns the start time,
    the aid's stats and what it published. ``seen(emulator)`` looks at the emulator before it
    stops; ``kill_after_start_s``: vehicle 3 dies that long after k = 0; ``done``: the vehicles
    whose status says done (landed) from the start; ``during(emulator, report, end_s)`` runs
    beside the aid (``report(vehicle_id, mission_id)`` says a vehicle is done, ``end_s`` is the
    last step's deadline)."""
    mission = scenario(mosquitto)
    ports = free_port_config(3, gcs=True)
    config = EmulatorConfig(
        vehicles=3,
        ports=ports,
        clock=ClockConfig(speed=clock_rate or 1.0),
        placement={"positions": [{"north_m": n, "east_m": e} for n, e in PLACES]},
        truth_stream=free_truth_stream(3, ports) if truth else {},
    )
    topics = mission.bus.topics(mission.name)
    async with (
        Emulator(config) as emulator,
        MqttBus(mosquitto.host, mosquitto.port, key=bus_test_key(), client_id="listener") as bus,
        bus.subscribe(topics.all_ranges(), queue_size=10_000) as ranges,
        bus.subscribe(topics.all_targets(), queue_size=10_000) as targets,
    ):
        start_s = math.ceil((time.time() + start_in_s) / STEP_S) * STEP_S
        if kill_after_start_s is not None:
            emulator.kill_vehicle(2, emulator.time_s + start_s + kill_after_start_s - time.time())
        # Retained, as the aid may subscribe after the ground station spoke.
        start = MissionControl(
            ControlCommand.START,
            start_s,
            mission_id="m1",
            clock_rate=clock_rate,
            clock_reference_s=start_s if clock_rate else None,
        )
        await bus.publish_message(topics.control(), start, retain=True, timeout=5.0)

        async def report(vehicle_id, mission_id="m1"):
            status = VehicleStatus(vehicle_id, 0.0, "done", steps, False, mission_id=mission_id)
            sender = Sender.vehicle(vehicle_id)
            topic = topics.status(vehicle_id)
            await bus.publish_message(topic, status, retain=True, timeout=5.0, sender=sender)

        for vehicle_id in done:
            await report(vehicle_id)
        end_s = start_s + (steps - 1) * STEP_S + mission.flight.step_deadline_s
        async with asyncio.TaskGroup() as group:
            if during is not None:
                group.create_task(during(emulator, report, end_s))
            stats = await run_range_provider(
                mission,
                source=source,
                urls=[f"udpin://0.0.0.0:{ports.gcs_remote_port}"],
                truth_port_base=config.truth_stream.remote_base,
                truth_rate_hz=truth_rate_hz,
                vision=vision,
                steps=steps,
            )
        if seen is not None:
            seen(emulator)
        await bus.publish(topics.control(), b"", retain=True, timeout=5.0)
        for vehicle_id in range(1, 4):
            sender = Sender.vehicle(vehicle_id)
            await bus.publish(
                topics.status(vehicle_id), b"", retain=True, timeout=5.0, sender=sender
            )
        # The aid returns once it has published; the broker may still be delivering the last.
        sets, measured = [], []
        while len(measured) < stats.ranges:
            sets.append((await ranges.receive_message(RangeSet, timeout=5.0))[1])
            measured += Ranged.all_of(sets[-1])
        sets += [m for _, m in ranges.drain_messages(RangeSet)]  # empty ones, if any
        observed = [m for _, m in targets.drain_messages(TargetObservation)]
    return start_s, stats, measured, observed, sets


class Ranged(NamedTuple):
    """One range of a received set."""

    vehicle_id: int
    peer_id: int
    time_s: float
    range_m: float
    step: int | None

    @classmethod
    def all_of(cls, ranges: RangeSet) -> list["Ranged"]:
        return [
            cls(ranges.vehicle_id, peer, ranges.time_s, range_m, ranges.step)
            for peer, range_m in ranges.ranges_m
        ]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("source", ["gps", "sih"])
async def test_ranges_match_the_true_distances_on_the_step_grid(mosquitto, source):
    start_s, stats, measured, observed, sets = await fly_aid(
        mosquitto, source=source, truth=source == "sih"
    )
    assert stats.steps == 8
    assert stats.ranges == len(measured) == 6 * (8 - stats.skipped)
    # One set per vehicle and step, each the vehicle's ranges to both others.
    assert sorted((m.vehicle_id, m.step) for m in sets) == sorted(
        {(m.vehicle_id, m.step) for m in measured}
    )
    assert all(len(m.ranges_m) == 2 for m in sets)
    assert stats.missing_vehicles == 0
    assert {m.step for m in measured} == set(range(8))
    for message in measured:
        assert message.time_s == pytest.approx(start_s + message.step * STEP_S)
        here, there = PLACES[message.vehicle_id - 1], PLACES[message.peer_id - 1]
        assert message.range_m == pytest.approx(math.dist(here, there), abs=0.05)
    assert observed and {m.vehicle_id for m in observed} == {1}
    # The virtual target starts at the scenario's origin and moves at 0.8 m/s north.
    first = observed[0]
    target_north = 0.8 * (first.time_s - start_s)
    assert first.range_m == pytest.approx(np.hypot(*PLACES[0]) + target_north, abs=0.05)
    assert first.velocity_north_m_s == pytest.approx(0.8, abs=1e-3)
    # The truth recorded for scoring: every vehicle at its place at every step.
    assert [sample.step for sample in stats.truth] == list(range(8))
    for sample in stats.truth:
        assert sample.alive.all()
        assert sample.positions_m == pytest.approx(np.array(PLACES), abs=0.05)


@pytest.mark.timeout(60)
@pytest.mark.parametrize(("asked_hz", "low_hz", "high_hz"), [(None, 15, 35), (100.0, 40, 130)])
async def test_the_aid_asks_the_simulator_for_ground_truth_fast_enough(
    mosquitto, asked_hz, low_hz, high_hz
):
    """SIH (and the emulator's truth stream, like it) sends 25 Hz of ground truth; each step's
    ranges wait for the first sample after t_k, so the aid asks for more (SET_MESSAGE_INTERVAL
    on the truth link) unless told not to. (The emulator streams at most at its physics rate,
    50 Hz here.)"""
    _, stats, measured, _, _ = await fly_aid(
        mosquitto, source="sih", truth=True, truth_rate_hz=asked_hz
    )
    assert stats.ranges == len(measured) == 6 * (8 - stats.skipped)
    assert set(stats.position_rates_hz) == {1, 2, 3}
    for rate in stats.position_rates_hz.values():
        assert low_hz < rate < high_hz


@pytest.mark.timeout(60)
async def test_the_truth_rate_asked_is_per_second_of_host_time(mosquitto):
    """On a mission clock at 2x (PX4's speed factor 2, the emulator at speed 2 like it) the aid
    asks for half the rate in the autopilot's time, so that it parses what it asked for per
    second of the host's, not twice that."""
    _, stats, measured, _, _ = await fly_aid(
        mosquitto, source="sih", truth=True, truth_rate_hz=40.0, clock_rate=2.0
    )
    assert stats.ranges == len(measured) == 6 * (8 - stats.skipped)
    for rate in stats.position_rates_hz.values():
        assert 30 < rate < 50  # 20 Hz of the emulator's clock at 2x: 40 Hz of the host's


@pytest.mark.timeout(60)
async def test_steps_past_their_deadline_are_skipped_so_the_aid_catches_up(mosquitto):
    """An aid behind (here: started a second after k = 0) measures the steps whose deadline
    has passed for the truth and publishes none of them, then every step from the first it
    can still make on."""
    _, stats, measured, _, _ = await fly_aid(mosquitto, source="gps", start_in_s=-1.0, steps=40)
    assert 8 <= stats.skipped < 40
    # Steps 0-7 were past their deadline before the aid started; from then on it keeps up (a
    # step may still be skipped, or lack a vehicle's GPS fix, on a busy machine).
    assert measured and min(m.step for m in measured) >= 8
    assert len(stats.lateness_s) == 40 - stats.skipped  # each published step, timed
    assert stats.ranges == len(measured)
    assert [sample.step for sample in stats.truth] == list(range(40))


@pytest.mark.timeout(60)
async def test_the_aid_feeds_each_instance_a_vision_odometry_from_its_truth(mosquitto):
    """With a vision rate, every instance gets ODOMETRY on its truth link (as a VIO on the
    vehicle would send it): local NED from where its truth started, the truth's attitude, the
    noise's variance in the covariance, at the asked rate."""
    settings = VisionSettings(rate_hz=20.0, position_noise_std_m=0.01, velocity_noise_std_m_s=0.02)
    received = {}

    def seen(emulator):
        for index in range(3):
            autopilot = emulator.autopilot(index)
            received[index + 1] = (autopilot.external_vision_received, autopilot.external_vision)

    _, stats, measured, _, _ = await fly_aid(
        mosquitto, source="sih", truth=True, vision=settings, seen=seen
    )
    assert stats.ranges == len(measured) == 6 * (8 - stats.skipped)
    assert set(stats.vision_rates_hz) == {1, 2, 3}
    for vehicle_id, (count, last) in received.items():
        assert 12 < stats.vision_rates_hz[vehicle_id] < 25
        assert count >= 8 * STEP_S * 12  # the mission's second, at least, and the wait before it
        assert last.get_srcSystem() == vehicle_id
        assert last.frame_id == last.child_frame_id == mavlink.MAV_FRAME_LOCAL_NED
        assert last.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_VIO
        # Parked: where it started, standing still, level, within a few noise std.
        assert np.hypot(last.x, last.y) < 0.06 and abs(last.z) < 0.06
        assert np.hypot(last.vx, last.vy) < 0.1
        assert abs(last.q[0]) == pytest.approx(1.0, abs=0.01)
        assert last.pose_covariance[0] == pytest.approx(0.01**2)
        assert last.velocity_covariance[6] == pytest.approx(0.02**2)


async def _condition(check, timeout_s=10.0):
    """Until ``check()`` holds (polled), at most ``timeout_s``."""
    async with asyncio.timeout(timeout_s):
        while not check():
            await asyncio.sleep(0.02)


@pytest.mark.timeout(60)
async def test_the_vision_odometry_outlives_the_steps_until_every_vehicle_is_done(mosquitto):
    """A VIO does not switch off when the mission's steps end: the aid goes on feeding every
    instance while the vehicles land, until each reports itself done for this mission (a done
    of another mission does not count), then stops."""
    settings = VisionSettings(rate_hz=20.0)
    counts = []

    async def during(emulator, report, end_s):
        def received():
            return emulator.autopilot(2).external_vision_received

        await _condition(lambda: time.time() > end_s + 0.3)
        after_steps = received()
        await _condition(lambda: received() >= after_steps + 5)  # still fed, steps over
        await report(3, mission_id="another")
        before = received()
        await _condition(lambda: received() >= before + 5)  # another mission's: still fed
        counts.append(received())
        await report(3)

    _, stats, _, _, _ = await fly_aid(
        mosquitto, source="sih", truth=True, vision=settings, done=(1, 2), during=during
    )
    assert counts  # the vision went on after the steps until vehicle 3 was done
    assert stats.vehicles_done == 3
    assert 0.3 < stats.vision_after_steps_s < 10.0


async def test_a_vision_odometry_needs_a_simulator_truth(mosquitto):
    with pytest.raises(RunnerError, match="--source sih"):
        await run_range_provider(
            scenario(mosquitto), source="gps", vision=VisionSettings(rate_hz=50.0), steps=1
        )


@pytest.mark.parametrize(
    "settings",
    [
        {"rate_hz": 0.0},
        {"rate_hz": float("nan")},
        {"rate_hz": 50.0, "position_noise_std_m": -0.1},
        {"rate_hz": 50.0, "velocity_noise_std_m_s": float("inf")},
    ],
)
async def test_vision_settings_refuse_what_no_sensor_does(settings):
    with pytest.raises(RunnerError, match="vision odometry"):
        VisionSettings(**settings)


async def test_a_message_not_handed_over_in_time_is_dropped_and_counted():
    """One range the bus cannot hand over in time is lost like a radio packet: the others of
    the step still go out, the aid goes on, and its count says so."""
    mission = scenario(type("Broker", (), {"host": "127.0.0.1", "port": 1})())
    topics = mission.bus.topics(mission.name)
    sent = []

    class SlowOnce:
        async def publish_message(self, topic, message, *, timeout):
            if topic == topics.ranges(1):
                raise BusTimeoutError(f"publish to {topic}", timeout)
            sent.append(topic)

    stats = RangeStats()
    positions = np.array([[*place, -5.0] for place in PLACES])
    noise = (np.random.default_rng(0), UwbRanging(mission.sensors, len(positions), 0.1))
    await _publish_step(SlowOnce(), topics, mission, positions, 0, 10.0, 10.0, noise, stats)
    assert stats.unsent == 1
    # Vehicle 1's set (two ranges) is lost; the others' sets and the target observation go out.
    assert stats.ranges == 4 and len(sent) == 3
    assert topics.ranges(1) not in sent


async def test_just_past_its_newest_truth_a_vehicle_is_taken_at_that_velocity_at_once():
    """A step's ranges went out only once every vehicle had a truth sample after t_k (half a
    truth period late on average, and every vehicle's step waited for them). A sample at most
    ``extrapolate_s`` before t_k, with its velocity, answers at once; further back, the aid
    waits as before."""
    broker = type("Broker", (), {"host": "127.0.0.1", "port": 1883})()
    positions = _Positions(scenario(broker))
    north_per_deg = 111_195.0  # m per degree of latitude (the aid's flat earth)
    for unix_s, north_m in ((100.00, 0.0), (100.01, 0.02)):
        positions.add(
            1, unix_s, north_m / north_per_deg, 0.0, 10.0, velocity_ned_m_s=(2.0, 0.0, -1.0)
        )

    async def at(unix_s, extrapolate_s):
        task = asyncio.create_task(positions.bracketing(unix_s, 5.0, extrapolate_s=extrapolate_s))
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        return task

    quick = await at(100.02, 0.015)
    assert quick.done()
    assert quick.result()[0] == pytest.approx([0.04, 0.0, -0.01], abs=1e-3)
    assert np.isnan(quick.result()[1:]).all()  # never heard of: not waited for
    slow = await at(100.03, 0.015)  # 20 ms past the newest: waits for the next sample
    assert not slow.done()
    positions.add(1, 100.04, 0.08 / north_per_deg, 0.0, 10.0)
    assert (await slow)[0] == pytest.approx([0.06, 0.0, 0.0], abs=1e-3)


@pytest.mark.timeout(60)
async def test_a_vehicle_whose_truth_stops_costs_no_step_more_than_its_deadline(mosquitto):
    """Vehicle 3 dies mid-mission: its truth stops, and for STALE_AFTER_S it still counts as
    heard. The aid used to wait 0.25 s for it at every step, longer than a step, and fell
    further behind at each (seconds behind on four SIH at speed factor 2, every vehicle waiting
    on it); it now waits no longer than the step's deadline and publishes the others."""
    _, stats, measured, _, _ = await fly_aid(
        mosquitto, source="sih", truth=True, kill_after_start_s=2.5 * STEP_S
    )
    assert stats.missing_vehicles >= 4  # vehicle 3 had no position in its last steps
    assert stats.ranges == len(measured) < 8 * 6
    assert max(stats.lateness_s) < MAX_WAIT_S  # every wait ended at the deadline, not later


async def test_on_a_ring_the_aid_ranges_its_edges_and_closes_it_over_a_silent_vehicle():
    """A sparse graph: the aid ranges the ring's edges only, among the vehicles it heard in the
    last ``STALE_AFTER_S``; over one whose truth stopped, the ring closes."""
    from mission_runner.wiring import RangingGraph

    data = load("paper_tracking_flyable").model_dump(mode="json")
    data["algorithm"]["graph"] = {"kind": "ring"}
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": "127.0.0.1", "port": 1}}
    mission = validate_scenario(data)
    topics = mission.bus.topics(mission.name)
    ranging = RangingGraph.of(mission)
    positions = _Positions(mission)
    north_per_deg = 111_195.0
    for vehicle_id, newest_s in ((1, 100.0), (2, 98.5), (3, 100.0), (4, 100.0)):
        positions.add(vehicle_id, newest_s, vehicle_id / north_per_deg, 0.0, 10.0)
    assert positions.heard(100.0).tolist() == [True, False, True, True]

    class Sent:
        def __init__(self):
            self.sets = {}

        async def publish_message(self, topic, message, *, timeout):
            if isinstance(message, RangeSet):
                self.sets[message.vehicle_id] = {peer for peer, _ in message.ranges_m}

    everyone = np.array([[4.0 * i, 0.0, -5.0] for i in range(4)])
    bus = Sent()
    for heard, expected in (
        (np.ones(4, dtype=bool), {1: {2, 4}, 2: {1, 3}, 3: {2, 4}, 4: {1, 3}}),
        (positions.heard(100.0), {1: {3, 4}, 2: set(), 3: {1, 4}, 4: {1, 3}}),
    ):
        noise = (np.random.default_rng(0), UwbRanging(mission.sensors, 4, STEP_S))
        graph = ranging.among(heard)
        await _publish_step(
            bus, topics, mission, everyone, 0, 10.0, 10.0, noise, RangeStats(), graph=graph
        )
        assert bus.sets == expected

"""The vehicle controller's step loop against a scripted vehicle, a real in-process bus and a clock
that only moves when the controller sleeps (or a test stalls it).

Vehicle 2 of a three-vehicle swarm is under test. Its neighbours, vehicles 1 and 3, exist only as
what the bus shows of them: at each t_k their step-k messages and the ranges vehicle 2's UWB
measured to them, published the moment the controller wakes for t_k. Nothing waits on wall time
except the controller's own deadlines for inputs that never come, kept to a few milliseconds.
"""

import asyncio
import contextlib
import dataclasses
import itertools
import math

import numpy as np
import pytest

from mission_runner.bus import (
    RangeSet,
    StepMessage,
    TargetObservation,
    VehicleStatus,
    open_bus,
    shared_range,
)
from mission_runner.checks import validate_scenario
from mission_runner.enclosing import NeighbourReport, TargetReport, VehicleEnclosing
from mission_runner.runner import pipeline
from mission_runner.runner.controller import build_controller
from mission_runner.runner.odometry import OdometrySample
from mission_runner.wiring import algorithm_params

T = 0.125
START_S = 10.0
OMEGA = math.pi / 4
OWN = 2
PEERS = (1, 3)
ORIGINS = {1: (-3.0, -2.0), 2: (2.0, -4.0), 3: (3.0, 3.0)}
PHASES = {1: 0.0, 2: 0.3, 3: 0.9}
ALTITUDES = {1: 4.0, 2: 5.0, 3: 6.0}
TARGET_VELOCITY = (0.8, 0.0)  # relayed by vehicle 1, which senses the target


def t_(k):
    return START_S + k * T


def make_scenario(*, flight=None, speed_limit_m_s=10.0, sensing=(1,), **algorithm):
    vehicles = [
        {
            "id": vehicle_id,
            "initial_position_m": list(ORIGINS[vehicle_id]),
            "initial_phase_rad": PHASES[vehicle_id],
            "senses_target": vehicle_id in sensing,
            "altitude_m": ALTITUDES[vehicle_id],
        }
        for vehicle_id in (1, 2, 3)
    ]
    vehicles[OWN - 1]["speed_limit_m_s"] = speed_limit_m_s
    return validate_scenario(
        {
            "name": "controller_unit",
            "timing": {"step_s": T, "steps": 40},
            "algorithm": {
                "beta": 4.0,
                "saturation_m_s": 0.4,
                "forgetting_factor": 0.7,
                "omega_rad_s": OMEGA,
                "radius_m": 4.0,
                **algorithm,
            },
            "target": {"path": {"kind": "line", "start_m": [0.0, 0.0], "velocity_m_s": [0.8, 0]}},
            "vehicles": vehicles,
            "flight": {
                "step_deadline_s": 0.002,  # wall seconds lost per step with a missing input
                "silence_timeout_s": 1.0,
                **(flight or {}),
            },
        }
    )


def neighbour_position(peer, s):
    """Where neighbour ``peer`` is (world north, east) ``s`` seconds into the mission."""
    north, east = ORIGINS[peer]
    return north + 0.6 * math.sin(1.1 * s + peer), east + 0.5 * math.cos(0.8 * s + 2 * peer)


def wandering(s):
    """Vehicle 2's own odometry (north, east, down) ``s`` seconds into the mission."""
    return 0.4 * math.sin(0.9 * s), 0.3 * s, -ALTITUDES[OWN]


def bobbing(s):
    """As :func:`wandering`, with an altitude hold that wanders by decimetres."""
    north, east, down = wandering(s)
    return north, east, down + 0.4 * math.sin(3.0 * s)


def standing(s):
    return 0.0, 0.0, -ALTITUDES[OWN]


class FakeOdometry:
    """The link's odometry track: ``path(s)`` -> (north, east, down) or None (telemetry gone)."""

    def __init__(self, path):
        self.path = path
        self.latest = None

    def at(self, time_s, *, extrapolate_s=0.0):
        sample = self.path(time_s - START_S)
        if sample is not None:
            self.latest = OdometrySample(time_s, *sample)
        return sample


class FakeLink:
    """Records every velocity setpoint; ``stall_s`` makes one setpoint call (by index) take that
    long on the mission clock, as a blocked link or a slow machine would."""

    def __init__(self, path, clock):
        self.odometry = FakeOdometry(path)
        self.clock = clock
        self.setpoints = []
        self.stall_s = {}
        self.in_control = True
        self.control_lost = None

    async def odometry_updated(self):
        await asyncio.Event().wait()  # no telemetry ever arrives: the controller's timeout ends it

    async def set_velocity_ned(self, north_m_s, east_m_s, down_m_s):
        self.clock.now += self.stall_s.get(len(self.setpoints), 0.0)
        self.setpoints.append((north_m_s, east_m_s, down_m_s))


class FakeClock:
    """Mission time that stands still until the controller sleeps to a later instant (it arrives
    at once) or a stall moves it. On every wake, ``on_wake(t)`` runs and the event loop settles,
    so whatever it published is in the controller's inbox before the controller goes on."""

    lockstep = False
    rate = 1.0

    def __init__(self, now_s):
        self.now = now_s
        self.released = []
        self.on_wake = None

    def now_s(self):
        return self.now

    def release(self, time_s):
        self.released.append(time_s)

    @contextlib.asynccontextmanager
    async def commanding(self, released_s):
        yield

    async def sleep_until(self, time_s):
        self.now = max(self.now, time_s)
        if self.on_wake is not None:
            await self.on_wake(time_s)
        for _ in range(5):
            await asyncio.sleep(0)


@dataclasses.dataclass
class Delivered:
    """A neighbour's step-k input as it reached vehicle 2 on time."""

    message: StepMessage
    horizontal_range_m: float


class Neighbours:
    """Vehicles 1 and 3 as vehicle 2's bus shows them (see the module docstring)."""

    def __init__(self, bus, topics, own_path):
        self.bus = bus
        self.topics = topics
        self.own_path = own_path
        self.silent = set()  # steps at which neither is heard
        self.late = {}  # step -> peers whose step-k message and range come at t_(k+1)
        self.lost = {}  # step -> peers whose step-k message and range never come
        self.dropped = {}  # step -> peers whose message comes, but not vehicle 2's range to it
        self.heights = True  # step messages carry odometry_down_m
        self.ranges_3d = True  # ranges as UWB measures them (else already horizontal)
        self.on_time = {}  # step -> {peer: Delivered}
        self.shared = None  # peer -> what its radio reads more than vehicle 2's (shared ranges)
        self._held_back = []
        # k -> vehicle 1's relay fields at step k (default: it observes the target itself).
        self.relay = lambda k: {
            "target_odometry_north_m": TARGET_VELOCITY[0] * k * T,
            "target_odometry_east_m": TARGET_VELOCITY[1] * k * T,
            "target_velocity_north_m_s": TARGET_VELOCITY[0],
            "target_velocity_east_m_s": TARGET_VELOCITY[1],
        }
        self.own_tracker = None  # k -> vehicle 2's TargetObservation at t_k, if it has a tracker
        self.commands = {}  # peer -> the (north, east) setpoint its step messages say it flies

    def inputs(self, k, peer):
        """Neighbour ``peer``'s step-k message and vehicle 2's range to it, and the horizontal
        range (what the law should get)."""
        s = k * T
        north, east = neighbour_position(peer, s)
        own_north, own_east, own_down = self.own_path(s)
        horizontal = math.hypot(
            ORIGINS[OWN][0] + own_north - north, ORIGINS[OWN][1] + own_east - east
        )
        down = -ALTITUDES[peer]
        measured = math.hypot(horizontal, own_down - down) if self.ranges_3d else horizontal
        relay = self.relay(k) if peer == 1 else {}
        command = self.commands.get(peer)
        if command is not None:
            relay = {**relay, "command_north_m_s": command[0], "command_east_m_s": command[1]}
        message = StepMessage(
            peer,
            k,
            t_(k),
            PHASES[peer] + OMEGA * s,
            north - ORIGINS[peer][0],
            east - ORIGINS[peer][1],
            odometry_down_m=down if self.heights else None,
            ranges_m=None
            if self.shared is None
            else ((OWN, shared_range(measured + self.shared[peer])),),
            **relay,
        )
        return message, measured, horizontal

    async def at(self, time_s):
        """The clock woke vehicle 2 for t_k: what was held back arrives, then step k's inputs."""
        k = round((time_s - START_S) / T)
        for topic, message in self._held_back:
            await self.bus.publish_message(topic, message, timeout=1.0)
        self._held_back.clear()
        if self.own_tracker is not None:
            observation = self.own_tracker(k)
            if observation is not None:
                await self.bus.publish_message(self.topics.target(OWN), observation, timeout=1.0)
        if k in self.silent:
            return
        # Vehicle 2's ranges of the step come in one set: the on-time peers', and in a second
        # set held back with their messages, the late peers' (a lost peer's are not in either).
        on_time, late = [], []
        for peer in PEERS:
            if peer in self.lost.get(k, ()):
                continue
            step, measured_m, horizontal = self.inputs(k, peer)
            if peer in self.late.get(k, ()):
                self._held_back.append((self.topics.step(peer), step))
                late.append((peer, measured_m))
                continue
            self.on_time.setdefault(k, {})[peer] = Delivered(step, horizontal)
            await self.bus.publish_message(self.topics.step(peer), step, timeout=1.0)
            if peer not in self.dropped.get(k, ()):
                on_time.append((peer, measured_m))
        ranges = self.topics.ranges(OWN)
        if late:
            self._held_back.append((ranges, RangeSet(OWN, t_(k), tuple(late), step=k)))
        own = RangeSet(OWN, t_(k), tuple(on_time), step=k)
        await self.bus.publish_message(ranges, own, timeout=1.0)


@dataclasses.dataclass
class Rig:
    scenario: object
    controller: object
    link: FakeLink
    clock: FakeClock
    neighbours: Neighbours
    own_steps: object  # subscription to vehicle 2's step topic
    own_status: object  # subscription to vehicle 2's status topic

    async def fly(self, steps):
        return await self.controller.run(START_S, steps)

    def published_steps(self):
        return [message for _, message in self.own_steps.drain_messages(StepMessage)]

    def statuses(self):
        return [message for _, message in self.own_status.drain_messages(VehicleStatus)]


@contextlib.asynccontextmanager
async def rig(scenario=None, *, path=wandering, truth=None, **settings):
    """Vehicle 2's controller on the scenario (default: :func:`make_scenario`), flying a link
    whose odometry follows ``path`` (the vehicle follows ``truth``, by default ``path``: the
    ranges come from it); ``settings`` override :class:`ControllerSettings` fields."""
    scenario = scenario or make_scenario()
    topics = scenario.bus.topics(scenario.name)
    vehicle = next(v for v in scenario.vehicles if v.id == OWN)
    async with (
        open_bus(scenario.bus, sender=None) as bus,
        bus.subscribe(topics.step(OWN)) as own_steps,
        bus.subscribe(topics.status(OWN)) as own_status,
    ):
        clock = FakeClock(START_S)
        link = FakeLink(path, clock)
        controller = build_controller(scenario, vehicle, link=link, bus=bus, clock=clock)
        controller.settings = dataclasses.replace(controller.settings, **settings)
        neighbours = Neighbours(bus, topics, truth or path)
        clock.on_wake = neighbours.at
        yield Rig(scenario, controller, link, clock, neighbours, own_steps, own_status)


async def fly(steps, scenario=None, *, setup=None, **kwargs):
    """Records and setpoints of a flight of ``steps`` steps; ``setup(rig)`` scripts it first."""
    async with rig(scenario, **kwargs) as flight:
        if setup is not None:
            setup(flight)
        records = await flight.fly(steps)
        return records, flight.link.setpoints


def law_alone(scenario, on_time, steps):
    """(phase, command) of vehicle 2's law at each step, stepped directly with the inputs that
    reached the controller on time (:attr:`Neighbours.on_time`), horizontal ranges and the
    target velocity vehicle 1 relays: what the controller should have made of them."""
    law = VehicleEnclosing(algorithm_params(scenario), OWN, [1, 2, 3], PHASES[OWN], OMEGA)
    out = []
    for k in range(steps):
        delivered = on_time.get(k, {})
        phase = law.phase_rad
        command = law.step(
            own_odometry_m=wandering(k * T)[:2],
            neighbours={
                peer: NeighbourReport(
                    d.message.phase_rad, (d.message.odometry_north_m, d.message.odometry_east_m)
                )
                for peer, d in delivered.items()
            },
            ranges_m={peer: d.horizontal_range_m for peer, d in delivered.items()},
            target=TargetReport((math.nan, math.nan), TARGET_VELOCITY),
            members=[1, 2, 3],
        )
        out.append((phase, command))
    return out


def horizontal(velocity):
    return np.asarray(velocity[:2], dtype=float)


# --- following -----------------------------------------------------------------------------------


@pytest.mark.asyncio
async def test_messages_and_ranges_of_a_vehicle_that_is_not_a_graph_neighbour_are_ignored():
    # Graph 1-2, 1-3 (indices 0-1, 0-2): vehicle 3 talks and is ranged, but is not 2's neighbour.
    steps = 6
    scenario = make_scenario(graph={"kind": "edges", "edges": [[0, 1], [0, 2]]})
    async with rig(scenario) as flight:
        records = await flight.fly(steps)
        delivered = flight.neighbours.on_time
    assert all(3 in delivered[k] for k in range(steps))  # heard and ranged all along
    assert [r.neighbours_used for r in records] == [(1,)] * steps
    assert [sorted(r.estimates_m) for r in records] == [[1]] * steps
    graph = np.array([[False, True, True], [True, False, False], [True, False, False]])
    law = VehicleEnclosing(
        algorithm_params(scenario), OWN, [1, 2, 3], PHASES[OWN], OMEGA, graph=graph
    )
    for record, setpoint in zip(records, flight.link.setpoints, strict=True):
        command = law.step(
            own_odometry_m=wandering(record.step * T)[:2],
            neighbours={
                peer: NeighbourReport(
                    d.message.phase_rad, (d.message.odometry_north_m, d.message.odometry_east_m)
                )
                for peer, d in delivered[record.step].items()
            },
            ranges_m={peer: d.horizontal_range_m for peer, d in delivered[record.step].items()},
            target=TargetReport((math.nan, math.nan), TARGET_VELOCITY),
            members=[1, 2, 3],
        )
        np.testing.assert_allclose(horizontal(setpoint), command.velocity_m_s, atol=1e-9)
    complete, _ = await fly(steps)
    assert not np.allclose(records[-1].velocity_ned_m_s, complete[-1].velocity_ned_m_s)


@pytest.mark.asyncio
async def test_each_step_publishes_the_own_message_runs_the_law_and_sends_its_command():
    steps = 6
    async with rig() as flight:
        records = await flight.fly(steps)
        published = flight.published_steps()
        statuses = flight.statuses()
        delivered = flight.neighbours.on_time

    assert [r.step for r in records] == list(range(steps))
    assert [r.state for r in records] == ["following"] * steps
    assert flight.controller.state == "following"
    assert [r.neighbours_used for r in records] == [PEERS] * steps
    assert [sorted(r.estimates_m) for r in records] == [[1, 3]] * steps

    # Its own step-k message: the phase it steps from, its odometry and height sampled at t_k.
    assert [m.step for m in published] == list(range(steps))
    for record, message in zip(records, published, strict=True):
        north, east, down = wandering(record.step * T)
        assert (message.vehicle_id, message.time_s) == (OWN, t_(record.step))
        assert message.phase_rad == record.phase_rad
        assert (message.odometry_north_m, message.odometry_east_m) == (north, east)
        assert message.odometry_down_m == down == record.odometry_m[2]
        assert not message.has_target  # vehicle 2 does not sense it: nothing to relay

    # The setpoint is the law's command from exactly these inputs (3-D ranges made horizontal,
    # the target velocity relayed by vehicle 1), untouched: no lead, no tracking, no clamp.
    expected = law_alone(flight.scenario, delivered, steps)
    for record, setpoint, (phase, command) in zip(
        records, flight.link.setpoints, expected, strict=True
    ):
        assert record.phase_rad == pytest.approx(phase, abs=1e-12)
        np.testing.assert_allclose(horizontal(setpoint), command.velocity_m_s, atol=1e-9)
        np.testing.assert_allclose(record.consensus_m_s, command.consensus_m_s, atol=1e-9)
        for peer in PEERS:
            np.testing.assert_allclose(
                record.estimates_m[peer], command.estimates_m[peer], atol=1e-9
            )
        assert setpoint == record.velocity_ned_m_s
        assert setpoint[2] == 0.0  # at its altitude
        assert record.setpoint_sent_s == t_(record.step)

    # A status when the state changes, else once a second: here the first step's only.
    assert [(s.step, s.state) for s in statuses] == [(0, "following")]
    assert all(s.tracking_ok and s.vehicle_id == OWN for s in statuses)
    assert flight.clock.released == [
        t_(k) + flight.controller.settings.release_s for k in range(steps)
    ]


@pytest.mark.asyncio
async def test_a_vehicle_hears_its_peers_step_messages_not_its_own(monkeypatch):
    """Subscribed to each other member's step topic: over MQTT the wildcard brought every own
    message back (a quarter of a vehicle's step traffic in a formation of four, each
    authenticated and decoded only to be ignored), and any stranger's."""
    async with rig() as flight:
        bus = flight.controller.bus
        patterns = []

        def subscribe(pattern, **options):
            patterns.append(pattern)
            return type(bus).subscribe(bus, pattern, **options)

        monkeypatch.setattr(bus, "subscribe", subscribe)
        records = await flight.fly(3)
    topics = flight.scenario.bus.topics(flight.scenario.name)
    steps = [pattern for pattern in patterns if pattern.endswith("/step")]
    assert steps == [topics.step(1), topics.step(3)]
    assert [record.state for record in records] == ["following"] * 3


@pytest.mark.asyncio
async def test_step_messages_carry_the_setpoint_in_force_and_the_guard_uses_the_neighbours(
    monkeypatch,
):
    seen = []

    def guard(velocity, relative, distance, own, others, **settings):
        seen.append((own, others))
        return velocity

    monkeypatch.setattr(pipeline, "separation_guard", guard)
    async with rig(min_separation_m=1.0) as flight:
        # Vehicle 3 says it flies faster than any vehicle of the mission may (10 m/s).
        flight.neighbours.commands = {1: (0.5, -0.25), 3: (40.0, 0.0)}
        await flight.fly(4)
        published = flight.published_steps()
        setpoints = flight.link.setpoints

    # None before the first setpoint, then the one sent at the step before.
    assert published[0].command_m_s is None
    for k in range(1, 4):
        assert published[k].command_m_s == tuple(horizontal(setpoints[k - 1]))
    # The guard saw its own setpoint in force and vehicle 1's; vehicle 3's command was dropped
    # (unknown: NaN) and counted.
    assert np.isnan(seen[0][0]).all()
    for k in range(1, 4):
        np.testing.assert_allclose(seen[k][0], horizontal(setpoints[k - 1]))
    for _, others in seen:
        np.testing.assert_allclose(others[0], [0.5, -0.25])
        assert np.isnan(others[1]).all()
    assert flight.controller.command_gate.rejected == {"command_speed": 4}


# --- holding and losing the vehicle --------------------------------------------------------------


@pytest.mark.asyncio
async def test_holds_when_no_neighbour_is_heard_for_the_silence_timeout_and_resumes():
    def silence(flight):
        flight.neighbours.silent = {3, 4, 5, 6, 7}

    # Last heard at t_2; 0.3 s of silence is over between t_4 (0.25 s) and t_5 (0.375 s).
    scenario = make_scenario(flight={"silence_timeout_s": 0.3})
    records, setpoints = await fly(11, scenario, setup=silence)

    states = [r.state for r in records]
    assert states == ["following"] * 5 + ["holding"] * 3 + ["following"] * 3
    for record, setpoint in zip(records[5:8], setpoints[5:8], strict=True):
        assert setpoint == (0.0, 0.0, 0.0)
        assert record.neighbours_used == ()
        assert record.estimates_m == {}
        assert record.consensus_m_s == (0.0, 0.0)
    # Silent but not yet timed out: the law runs on what it has, with nobody in its sums.
    assert [r.neighbours_used for r in records[3:5]] == [(), ()]
    # The oscillator kept turning, uncoupled, through the hold.
    for before, after in itertools.pairwise(records[5:9]):
        assert after.phase_rad - before.phase_rad == pytest.approx(OMEGA * T, abs=1e-12)
    # Data is back at k = 8: the law drives the vehicle again, with both neighbours.
    for record, setpoint in zip(records[8:], setpoints[8:], strict=True):
        assert record.neighbours_used == PEERS
        assert np.hypot(*setpoint[:2]) > 0.5


@pytest.mark.asyncio
async def test_lost_own_odometry_holds_then_gives_the_vehicle_up():
    def telemetry_until_step_3(s):
        return None if s >= 3 * T - 1e-9 else wandering(s)

    async with rig(
        path=telemetry_until_step_3, truth=wandering, odometry_timeout_s=0.001
    ) as flight:
        records = await flight.fly(20)
        published = flight.published_steps()
        statuses = flight.statuses()

    lost_after = flight.controller.settings.lost_after_missed_steps
    assert lost_after == 3
    # Steps 3, 4 and 5 find no odometry; after the third the controller stops driving it.
    assert len(records) == 6
    assert [r.state for r in records] == ["following"] * 3 + ["holding"] * 3
    assert flight.controller.state == "lost"
    assert flight.link.setpoints[3:] == [(0.0, 0.0, 0.0)] * 3  # no altitude hold without height
    assert len(flight.link.setpoints) == 6  # nothing after it was given up
    assert flight.clock.now == t_(5)  # and it never waited for another step
    assert all(math.isnan(v) for r in records[3:] for v in r.odometry_m)
    assert [m.step for m in published] == [0, 1, 2]  # no step message without odometry
    assert statuses[-1].state == "lost"
    assert statuses[-1].step == 5
    assert not statuses[-1].tracking_ok
    # A status at each change of state, each saying how many steps were held so far (the
    # ground's verdict counts them).
    assert [(s.step, s.state, s.stale_steps) for s in statuses] == [
        (0, "following", 0),
        (3, "holding", 1),
        (5, "lost", 3),
    ]
    assert flight.controller.stale_steps == 3


# --- who flies the vehicle ------------------------------------------------------------------------


def taken_over_at(step, reason="switched to HOLD by someone other than the runner"):
    """A setup that has someone else take the vehicle (the link says so) at t_step."""

    def setup(flight):
        feed = flight.clock.on_wake

        async def on_wake(t):
            if t >= t_(step) - 1e-9:
                flight.link.in_control, flight.link.control_lost = False, reason
            await feed(t)

        flight.clock.on_wake = on_wake

    return setup


@pytest.mark.asyncio
async def test_a_vehicle_taken_over_is_no_longer_driven_and_says_so():
    async with rig() as flight:
        taken_over_at(3)(flight)
        records = await flight.fly(10)
        published = flight.published_steps()
        statuses = flight.statuses()

    # Step 3's wait is where the takeover is seen: that step holds (never "following") and
    # sends no setpoint to a vehicle someone else flies; from step 4 nothing is sent at all.
    assert [r.state for r in records] == ["following"] * 3 + ["holding"]
    assert flight.controller.state == "taken_over"
    assert len(flight.link.setpoints) == 3
    assert [m.step for m in published] == [0, 1, 2, 3]
    assert statuses[-1].state == "taken_over"
    assert statuses[-1].step == 4
    assert not statuses[-1].tracking_ok
    assert "someone other than the runner" in statuses[-1].detail


@pytest.mark.asyncio
async def test_never_following_before_the_vehicle_is_seen_armed_in_offboard():
    async with rig() as flight:
        flight.link.in_control = False  # OFFBOARD asked for, not yet seen in a heartbeat
        feed = flight.clock.on_wake

        async def on_wake(t):
            flight.link.in_control = t >= t_(3) - 1e-9  # the heartbeat comes at t_3
            await feed(t)

        flight.clock.on_wake = on_wake
        records = await flight.fly(6)

    assert [r.state for r in records] == ["holding"] * 3 + ["following"] * 3
    assert all(setpoint[:2] == (0.0, 0.0) for setpoint in flight.link.setpoints[:3])


@pytest.mark.asyncio
async def test_the_operators_hold_hovers_in_place_until_resume():
    async with rig() as flight:
        feed = flight.clock.on_wake

        async def on_wake(t):
            flight.controller.operator_hold = t_(2) - 1e-9 <= t < t_(5) - 1e-9
            await feed(t)

        flight.clock.on_wake = on_wake
        records = await flight.fly(7)
        statuses = flight.statuses()

    assert [r.state for r in records] == ["following"] * 2 + ["held"] * 3 + ["following"] * 2
    assert all(setpoint[:2] == (0.0, 0.0) for setpoint in flight.link.setpoints[2:5])
    assert [(s.step, s.state) for s in statuses] == [
        (0, "following"),
        (2, "held"),
        (5, "following"),
    ]


# --- step alignment ------------------------------------------------------------------------------


@pytest.mark.asyncio
async def test_late_or_missing_neighbours_drop_out_of_that_step_only():
    async with rig() as flight:
        flight.neighbours.late = {2: {3}}  # vehicle 3's step-2 inputs come at t_3
        flight.neighbours.lost = {4: {1}}  # vehicle 1's step-4 inputs never come
        records = await flight.fly(6)
        inbox = flight.controller.inbox

    used = [r.neighbours_used for r in records]
    assert used == [PEERS, PEERS, (1,), PEERS, (3,), PEERS]
    assert 3 not in records[2].estimates_m
    assert 1 not in records[4].estimates_m
    assert [r.state for r in records] == ["following"] * 6
    # The late message and range were thrown away, not applied to step 3.
    assert inbox.discarded_late == 2
    # Step 3 used vehicle 3's own step-3 message: the law given exactly the on-time inputs
    # agrees with what was flown.
    expected = law_alone(flight.scenario, flight.neighbours.on_time, 6)
    for setpoint, (_, command) in zip(flight.link.setpoints, expected, strict=True):
        np.testing.assert_allclose(horizontal(setpoint), command.velocity_m_s, atol=1e-9)


@pytest.mark.asyncio
async def test_a_step_already_a_whole_step_past_is_skipped_and_the_oscillator_stays_on_grid():
    async with rig() as flight:
        scenario = flight.scenario
        params = dataclasses.replace(
            algorithm_params(scenario), coupling_gain=0.0, coupling_gain_last=0.0
        )
        flight.controller.law = VehicleEnclosing(params, OWN, [1, 2, 3], PHASES[OWN], OMEGA)
        flight.link.stall_s = {2: 2.5 * T}  # step 2's setpoint returns at t_2 + 2.5 T = t_4.5
        records = await flight.fly(6)
        published = flight.published_steps()

    assert [r.state for r in records] == ["following"] * 3 + ["skipped"] + ["following"] * 2
    skipped = records[3]
    assert skipped.step == 3
    assert skipped.time_s == t_(3)
    assert skipped.velocity_ned_m_s == (0.0, 0.0, 0.0)
    assert skipped.neighbours_used == ()
    assert flight.controller.skipped_steps == 1
    assert len(flight.link.setpoints) == 5  # none for step 3
    assert [m.step for m in published] == [0, 1, 2, 4, 5]
    # Uncoupled, the phase is theta(0) + k omega T at every record, skipped or not.
    for record in records:
        assert record.phase_rad == pytest.approx(PHASES[OWN] + record.step * OMEGA * T, abs=1e-12)
    assert records[4].phase_rad - records[2].phase_rad == pytest.approx(2 * OMEGA * T, abs=1e-12)
    # Step 4 is flown late (the clock is at t_4.5) but flown, with both neighbours.
    assert records[4].neighbours_used == PEERS
    assert records[4].setpoint_sent_s == pytest.approx(t_(4) + 0.5 * T)


# --- what is done to the law's command -----------------------------------------------------------


@pytest.mark.asyncio
async def test_velocity_lead_adds_lead_times_the_commands_rate_of_change():
    lead_s = 0.17
    plain, _ = await fly(8)
    led, setpoints = await fly(8, make_scenario(flight={"velocity_lead_s": lead_s}))

    commands = np.array([horizontal(r.velocity_ned_m_s) for r in plain])
    sent = np.array([horizontal(s) for s in setpoints])
    np.testing.assert_allclose(sent[0], commands[0], atol=1e-12)  # no previous command yet
    expected = commands[1:] + lead_s * (commands[1:] - commands[:-1]) / T
    np.testing.assert_allclose(sent[1:], expected, atol=1e-9)
    assert np.min(np.hypot(*(sent[1:] - commands[1:]).T)) > 0.05  # the lead did something
    # The lead acts on the setpoint only: the law ran on the same inputs.
    for a, b in zip(plain, led, strict=True):
        assert a.consensus_m_s == pytest.approx(b.consensus_m_s, abs=1e-12)


@pytest.mark.asyncio
async def test_after_a_hold_the_lead_does_not_difference_against_the_command_before_it():
    lead_s = 0.17

    def silence(flight):
        flight.neighbours.silent = {3, 4, 5, 6, 7}  # holding at k = 5, 6, 7

    timeout = {"silence_timeout_s": 0.3}
    plain, _ = await fly(9, make_scenario(flight=timeout), setup=silence)
    led, setpoints = await fly(
        9, make_scenario(flight={**timeout, "velocity_lead_s": lead_s}), setup=silence
    )

    assert [r.state for r in led[4:]] == ["following", "holding", "holding", "holding", "following"]
    command = horizontal(plain[8].velocity_ned_m_s)
    sent = horizontal(setpoints[8])
    # Whether the lead starts afresh (no lead) or leads from the hold's zero setpoint, the vehicle
    # is sent along the law's command.
    assert command[0] * sent[1] - command[1] * sent[0] == pytest.approx(0.0, abs=1e-9)
    assert np.dot(command, sent) > 0


@pytest.mark.asyncio
async def test_a_command_above_the_speed_limit_is_scaled_down_keeping_its_direction():
    limit = 0.5  # just above the law's saturation (0.4 m/s), as the scenario rules require
    free, _ = await fly(6)
    limited, setpoints = await fly(6, make_scenario(speed_limit_m_s=limit))

    for unlimited, record, setpoint in zip(free, limited, setpoints, strict=True):
        command = horizontal(unlimited.velocity_ned_m_s)
        sent = horizontal(setpoint)
        assert np.hypot(*command) > 2 * limit
        assert np.hypot(*sent) == pytest.approx(limit, abs=1e-12)
        np.testing.assert_allclose(sent, limit * command / np.hypot(*command), atol=1e-12)
        assert record.velocity_ned_m_s == setpoint


@pytest.mark.asyncio
async def test_altitude_hold_is_proportional_to_the_height_error_and_bounded():
    downs = [-5.0, -4.8, -5.3, -2.0, -9.0, -5.1]

    def climbing(s):
        north, east, _ = wandering(s)
        return north, east, downs[round(s / T)]

    scenario = make_scenario(flight={"max_vertical_speed_m_s": 0.5})
    _, setpoints = await fly(6, scenario, path=climbing, altitude_gain_per_s=2.0)

    # clip(2 (-5 - down), +-0.5), NED: positive is down.
    expected = [0.0, -0.4, 0.5, -0.5, 0.5, 0.2]
    assert [s[2] for s in setpoints] == pytest.approx(expected, abs=1e-12)


@pytest.mark.asyncio
async def test_three_d_ranges_lose_the_height_difference_before_the_law():
    def flat(flight):
        flight.neighbours.ranges_3d = False
        flight.neighbours.heights = False

    def no_heights(flight):
        flight.neighbours.heights = False

    # Vehicles 1 and 3 fly 1 m below and above vehicle 2, whose height wanders.
    projected, projected_sent = await fly(6, path=bobbing)
    given_flat, flat_sent = await fly(6, setup=flat, path=bobbing)
    unprojected, _ = await fly(6, setup=no_heights, path=bobbing)

    np.testing.assert_allclose(projected_sent, flat_sent, atol=1e-9)
    for a, b in zip(projected, given_flat, strict=True):
        for peer in PEERS:
            np.testing.assert_allclose(a.estimates_m[peer], b.estimates_m[peer], atol=1e-9)
    # Without the neighbours' heights the 3-D ranges go in as they are: a constant height
    # difference would cancel out of the cosine law, a changing one shows in the estimates.
    errors = [
        np.hypot(*(c.estimates_m[peer] - b.estimates_m[peer]))
        for b, c in zip(given_flat[1:], unprojected[1:], strict=True)
        for peer in PEERS
    ]
    assert max(errors) > 0.05


@pytest.mark.parametrize(
    ("gain_1_s", "integral_gain_1_s2"),
    [(0.8, 0.0), (0.5, 1.0)],
    ids=["proportional", "proportional-integral"],
)
@pytest.mark.asyncio
async def test_displacement_tracking_pushes_a_vehicle_that_lags_within_its_bound(
    gain_1_s, integral_gain_1_s2
):
    limit = 0.6
    tracking = {
        "displacement_tracking": {
            "gain_1_s": gain_1_s,
            "integral_gain_1_s2": integral_gain_1_s2,
            "max_correction_m_s": limit,
        }
    }
    plain, _ = await fly(12, path=standing)
    tracked, setpoints = await fly(12, make_scenario(flight=tracking), path=standing)

    commands = np.array([horizontal(r.velocity_ned_m_s) for r in plain])
    corrections = np.array([horizontal(s) for s in setpoints]) - commands
    # Where the law's commands would have taken the vehicle by t_k, from where it stands.
    shortfall = T * np.cumsum(np.vstack([np.zeros(2), commands[:-1]]), axis=0)
    sizes = np.hypot(*corrections.T)

    assert sizes[0] == pytest.approx(0.0, abs=1e-12)
    assert np.all(sizes <= limit + 1e-12)
    assert np.all(np.diff(sizes[:4]) > 0.1)  # grows while the vehicle does not move
    assert np.all(np.diff(sizes) >= -1e-12)
    assert sizes[-1] == pytest.approx(limit, abs=1e-9)  # until it saturates
    cosines = np.sum(corrections[1:] * shortfall[1:], axis=1) / (
        sizes[1:] * np.hypot(*shortfall[1:].T)
    )
    assert np.all(cosines > 0.99)  # towards where the commands point
    if integral_gain_1_s2 == 0:
        scale = np.minimum(1.0, limit / np.maximum(gain_1_s * np.hypot(*shortfall.T), 1e-12))
        np.testing.assert_allclose(corrections, gain_1_s * shortfall * scale[:, None], atol=1e-9)
    assert [r.state for r in tracked] == ["following"] * 12


# --- impossible ranges ---------------------------------------------------------------------------


@pytest.mark.asyncio
async def test_impossible_ranges_never_reach_the_estimator_and_are_counted():
    """The issue's forged ranges (40 m for every pair), arriving after the true ones of each
    step: the controller flies exactly as if they had never been sent."""
    steps = 8
    async with rig() as flight:
        honest = flight.neighbours.at

        async def with_forgeries(time_s):
            await honest(time_s)
            k = round((time_s - START_S) / T)
            forged = RangeSet(OWN, t_(k), tuple((peer, 40.0) for peer in PEERS), step=k)
            beyond = RangeSet(OWN, t_(k), ((1, 5000.0),), step=k)
            for hostile in (forged, beyond):
                await flight.neighbours.bus.publish_message(
                    flight.neighbours.topics.ranges(OWN), hostile, timeout=1.0
                )

        flight.clock.on_wake = with_forgeries
        records = await flight.fly(steps)
        delivered = flight.neighbours.on_time
        gate = flight.controller.range_gate

    expected = law_alone(flight.scenario, delivered, steps)
    for record, (_, command) in zip(records, expected, strict=True):
        for peer in PEERS:
            np.testing.assert_allclose(
                record.estimates_m[peer], command.estimates_m[peer], atol=1e-9
            )
    assert gate is not None
    assert gate.rejected == {"invalid": 0, "beyond_reach": steps, "jump": 2 * steps}


# --- shared ranges -------------------------------------------------------------------------------


@pytest.mark.asyncio
async def test_shared_ranges_go_out_in_the_step_message_and_come_back_to_the_law():
    """With ``algorithm.shared_ranges`` vehicle 2 publishes its step-k ranges (rounded as
    carried) and hands the law, beside its own, the ranges its neighbours measured to it; a
    neighbour whose message is missing leaves the own range alone."""
    given = []

    def setup(flight):
        flight.neighbours.shared = {1: 0.1, 3: -0.05}
        flight.neighbours.lost = {3: {1}}
        flight.neighbours.ranges_3d = flight.neighbours.heights = False
        law_step = flight.controller.law.step

        def spy(**kwargs):
            given.append(kwargs)
            return law_step(**kwargs)

        flight.controller.law.step = spy

    async with rig(make_scenario(shared_ranges=True, estimator="ekf")) as flight:
        setup(flight)
        records = await flight.fly(5)
        published = flight.published_steps()
        delivered = flight.neighbours.on_time

    for k, (message, inputs) in enumerate(zip(published, given, strict=True)):
        measured = {peer: d.horizontal_range_m for peer, d in delivered[k].items()}
        own = {peer: shared_range(value) for peer, value in measured.items()}
        assert message.ranges_m == tuple(sorted(own.items()))
        assert inputs["ranges_m"] == own == records[k].ranges_m
        offsets = flight.neighbours.shared
        expected = {peer: shared_range(measured[peer] + offsets[peer]) for peer in measured}
        assert inputs["peer_ranges_m"] == pytest.approx(expected, abs=1e-12)
    assert sorted(given[3]["peer_ranges_m"]) == [3]


# --- the target hidden ---------------------------------------------------------------------------


def relayed_since(step):
    """Vehicle 1's relay when it last saw the target at ``step``: the freshest observation."""
    return {
        "target_velocity_north_m_s": TARGET_VELOCITY[0],
        "target_velocity_east_m_s": TARGET_VELOCITY[1],
        "target_observed_step": step,
    }


def own_observation(k, *, seen):
    """Vehicle 2's tracker at t_k: the target (on the scenario's line) seen, or not."""
    if not seen:
        return TargetObservation.not_seen(OWN, t_(k))
    s = k * T
    north, east, _ = wandering(s)
    gap = (ORIGINS[OWN][0] + north - TARGET_VELOCITY[0] * s, ORIGINS[OWN][1] + east)
    return TargetObservation(OWN, t_(k), math.hypot(*gap), *TARGET_VELOCITY)


@pytest.mark.asyncio
async def test_a_target_nobody_sees_is_predicted_then_declared_lost_and_held_for():
    steps = 16
    async with rig(target_lost_after_s=1.0) as flight:
        seen = flight.neighbours.relay
        flight.neighbours.relay = lambda k: seen(k) if k < 5 else relayed_since(4)
        records = await flight.fly(steps)
        statuses = flight.statuses()
        published = flight.published_steps()
        delivered = flight.neighbours.on_time

    # Last seen at step 4: predicted while unseen for at most 1 s (steps 5-12), then lost.
    assert [r.target for r in records] == ["observed"] * 5 + ["predicted"] * 8 + ["lost"] * 3
    assert [r.state for r in records] == ["following"] * 13 + ["target_lost"] * 3
    # Predicted at constant velocity: the same commands as with the target in sight.
    expected = law_alone(flight.scenario, delivered, 13)
    for setpoint, (_, command) in zip(flight.link.setpoints, expected, strict=False):
        np.testing.assert_allclose(horizontal(setpoint), command.velocity_m_s, atol=1e-9)
    # Lost: it holds (target_on_lost: hold) and never says it follows.
    assert all(
        horizontal(setpoint).tolist() == [0.0, 0.0] for setpoint in flight.link.setpoints[13:]
    )
    # Following: a status at the start and a second later; lost: every step, as its detail
    # (how long unseen) changes.
    assert [(s.step, s.state) for s in statuses] == [(0, "following"), (8, "following")] + [
        (k, "target_lost") for k in (13, 14, 15)
    ]
    assert not any(s.tracking_ok for s in statuses[2:])
    assert statuses[2].detail == f"target not seen for {9 * T:.2f} s"
    # It relays the freshest observation it knows of, so every vehicle predicts alike.
    assert published[0].relayed_target is None  # nothing heard yet when it sends step 0
    assert [m.relayed_target for m in published[1:]] == [
        (min(k - 1, 4), TARGET_VELOCITY) for k in range(1, steps)
    ]


@pytest.mark.asyncio
async def test_vehicle_1_lost_hands_the_target_over_to_vehicle_2_which_sees_it_by_then():
    steps = 14
    async with rig(make_scenario(sensing=(1, 2))) as flight:
        flight.neighbours.own_tracker = lambda k: own_observation(k, seen=k >= 3)
        flight.neighbours.lost = {k: {1} for k in range(6, steps)}
        records = await flight.fly(steps)
        published = flight.published_steps()

    assert [r.target for r in records] == ["observed"] * steps
    assert [r.state for r in records] == ["following"] * steps
    assert all(0 in r.ranges_m for r in records[3:]) and not any(
        0 in r.ranges_m for r in records[:3]
    )
    assert all(0 in r.estimates_m for r in records[3:])  # its own edge to the target
    # From step 3 it relays its own observations (with the target's odometry in its frame).
    assert [m.has_target for m in published] == [False] * 3 + [True] * (steps - 3)
    assert [m.relayed_target for m in published[3:]] == [
        (k, TARGET_VELOCITY) for k in range(3, steps)
    ]
    np.testing.assert_allclose(
        [m.target_odometry_north_m - published[3].target_odometry_north_m for m in published[3:]],
        [TARGET_VELOCITY[0] * (k - 3) * T for k in range(3, steps)],
        atol=1e-12,
    )


@pytest.mark.asyncio
@pytest.mark.parametrize("shared", [False, True])
async def test_in_lockstep_a_dropped_range_is_not_waited_for(shared):
    """Vehicle 2's radio drops its range to vehicle 3 at step 2 and both at step 4: the step's
    range set says so, and the controller waits for nothing more (an hour's wall deadline:
    waiting for a range that never comes would hang)."""
    scenario = make_scenario(shared_ranges=shared)
    async with rig(scenario, wall_deadline_s=3600.0) as flight:
        flight.clock.lockstep = True
        flight.neighbours.dropped = {2: {3}, 4: {1, 3}}
        async with asyncio.timeout(60):
            records = await flight.fly(6)
        published = flight.published_steps()
    ranged = [tuple(sorted(peer for peer in r.ranges_m if peer != 0)) for r in records]
    assert ranged == [PEERS, PEERS, (1,), PEERS, (), PEERS]
    assert [r.neighbours_used for r in records] == [PEERS] * 6
    if shared:
        assert [tuple(peer for peer, _ in m.ranges_m or ()) for m in published] == ranged


@pytest.mark.asyncio
async def test_in_lockstep_a_not_seen_observation_is_not_waited_for():
    # An hour's wall deadline: waiting for an observation that is known not to come would hang.
    async with rig(make_scenario(sensing=(1, 2)), wall_deadline_s=3600.0) as flight:
        flight.clock.lockstep = True
        flight.neighbours.own_tracker = lambda k: own_observation(k, seen=False)
        async with asyncio.timeout(60):
            records = await flight.fly(6)
    assert [r.target for r in records] == ["observed"] * 6  # vehicle 1 still sees it
    assert not any(0 in r.ranges_m for r in records)


@pytest.mark.asyncio
@pytest.mark.parametrize("shared", [False, True])
async def test_an_own_input_is_awaited_half_the_deadline_so_the_message_still_reaches_peers(
    shared, monkeypatch
):
    """The neighbours wait for this vehicle's step message until their deadline: the target
    observation (and, when sharing, the ranges) it relays is awaited half of it at most."""
    scenario = make_scenario(sensing=(1, 2), shared_ranges=shared)
    async with rig(scenario, wall_deadline_s=8.0) as flight:
        flight.clock.lockstep = True
        flight.neighbours.own_tracker = lambda k: own_observation(k, seen=True)
        bounds = []
        waiting = flight.controller.inbox.wait_for

        async def wait_for(ready, timeout_s):
            bounds.append(timeout_s)
            return await waiting(ready, timeout_s)

        monkeypatch.setattr(flight.controller.inbox, "wait_for", wait_for)
        await flight.fly(3)
    # Each step: its own inputs half the deadline, then the neighbours' the whole of it
    assert bounds == [4.0, 8.0] * 3

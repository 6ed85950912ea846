"""The ground station's phases alone, on the in-process bus with an injected UNIX clock: the
ready verdict (abort for everyone when a vehicle failed or not all were ready), the start on the
step grid at the autopilots' rate, and the mission clock following the autopilots' clocks. Then
a vehicle process's end: what it does to its vehicle and reports, by how its controller ended."""

import contextlib
import math
from types import SimpleNamespace

import pytest

from mission_runner.bus import (
    ControlCommand,
    MissionControl,
    Sender,
    VehicleStatus,
    open_bus,
)
from mission_runner.checks import validate_scenario
from mission_runner.runner.process import GroundStation, MissionAbortedError, VehicleProcess

from .flying import load

pytestmark = pytest.mark.asyncio


class Unix:
    """A UNIX clock the test sets."""

    def __init__(self, now_s):
        self.now_s = now_s

    def __call__(self):
        return self.now_s


@contextlib.asynccontextmanager
async def ground_station(unix):
    """A :class:`GroundStation` on an in-process bus, with ``vehicle(i)``: vehicle ``i``'s view
    of it, and ``commands``: what the ground published on the control topic."""
    scenario = load("paper_tracking_flyable")
    topics = scenario.bus.topics(scenario.name)
    async with open_bus(scenario.bus, sender=None) as bus:
        ground_bus = bus.as_sender(Sender.ground())
        async with (
            ground_bus.subscribe(topics.all_status()) as heard,
            bus.subscribe(topics.control()) as control,
        ):
            ground = GroundStation(scenario, ground_bus, heard, unix_s=unix)
            ground.vehicle = lambda i: bus.as_sender(Sender.vehicle(i))
            ground.commands = lambda: drain(control)
            yield ground


async def drain(control):
    return [message for _, message in control.drain_messages(MissionControl)]


async def report(ground, vehicle_id, state, *, detail="", clock_rate=1.0, mission_id=None):
    status = VehicleStatus(
        vehicle_id, ground.unix_s(), state, 0, False, detail,
        mission_id=ground.mission_id if mission_id is None else mission_id,
        clock_rate=clock_rate,
    )  # fmt: skip
    topic = ground.topics.status(vehicle_id)
    await ground.vehicle(vehicle_id).publish_message(topic, status, retain=True, timeout=1.0)


async def test_a_failed_vehicle_aborts_the_mission_for_everyone_with_its_reason():
    async with ground_station(Unix(1000.0)) as ground:
        await ground.prepare()
        await report(ground, 1, "ready")
        await report(ground, 2, "failed", detail="arming refused: preflight checks")
        with pytest.raises(MissionAbortedError, match="arming refused: preflight checks"):
            await ground.wait_ready(timeout_s=5.0)
        prepare, land = await ground.commands()
    assert prepare.command is ControlCommand.PREPARE and prepare.time_s == 1000.0
    assert land.command is ControlCommand.LAND and land.vehicle_id is None
    assert land.reason == "vehicle(s) [2] failed" and land.mission_id == ground.mission_id


async def test_vehicles_not_ready_in_time_abort_the_mission_naming_them():
    async with ground_station(Unix(1000.0)) as ground:
        await report(ground, 1, "ready")
        await report(ground, 3, "ready", mission_id="an-earlier-mission")  # not this one's
        with pytest.raises(MissionAbortedError, match=r"vehicles \[2, 3, 4\] not ready"):
            await ground.wait_ready(timeout_s=1.0)  # vehicle 1's status is read first
        (land,) = await ground.commands()
    assert land.command is ControlCommand.LAND and land.reason == "not ready: [2, 3, 4]"


async def test_every_vehicle_ready_is_no_abort():
    async with ground_station(Unix(1000.0)) as ground:
        for vehicle_id in ground.ids:
            await report(ground, vehicle_id, "ready")
        await ground.wait_ready(timeout_s=5.0)
        assert await ground.commands() == []


async def test_the_start_is_on_the_step_grid_after_the_delay_at_the_autopilots_rate():
    """A delay of 2 s at the autopilots' median rate (0.6) from the clock's now, rounded up."""
    unix = Unix(1000.03)
    async with ground_station(unix) as ground:
        for vehicle_id, rate in zip(sorted(ground.ids), (0.5, 0.6, 0.6, 0.7), strict=True):
            await report(ground, vehicle_id, "ready", clock_rate=rate)
        await ground.wait_ready(timeout_s=5.0)
        assert await ground.start(start_delay_s=2.0) == pytest.approx(0.6)
        (start,) = await ground.commands()
    step_s = ground.scenario.timing.step_s
    assert start.command is ControlCommand.START
    assert start.time_s == ground.start_s == math.ceil((1000.03 + 1.2) / step_s) * step_s
    assert start.clock_rate == pytest.approx(0.6) and start.clock_reference_s == 1000.03
    unix.now_s = 1010.03
    assert ground.follower.time.now_s() == pytest.approx(1000.03 + 0.6 * 10.0)


async def test_the_mission_clock_follows_the_autopilots_once_they_stay_off():
    """Rates heard after the start go to the follower; a change is sent only once the median
    has stayed off the clock's rate for the follower's hold, ``lead_s`` ahead."""
    unix = Unix(1000.0)
    async with ground_station(unix) as ground:
        for vehicle_id in ground.ids:
            await report(ground, vehicle_id, "ready")
        await ground.wait_ready(timeout_s=5.0)
        await ground.start(start_delay_s=2.0)
        hold_s, lead_s = ground.follower.hold_s, ground.follower.lead_s
        for vehicle_id in ground.ids:
            ground.accept(status(ground, vehicle_id, clock_rate=0.8))
        await ground.follow_clock()  # off from now on: not yet held long enough
        unix.now_s += hold_s / 2
        await ground.follow_clock()
        _, *changes = await ground.commands()
        assert changes == []
        unix.now_s = 1000.0 + hold_s
        await ground.follow_clock()
        (change,) = await ground.commands()
    assert change.command is ControlCommand.CLOCK and change.clock_rate == pytest.approx(0.8)
    assert change.clock_reference_s == pytest.approx(1000.0 + hold_s + lead_s)
    assert change.time_s == pytest.approx(1000.0 + hold_s + lead_s)  # continuous there
    assert ground.outcome({}).clock_changes == 1
    assert ground.outcome({}).clock_rate_at_end == pytest.approx(0.8)


def status(ground, vehicle_id, *, clock_rate):
    return VehicleStatus(
        vehicle_id, ground.unix_s(), "following", 1, True, "",
        mission_id=ground.mission_id, clock_rate=clock_rate,
    )  # fmt: skip


# -- the vehicle process's end ----------------------------------------------------------------


class Vehicle:
    """What the vehicle process's end does to its vehicle."""

    def __init__(self, control_lost=None):
        self.control_lost, self.done = control_lost, []

    async def finish(self, action, timeout_s=None):
        self.done.append(action)

    async def stream_ended(self):
        self.done.append("stream ended")


class Controller:
    def __init__(self, state, steps):
        self.state = state
        self.records = [SimpleNamespace(step=k) for k in range(steps)]


def vehicle_process(state, *, steps=5, control_lost=None, end_action="land", on_lost="hold"):
    data = load("paper_tracking_flyable").model_dump(mode="json")
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": "127.0.0.1", "port": 1883}}
    data["flight"] |= {"end_action": end_action, "on_lost": on_lost}
    process = VehicleProcess(validate_scenario(data), 2)
    process.vehicle = Vehicle(control_lost)
    process.controller = Controller(state, steps)
    process.reported = []

    async def report(state, **fields):
        process.reported.append((state, fields))

    process.report = report
    return process


async def test_a_vehicle_that_flew_its_steps_takes_the_end_action_and_reports_done():
    process = vehicle_process("following", steps=5, end_action="return")
    await process.land(None)
    assert process.vehicle.done == ["return"]
    assert process.reported == [("done", {"step": 5})]


async def test_a_lost_vehicle_reports_lost_at_its_last_step_and_takes_the_on_lost_action():
    process = vehicle_process("lost", steps=4, on_lost="land")
    await process.land(None)
    assert process.reported == [
        ("lost", {"step": 3, "detail": "own odometry stopped: no longer driven"})
    ]
    assert process.vehicle.done == ["land"]


async def test_a_vehicle_taken_over_is_left_to_whoever_took_it():
    process = vehicle_process("taken_over", steps=2, control_lost="mode changed to POSCTL")
    await process.land(None)
    assert process.vehicle.done == ["stream ended"]  # never commanded against the pilot
    assert process.reported == [("taken_over", {"step": 1, "detail": "mode changed to POSCTL"})]


async def test_the_operators_ending_is_carried_out_and_reported_aborted():
    process = vehicle_process("following")
    stop = MissionControl(ControlCommand.RETURN, 0.0, reason="weather", vehicle_id=2)
    await process.land(stop)
    assert process.vehicle.done == ["return"]
    assert process.reported == [
        ("aborted", {"detail": "mission aborted by the ground station: weather"})
    ]

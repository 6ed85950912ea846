"""A SIMULATION AID: UWB ranges and target observations synthesised from the vehicles' reported
global positions, for flying the mission on vehicles without UWB (real PX4 SITL, or a GPS field
test). It publishes exactly what a UWB driver and a target tracker would publish (see
:mod:`sitl.world`), so the controllers run unchanged; nothing here is used when real sensors exist.

It listens to every vehicle's GLOBAL_POSITION_INT with its timestamp (MAVSDK raw messages, boot
time mapped to UNIX time with SYSTEM_TIME), interpolates each position at the step boundaries
t_k = start + kT (UNIX time), and publishes the 3-D distance between every pair plus Gaussian noise,
and, for the vehicles that sense it, the horizontal range and velocity of a virtual target that
follows the scenario's path. The scenario frame's origin is placed so that the first vehicle's first
fix is at its ``initial_position_m``.
"""

import asyncio
import contextlib
import json
import logging
import math
import time

import numpy as np

from ..bus import ControlCommand, MissionControl, RangeMessage, TargetObservation, open_bus
from ..scenario import target_positions
from .errors import RunnerError, RunnerTimeoutError
from .links import MavsdkVehicle, connected_vehicles
from .odometry import OdometrySample, OdometryTrack

logger = logging.getLogger(__name__)

EARTH_RADIUS_M = 6_371_000.0
POSITION_RATE_HZ = 20.0


class GlobalTrack:
    """One vehicle's GLOBAL_POSITION_INT on UNIX time, in a local north-east-down frame."""

    def __init__(self, vehicle):
        self.vehicle = vehicle
        self.track = OdometryTrack()
        self.reference = None  # (lat, lon, alt) of the frame origin

    def local(self, lat_deg, lon_deg, alt_m):
        lat0, lon0, alt0 = self.reference
        north = math.radians(lat_deg - lat0) * EARTH_RADIUS_M
        east = math.radians(lon_deg - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
        return north, east, -(alt_m - alt0)

    async def stream(self, offset_s, on_first_fix):
        stream = self.vehicle.raw.subscribe_message("GLOBAL_POSITION_INT")
        async with contextlib.aclosing(stream):
            async for message in stream:
                if message.system_id != self.vehicle.system_id:
                    continue
                fields = json.loads(message.fields_json)
                lat, lon, alt = fields["lat"] / 1e7, fields["lon"] / 1e7, fields["alt"] / 1000.0
                if self.reference is None:
                    on_first_fix(self, lat, lon, alt)
                    if self.reference is None:
                        continue  # the origin (the first vehicle's first fix) is not known yet
                self.track.add(
                    OdometrySample(
                        fields["time_boot_ms"] / 1000.0 + offset_s, *self.local(lat, lon, alt)
                    )
                )


async def run_range_provider(scenario, urls, *, steps=None, start_s=None, seed=0):
    """Publish synthetic ranges for ``steps`` steps (default: the scenario's) from ``start_s``
    (UNIX; default: the ground station's start command). Returns the number of steps done."""
    if scenario.bus.kind != "mqtt":
        raise RunnerError("the range provider publishes for vehicle processes: set bus.kind: mqtt")
    ids = [v.id for v in scenario.vehicles]
    step_s = scenario.timing.step_s
    steps = scenario.timing.steps if steps is None else steps
    topics = scenario.bus.topics(scenario.name)
    rng = np.random.default_rng([seed, 11])
    sensors = scenario.sensors
    async with contextlib.AsyncExitStack() as stack:
        systems = await stack.enter_async_context(connected_vehicles(urls, ids))
        bus = await stack.enter_async_context(
            open_bus(scenario.bus, client_id=f"{scenario.name}-range-provider")
        )
        control = await stack.enter_async_context(bus.subscribe(topics.control()))
        tracks = []
        for vehicle_id in ids:
            vehicle = await stack.enter_async_context(
                MavsdkVehicle(systems[vehicle_id], vehicle_id, sample_time_s=lambda ms: math.nan)
            )
            with contextlib.suppress(Exception):
                await vehicle.telemetry.set_rate_position(POSITION_RATE_HZ)
            tracks.append((GlobalTrack(vehicle), await vehicle.boot_to_unix_offset_s()))
        origin = {}

        def first_fix(track, lat, lon, alt):
            # Every track shares one origin: the first vehicle's first fix (which the scenario
            # frame puts at that vehicle's initial_position_m).
            if track is tracks[0][0]:
                origin["lla"] = (lat, lon, alt)
            if origin:
                track.reference = origin["lla"]

        async with asyncio.TaskGroup() as group:
            streams = [
                group.create_task(
                    track.stream(offset, first_fix), name=f"gps-{track.vehicle.system_id}"
                )
                for track, offset in tracks
            ]
            try:
                if start_s is None:
                    start_s = await _start_command(control)
                for k in range(steps):
                    t_k = start_s + k * step_s
                    await asyncio.sleep(max(0.0, t_k + 0.06 - time.time()))  # a fix after t_k
                    positions = [track.track.at(t_k) for track, _ in tracks]
                    await _publish_step(
                        bus, topics, scenario, ids, positions, k, t_k, start_s, rng, sensors
                    )
            finally:
                for task in streams:
                    task.cancel()
    return steps


async def _start_command(control, timeout_s=600.0):
    try:
        async with asyncio.timeout(timeout_s):
            async for _, message in control.messages(MissionControl):
                if message.command is ControlCommand.START:
                    return message.time_s
    except TimeoutError:
        raise RunnerTimeoutError("the ground station's start command", timeout_s) from None
    raise RunnerError("the bus closed before the start command")


async def _publish_step(bus, topics, scenario, ids, positions, k, t_k, start_s, rng, sensors):  # noqa: PLR0917
    noise = sensors.range_noise_std_m
    for i, here in enumerate(positions):
        if here is None:
            continue
        for j, there in enumerate(positions):
            if i == j or there is None:
                continue
            distance = math.dist(here, there) + (rng.normal(scale=noise) if noise else 0.0)
            if sensors.range_max_m is not None and distance > sensors.range_max_m:
                continue
            message = RangeMessage(ids[i], ids[j], t_k, abs(distance), step=k)
            await bus.publish_message(topics.range(ids[i], ids[j]), message, timeout=0.1)
    elapsed = np.array([t_k - start_s, t_k - start_s + 1e-3])
    target = target_positions(scenario.target.path, elapsed)
    velocity = (target[1] - target[0]) / 1e-3
    first = scenario.vehicles[0].initial_position_m
    for i, vehicle in enumerate(scenario.vehicles):
        if not vehicle.senses_target or positions[i] is None:
            continue
        # Scenario frame = track frame shifted by the first vehicle's scenario start position.
        north = positions[i][0] + first[0]
        east = positions[i][1] + first[1]
        horizontal = math.hypot(north - target[0, 0], east - target[0, 1])
        observation = TargetObservation(ids[i], t_k, horizontal, *map(float, velocity))
        await bus.publish_message(topics.target(ids[i]), observation, timeout=0.1)

"""The vehicle emulator: N PX4-like vehicles in one process, each with its own UDP links.

:class:`Emulator` is an async context manager. Entering it builds the world (vectorised physics,
odometry, one :class:`sitl.autopilot.Px4Autopilot` per vehicle), binds every UDP endpoint
(raising :class:`sitl.errors.PortInUseError` naming the port and the setting to change) and only
then starts its one task, ``sitl-physics``, in a task group it owns. Leaving it stops the task,
closes the sockets and the telemetry logs.

The physics task steps everything in fixed simulated steps as far as the clock allows (real time,
sped-up real time, or lockstep; see :mod:`sitl.clock`). One step: scheduled faults, autopilot
updates, ``physics.step(dt)``, odometry drift, GPS error, step listeners, due telemetry, send.

For a world module (ranging, moving target, sensor faults published on a bus) there are
:meth:`Emulator.add_step_listener` - called after every step with ``(time_s, truth)`` - and the
read-only :attr:`Emulator.truth`. Faults: :meth:`Emulator.kill_vehicle`,
:meth:`Emulator.drop_link`, :meth:`Emulator.inject_failure` (PX4's failure units and types, the
same failures MAV_CMD_INJECT_FAILURE injects; :meth:`Emulator.fail_sensor` is a short form),
:meth:`Emulator.deny_arming` (now or at a simulated time).

Like PX4 SITL, every vehicle can have a third link, SIH's ground-truth stream
(``config.truth_stream``), and its own boot clock (``config.boot_clock``); everything inside the
emulator runs on the one simulated time.

Every vehicle speaks MAVLink 2 signing as PX4 does (:mod:`sitl.signing`): off until a ground
station sends SETUP_SIGNING or ``config.signing`` gives a start-up key; keys are kept in a
:class:`sitl.signing.KeyStore` (``config.signing.key_dir`` or memory, or one passed in).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import heapq
import itertools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from sitl import physics as ph
from sitl.autopilot import Px4Autopilot, Snapshot
from sitl.clock import Clock
from sitl.config import (
    PX4_ARMING_DENIED_TEXT,
    DenyArmingFault,
    EmulatorConfig,
    FailureFault,
    KillFault,
    LinkDropFault,
    SensorFault,
    StreamRates,
)
from sitl.errors import EmulatorStateError, PortInUseError, SitlTimeoutError
from sitl.failure_injection import SUPPORTED, TYPES, UNITS, describe
from sitl.geo import MapProjection
from sitl.gnss import GnssError
from sitl.link import VehicleLink
from sitl.modes import FlightMode
from sitl.odometry import Odometry
from sitl.signing import FileKeyStore, KeyStore, MemoryKeyStore, VehicleSigning
from sitl.tlog import TlogWriter

logger = logging.getLogger(__name__)

LinkName = Literal["api", "gcs", "all"]
SensorName = Literal["flow", "gps"]
_SENSOR_UNITS: dict[str, str] = {"flow": "optical_flow", "gps": "gps"}

_LOCKSTEP_BATCH_STEPS = 10
#: Steps run back to back before datagrams get a turn, when real time has run ahead.
_CATCH_UP_BATCH_STEPS = 25
#: Mode logic, failsafes and timers need no more than this (PX4's commander runs slower);
#: a faster physics rate only refines the motion.
_AUTOPILOT_RATE_HZ = 50.0


@dataclass(frozen=True, slots=True)
class VehicleEndpoints:
    """Where to reach vehicle ``index``."""

    index: int
    sysid: int
    api_local_port: int
    api_remote_port: int
    gcs_local_port: int | None
    gcs_remote_port: int | None
    truth_local_port: int | None = None
    """Port of the ground-truth link (None when ``truth_stream`` is off)."""
    truth_remote_port: int | None = None

    @property
    def mavsdk_url(self) -> str:
        """What a MAVSDK client passes to ``add_any_connection``."""
        return f"udpin://0.0.0.0:{self.api_remote_port}"


@dataclass(frozen=True, slots=True)
class VehicleStatus:
    """What the autopilot of one vehicle believes, for tests and monitoring."""

    index: int
    sysid: int
    alive: bool
    armed: bool
    mode: FlightMode
    landed: bool
    failsafe: bool
    flow_ok: bool
    gps_ok: bool
    battery_percent: float
    status_texts: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class EmulatorStats:
    """Loop figures since start (wall seconds unless stated)."""

    steps: int
    sim_time_s: float
    wall_time_s: float
    max_lag_s: float
    """Largest simulated-time backlog seen in realtime mode (how far the loop fell behind)."""
    late_wakeups: int
    """Realtime wake-ups that found more than one step due."""
    rx_datagrams: int
    rx_packets: int
    rx_bad: int
    tx_packets: int
    handler_errors: int
    rx_rejected: int = 0
    """Valid packets refused by message signing (unsigned, badly signed, replayed)."""


class Truth:
    """Read-only views of the true vehicle states, in the world NED frame of the origin.

    Every property returns a fresh read-only numpy view (no copy): copy what you keep beyond the
    current step. Shapes: ``(n, 3)`` for vectors, ``(n,)`` for scalars.
    """

    def __init__(self, emulator: Emulator) -> None:
        self._emulator = emulator

    @property
    def time_s(self) -> float:
        return self._emulator.time_s

    @property
    def n(self) -> int:
        return self._emulator._physics_or_raise().n

    def _view(self, array: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        view = array.view()
        view.flags.writeable = False
        return view

    @property
    def position_ned_m(self) -> npt.NDArray[np.float64]:
        return self._view(self._emulator._physics_or_raise().position_ned_m)

    @property
    def velocity_ned_m_s(self) -> npt.NDArray[np.float64]:
        return self._view(self._emulator._physics_or_raise().velocity_ned_m_s)

    @property
    def acceleration_ned_m_s2(self) -> npt.NDArray[np.float64]:
        return self._view(self._emulator._physics_or_raise().acceleration_ned_m_s2)

    @property
    def yaw_rad(self) -> npt.NDArray[np.float64]:
        return self._view(self._emulator._physics_or_raise().yaw_rad)

    @property
    def roll_rad(self) -> npt.NDArray[np.float64]:
        return self._view(self._emulator._physics_or_raise().roll_rad)

    @property
    def pitch_rad(self) -> npt.NDArray[np.float64]:
        return self._view(self._emulator._physics_or_raise().pitch_rad)

    @property
    def roll_rate_rad_s(self) -> npt.NDArray[np.float64]:
        """(n,) rate of change of the roll angle (an Euler rate, not a body rate)."""
        return self._view(self._emulator._physics_or_raise().roll_rate_rad_s)

    @property
    def pitch_rate_rad_s(self) -> npt.NDArray[np.float64]:
        """(n,) rate of change of the pitch angle (an Euler rate, not a body rate)."""
        return self._view(self._emulator._physics_or_raise().pitch_rate_rad_s)

    @property
    def yaw_rate_rad_s(self) -> npt.NDArray[np.float64]:
        """(n,) rate of change of the yaw angle (an Euler rate, not a body rate)."""
        return self._view(self._emulator._physics_or_raise().yaw_rate_rad_s)

    @property
    def odometry_origin_ned_m(self) -> npt.NDArray[np.float64]:
        """Where each vehicle's LOCAL_POSITION_NED frame has its origin (world NED)."""
        return self._view(self._emulator._odometry_or_raise().origin_ned_m)

    @property
    def odometry_drift_ned_m(self) -> npt.NDArray[np.float64]:
        """Current drift of each vehicle's odometry (world NED metres)."""
        return self._view(self._emulator._odometry_or_raise().drift_ned_m)

    @property
    def gps_error_ned_m(self) -> npt.NDArray[np.float64]:
        """(n, 3) error of the position each vehicle reports (GLOBAL_POSITION_INT, GPS_RAW_INT)
        at this step, world NED metres: reported = true + error."""
        return self._view(self._emulator._gnss_or_raise().error_ned_m)

    @property
    def boot_clock_offset_s(self) -> npt.NDArray[np.float64]:
        """(n,) each vehicle's boot clock minus simulated time, s (``config.boot_clock``)."""
        return self._view(self._emulator._boot_offsets_s)

    @property
    def alive(self) -> npt.NDArray[np.bool_]:
        return np.array([ap.alive for ap in self._emulator._autopilots], dtype=bool)

    @property
    def armed(self) -> npt.NDArray[np.bool_]:
        return np.array([ap.armed for ap in self._emulator._autopilots], dtype=bool)

    def global_position(self, index: int) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude AMSL m) of vehicle ``index``."""
        emulator = self._emulator
        n, e, d = (float(v) for v in emulator._physics_or_raise().position_ned_m[index])
        lat, lon = emulator.projection.to_global(n, e)
        return lat, lon, emulator.config.home.altitude_amsl_m - d


StepListener = Callable[[float, Truth], None]


class Emulator:
    """N emulated PX4 vehicles; use as ``async with Emulator(config) as emulator:``.

    ``clock`` defaults to one built from ``config.clock``; pass a shared one to run other
    participants in lockstep with the vehicles. ``tlog_dir`` overrides ``config.tlog_dir``.
    ``key_store`` keeps the vehicles' signing keys (default: files in ``config.signing.key_dir``,
    or memory); pass the same :class:`sitl.signing.MemoryKeyStore` to a later emulator to
    restart vehicles with the keys they had.
    """

    def __init__(
        self,
        config: EmulatorConfig | None = None,
        *,
        clock: Clock | None = None,
        tlog_dir: Path | None = None,
        key_store: KeyStore | None = None,
    ) -> None:
        self.config = config if config is not None else EmulatorConfig()
        self.clock = clock if clock is not None else Clock.from_config(self.config.clock)
        self.tlog_dir = tlog_dir if tlog_dir is not None else self.config.tlog_dir
        home = self.config.home
        self.projection = MapProjection(home.latitude_deg, home.longitude_deg)
        self.truth = Truth(self)
        self.events: list[tuple[float, int, str]] = []
        """(time_s, vehicle index, what happened) for faults and failsafes."""
        self._physics: ph.MulticopterPhysics | None = None
        self._odometry: Odometry | None = None
        self._gnss: GnssError | None = None
        self._boot_offsets_s: npt.NDArray[np.float64] = np.zeros(0)
        self._snapshot = Snapshot()
        self._autopilots: list[Px4Autopilot] = []
        self._signing: list[VehicleSigning] = []
        if key_store is None:
            key_dir = self.config.signing.key_dir
            key_store = FileKeyStore(key_dir) if key_dir is not None else MemoryKeyStore()
        self.key_store: KeyStore = key_store
        self._links: list[list[VehicleLink]] = []
        self._all_links: list[VehicleLink] = []
        self._tlogs: list[TlogWriter] = []
        self._listeners: list[StepListener] = []
        self._end_batch = False
        self._schedule: list[tuple[float, int, str, Callable[[], None]]] = []
        self._schedule_ids = itertools.count()
        self._steps = 0
        self._dt_s = 1.0 / self.config.physics.rate_hz
        self._autopilot_every = max(1, round(self.config.physics.rate_hz / _AUTOPILOT_RATE_HZ))
        self._stack = contextlib.AsyncExitStack()  # what a started emulator owns
        self._run_task: asyncio.Task[None] | None = None
        self._progress = asyncio.Event()
        self._epoch_start_us = 0
        self._wall_start_s = 0.0
        self._max_lag_s = 0.0
        self._late_wakeups = 0
        self._entered = False

    # ================================================================ lifecycle
    async def __aenter__(self) -> Emulator:
        if self._entered:
            raise EmulatorStateError("this Emulator has already been started; create a new one")
        self._entered = True
        self._build_world()
        async with contextlib.AsyncExitStack() as stack:
            stack.push_async_callback(self._close_io)
            self._open_tlogs()
            await self._bind_all()
            self.clock.set_step(self._dt_s)
            self._warn_about_client_timers()
            self.clock.start()
            self._wall_start_s = time.monotonic()
            self._epoch_start_us = int(time.time() * 1e6)
            # Simulated time 0 is now, not when the autopilots were built: binding every
            # vehicle's sockets took long enough on a loaded machine that their UNIX clocks (and
            # a world on them) ran that far behind the host's, past the step's deadlines.
            for ap in self._autopilots:
                ap.unix_epoch_start_us = self._epoch_start_us
            task_group = await stack.enter_async_context(asyncio.TaskGroup())
            self._run_task = task_group.create_task(self._run(), name="sitl-physics")
            stack.callback(self._run_task.cancel)  # the physics loop runs until cancelled
            self._stack = stack.pop_all()
        logger.info(
            "SITL ready: %d vehicle(s), clock %s x%g; MAVSDK URLs %s",
            self.config.vehicles,
            self.clock.mode,
            self.clock.speed,
            ", ".join(ep.mavsdk_url for ep in self.endpoints[:3])
            + (" ..." if self.config.vehicles > 3 else ""),
        )
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            await self._stack.__aexit__(exc_type, exc, tb)
        finally:
            logger.info("SITL stopped at %.2f s simulated", self.time_s)

    async def _close_io(self) -> None:
        for signing in self._signing:
            signing.checkpoint()
        for link in self._all_links:
            link.close()
        for tlog in self._tlogs:
            tlog.close()
        # Transports close their sockets on the next loop iteration: let that happen so the
        # ports are free when we return.
        await asyncio.sleep(0)

    def _build_world(self) -> None:
        config = self.config
        start, yaw = _start_poses(config)
        self._physics = _physics_model(config, start, yaw)
        self._odometry = _odometry_model(config, start)
        self._gnss = _gnss_model(config)
        self._boot_offsets_s = self._boot_offsets(config.vehicles)
        self._snapshot.refresh(self._physics, self._odometry, self._gnss)
        self._autopilots = self._build_autopilots(self._physics, self._odometry)
        initial_key = config.signing.initial_key()
        self._signing = [
            VehicleSigning(
                ap.sysid,
                compid=ap.compid,
                store=self.key_store,
                initial_key=initial_key,
                is_armed=_armed_flag(ap),
            )
            for ap in self._autopilots
        ]
        for fault in config.faults:
            self._schedule_fault(fault)

    def _build_autopilots(
        self, physics: ph.MulticopterPhysics, odometry: Odometry
    ) -> list[Px4Autopilot]:
        """One autopilot per vehicle on the shared physics, odometry and snapshot, each on its
        boot clock, its STATUSTEXTs observed by the emulator."""
        config = self.config
        unix_time_us = None
        if config.clock.unix_time == "host" and self.clock.mode == "realtime":
            # PX4's SYSTEM_TIME reads the host's clock (CLOCK_REALTIME) when it sends.
            def unix_time_us(now_s: float) -> int:
                return int(time.time() * 1e6)

        autopilots = [
            Px4Autopilot(
                i,
                physics=physics,
                odometry=odometry,
                snapshot=self._snapshot,
                projection=self.projection,
                ground_amsl_m=config.home.altitude_amsl_m,
                param_overrides=config.params,
                preflight_ready_after_s=config.preflight_ready_after_s,
                battery_drain_percent_per_min=config.battery_drain_percent_per_min,
                unix_time_us=unix_time_us,
                boot_offset_s=float(self._boot_offsets_s[i]),
                ftp_ardupilot_extensions=config.ftp.ardupilot_extensions,
                flight_logs=config.flight_logs,
            )
            for i in range(config.vehicles)
        ]
        for ap in autopilots:
            ap.on_statustext = self._statustext_observer(ap.index)
            ap.telemetry.truth_fields = config.truth_stream.fields
        return autopilots

    def _boot_offsets(self, n: int) -> npt.NDArray[np.float64]:
        boot = self.config.boot_clock
        if boot.offset_s:
            return np.array(boot.offset_s, dtype=float)
        if boot.spread_s > 0:
            seed = self.config.seed if boot.seed is None else boot.seed
            return np.random.default_rng([seed, 0xB007]).uniform(0.0, boot.spread_s, size=n)
        return np.zeros(n)

    def _warn_about_client_timers(self) -> None:
        """MAVSDK's timers are wall-clock; at high speed factors PX4's timeouts (simulated
        seconds) can fire between two of its messages."""
        clock = self.clock
        if clock.mode != "realtime" or not self._autopilots:
            return
        params = self._autopilots[0].params
        # MAVSDK resends offboard setpoints every 50 ms of wall time; allow 5x for scheduling.
        if clock.speed * 0.25 >= params["COM_OF_LOSS_T"]:
            logger.warning(
                "speed x%g: 0.25 wall s between offboard setpoints are %.2f simulated s, more "
                "than COM_OF_LOSS_T = %.2f s; offboard may fail safe spuriously",
                clock.speed,
                clock.speed * 0.25,
                params["COM_OF_LOSS_T"],
            )
        # MAVSDK sends its heartbeat once per wall second.
        if params["NAV_DLL_ACT"] != 0 and clock.speed * 1.5 >= params["COM_DL_LOSS_T"]:
            logger.warning(
                "speed x%g: client heartbeats arrive %.1f simulated s apart, close to "
                "COM_DL_LOSS_T = %d s; the data-link-loss failsafe may fire spuriously",
                clock.speed,
                clock.speed,
                params["COM_DL_LOSS_T"],
            )

    def _statustext_observer(self, index: int) -> Callable[[float, int, str], None]:
        def observe(time_s: float, severity: int, text: str) -> None:
            if text.startswith("Failsafe") or "lost" in text:
                self.events.append((time_s, index, text))

        return observe

    def _open_tlogs(self) -> None:
        if self.tlog_dir is None:
            return
        for ap in self._autopilots:
            tlog = TlogWriter(Path(self.tlog_dir) / f"vehicle_{ap.sysid:03d}.tlog").open()
            self._tlogs.append(tlog)

    async def _bind_all(self) -> None:
        truth_rates = _truth_stream_rates(self.config)
        # Spread the vehicles' telemetry over the steps of a 0.1 s period.
        phases = max(round(0.1 / self._dt_s), 1)
        for ap in self._autopilots:
            i = ap.index
            links: list[VehicleLink] = []
            for spec in self._link_specs(i, truth_rates):
                link = await self._bind_link(ap, spec, stream_phase_s=(i % phases) * self._dt_s)
                links.append(link)
                self._all_links.append(link)
            self._links.append(links)
            ap.links = list(links)
            ap.link_switch = self._mavlink_signal_switch(i)

    def _link_specs(self, index: int, truth_rates: StreamRates) -> list[_LinkSpec]:
        """Vehicle ``index``'s links: the API's, the ground station's and the ground truth's
        where enabled."""
        config = self.config
        ports = config.ports
        specs = [
            _LinkSpec(
                "api",
                ports.api_local_port(index, config.vehicles),
                (ports.remote_host, ports.api_remote_port(index)),
                config.telemetry.api,
                "ports.api_local_base (--api-local-port-base)",
            )
        ]
        if ports.gcs_enabled:
            specs.append(
                _LinkSpec(
                    "gcs",
                    ports.gcs_local_port(index),
                    (ports.remote_host, ports.gcs_remote_port),
                    config.telemetry.gcs,
                    "ports.gcs_local_base (--gcs-port-base)",
                )
            )
        truth = config.truth_stream
        if truth.enabled:
            specs.append(
                _LinkSpec(
                    "truth",
                    truth.local_base + index,
                    (ports.remote_host, truth.remote_base + index),
                    truth_rates,
                    "truth_stream.local_base (--truth-port-base)",
                )
            )
        return specs

    async def _bind_link(
        self, ap: Px4Autopilot, spec: _LinkSpec, *, stream_phase_s: float
    ) -> VehicleLink:
        """``ap``'s link ``spec`` on its UDP port; PortInUseError names the setting to change."""
        i = ap.index
        tlog = self._tlogs[i] if self._tlogs else None
        link = VehicleLink(
            spec.name,
            sysid=ap.sysid,
            local_port=spec.local_port,
            remote_address=spec.remote,
            rates=spec.rates,
            deliver=self._deliver_to(ap),
            stream_phase_s=stream_phase_s,
            step_s=self._dt_s,
            # 25 Hz of ground truth would swamp the tlogs; PX4 logs none of it either.
            tlog=tlog if spec.name != "truth" else None,
            now_us=self._tlog_time_us,
            signing=self._signing[i],
        )
        try:
            await asyncio.get_running_loop().create_datagram_endpoint(
                functools.partial(_protocol, link),
                local_addr=(self.config.ports.bind_host, spec.local_port),
            )
        except OSError as exc:
            if exc.errno in (errno.EADDRINUSE, errno.EACCES):
                raise PortInUseError(spec.local_port, spec.setting, i, exc.strerror or "") from exc
            raise
        return link

    def _mavlink_signal_switch(self, index: int) -> Callable[[bool], None]:
        """The mavlink_signal failure of vehicle ``index``: all of its links, from the next
        step on (so the acknowledgement of the command that asked for it still goes out)."""

        def switch(up: bool) -> None:
            self._at(
                self.time_s + 0.5 * self._dt_s,
                lambda: self._set_links_up(index, "all", up),
                f"{'restore' if up else 'drop'} every link of vehicle {index}",
            )

        return switch

    def _deliver_to(self, ap: Px4Autopilot) -> Callable[..., None]:
        def deliver(msg: object, link: VehicleLink) -> None:
            ap.handle_message(msg, link, self.time_s)

        return deliver

    def _tlog_time_us(self) -> int:
        return self._epoch_start_us + int(self.time_s * 1e6)

    # ================================================================ running
    @property
    def time_s(self) -> float:
        """Simulated time of the last completed step."""
        return self._steps * self._dt_s

    @property
    def dt_s(self) -> float:
        return self._dt_s

    async def _run(self) -> None:
        clock = self.clock
        dt = self._dt_s
        lockstep = clock.mode == "lockstep"
        while True:
            allowed = clock.allowed_time_s()
            if allowed == math.inf:
                due = _LOCKSTEP_BATCH_STEPS
            else:
                due = math.floor((allowed - self.time_s) / dt + 1e-9)
            if due <= 0:
                await clock.wait_until_allowed_beyond(self.time_s + dt - 1e-9)
                if lockstep:
                    # Let datagrams sent before the release reach their handlers first, so the
                    # step that follows sees them (deterministic lockstep over loopback).
                    await asyncio.sleep(0)
                    await asyncio.sleep(0)
                continue
            if lockstep:
                batch = min(due, _LOCKSTEP_BATCH_STEPS)
            else:
                batch = min(due, _CATCH_UP_BATCH_STEPS)
                if due > 1:
                    self._late_wakeups += 1
                    self._max_lag_s = max(self._max_lag_s, (due - 1) * dt)
            for _ in range(batch):
                self._step(dt)
                if self._end_batch:
                    self._end_batch = False
                    break
            # Once a batch: the steps of a batch run back to back without yielding, so their
            # messages would leave together anyway; a datagram per step was a system call per
            # link per 5 ms (PX4's mavlink module also sends what a loop queued in one datagram).
            for link in self._all_links:
                if link.pending:
                    link.flush()
            self._progress.set()
            self._progress = asyncio.Event()
            await asyncio.sleep(0)

    def _step(self, dt: float) -> None:
        physics = self._physics
        odometry = self._odometry
        assert physics is not None and odometry is not None
        now = self.time_s
        schedule = self._schedule
        while schedule and schedule[0][0] <= now + 1e-9:
            _, _, _, action = heapq.heappop(schedule)
            action()
        if self._steps % self._autopilot_every == 0:
            for ap in self._autopilots:
                ap.update(now)
        physics.step(dt)
        odometry.step(dt)
        gnss = self._gnss
        if gnss is not None and gnss.active:
            gnss.step(dt)
        self._steps += 1
        now = self.time_s
        self._snapshot.refresh(physics, odometry, gnss)
        self.clock.advance_to(now)
        for listener in self._listeners:
            listener(now, self.truth)
        for ap, links in zip(self._autopilots, self._links, strict=True):
            if not ap.alive:
                continue
            build = ap.telemetry.build
            for link in links:
                if now < link.streams.next_due_s:
                    continue
                for msg_id in link.streams.due(now):
                    msg = build(msg_id, now)
                    if msg is not None:
                        link.send(msg)

    async def wait_for(
        self, predicate: Callable[[], bool], *, timeout_s: float, what: str = "a condition"
    ) -> None:
        """Wait (wall ``timeout_s``) until ``predicate()`` holds after a physics step.

        Raises :class:`sitl.errors.SitlTimeoutError` naming ``what``.
        """
        self._require_running()
        try:
            async with asyncio.timeout(timeout_s):
                while not predicate():
                    await self._progress.wait()
        except TimeoutError:
            raise SitlTimeoutError(what, timeout_s) from None

    async def run_for(self, duration_s: float, *, timeout_s: float = 60.0) -> None:
        """Wait until ``duration_s`` more simulated seconds have been stepped."""
        end = self.time_s + duration_s
        await self.wait_for(
            lambda: self.time_s >= end - 1e-9,
            timeout_s=timeout_s,
            what=f"simulated time {end:.2f} s",
        )

    def _require_running(self) -> None:
        if self._run_task is None:
            raise EmulatorStateError("the emulator is not running; use 'async with Emulator()'")

    # ================================================================ world hooks
    def add_step_listener(self, listener: StepListener) -> Callable[[], None]:
        """Call ``listener(time_s, truth)`` after every physics step; returns a remover.

        Listeners run inside the physics loop: keep them quick and synchronous. An exception
        stops the emulator (it surfaces when the ``async with`` block exits).
        """
        self._listeners.append(listener)

        def remove() -> None:
            with contextlib.suppress(ValueError):
                self._listeners.remove(listener)

        return remove

    def end_batch(self) -> None:
        """End the running batch of steps after this one (for a step listener that has sampled
        something to hand over): the event loop runs before the next step, so what the listener
        queued goes out stamped and sent before later steps' (steps of a batch run back to back
        and their messages would otherwise leave together)."""
        self._end_batch = True

    @property
    def endpoints(self) -> list[VehicleEndpoints]:
        ports = self.config.ports
        gcs = ports.gcs_enabled
        truth = self.config.truth_stream
        return [
            VehicleEndpoints(
                i,
                i + 1,
                ports.api_local_port(i, self.config.vehicles),
                ports.api_remote_port(i),
                ports.gcs_local_port(i) if gcs else None,
                ports.gcs_remote_port if gcs else None,
                truth.local_base + i if truth.enabled else None,
                truth.remote_base + i if truth.enabled else None,
            )
            for i in range(self.config.vehicles)
        ]

    def vehicle_status(self, index: int) -> VehicleStatus:
        ap = self._autopilot(index)
        return VehicleStatus(
            index,
            ap.sysid,
            ap.alive,
            ap.armed,
            ap.mode,
            ap.landed,
            ap.failsafe_active,
            ap.flow_ok,
            ap.gps_ok,
            ap.battery_remaining_pct,
            tuple(text for _, text in ap.status_log),
        )

    def autopilot(self, index: int) -> Px4Autopilot:
        """The state machine of vehicle ``index`` (for inspection; drive it over MAVLink)."""
        return self._autopilot(index)

    def signing(self, index: int) -> VehicleSigning:
        """The message-signing state of vehicle ``index`` (key on or off, counters)."""
        self._autopilot(index)
        return self._signing[index]

    def stats(self) -> EmulatorStats:
        links = self._all_links
        return EmulatorStats(
            self._steps,
            self.time_s,
            time.monotonic() - self._wall_start_s if self._wall_start_s else 0.0,
            self._max_lag_s,
            self._late_wakeups,
            sum(link.rx_datagrams for link in links),
            sum(link.rx_packets for link in links),
            sum(link.rx_bad for link in links),
            sum(link.tx_packets for link in links),
            sum(link.handler_errors for link in links),
            sum(link.rx_rejected for link in links),
        )

    def _autopilot(self, index: int) -> Px4Autopilot:
        if not self._autopilots:
            raise EmulatorStateError("the emulator has not been started")
        if not 0 <= index < len(self._autopilots):
            raise EmulatorStateError(
                f"no vehicle with index {index}; valid: 0..{len(self._autopilots) - 1}"
            )
        return self._autopilots[index]

    def _physics_or_raise(self) -> ph.MulticopterPhysics:
        if self._physics is None:
            raise EmulatorStateError("the emulator has not been started")
        return self._physics

    def _odometry_or_raise(self) -> Odometry:
        if self._odometry is None:
            raise EmulatorStateError("the emulator has not been started")
        return self._odometry

    def _gnss_or_raise(self) -> GnssError:
        if self._gnss is None:
            raise EmulatorStateError("the emulator has not been started")
        return self._gnss

    # ================================================================ faults
    def kill_vehicle(self, index: int, at_s: float | None = None) -> None:
        """Vehicle ``index`` dies (stops sending and answering, motors off) now or at ``at_s``."""
        ap = self._autopilot(index)

        def kill() -> None:
            ap.kill(self.time_s)
            for link in self._links[index] if self._links else []:
                link.alive = False
            self.events.append((self.time_s, index, "killed"))

        self._at(at_s, kill, f"kill vehicle {index}")

    def take_over(
        self,
        index: int,
        mode: str = "hold",
        at_s: float | None = None,
        *,
        rearm_after_s: float | None = None,
    ) -> None:
        """A pilot takes vehicle ``index`` over now or at ``at_s``: an RC mode switch to
        ``mode`` (``hold``, ``land``, ``return`` or ``posctl``), which PX4 obeys at once; or
        ``disarm``: another ground station force-disarms it (MAV_CMD_COMPONENT_ARM_DISARM,
        param2 21196), in the air too. ``rearm_after_s``: the pilot arms it again that long
        after, as a pilot does (an ordinary arm, PX4's checks and all)."""
        ap = self._autopilot(index)
        modes = {
            "hold": FlightMode.HOLD,
            "land": FlightMode.LAND,
            "return": FlightMode.RTL,
            "posctl": FlightMode.POSCTL,
        }
        if mode not in modes and mode != "disarm":
            raise ValueError(
                f"unknown takeover mode {mode!r}; use one of {sorted([*modes, 'disarm'])}"
            )

        def take() -> None:
            if mode == "disarm":
                result = ap.ground_station_arm(arm=False, force=True, now_s=self.time_s)
                self.events.append(
                    (self.time_s, index, f"force-disarmed by another ground station ({result})")
                )
            else:
                ap.pilot_takeover(modes[mode], self.time_s)
                self.events.append((self.time_s, index, f"taken over by a pilot ({mode})"))

        def rearm() -> None:
            result = ap.ground_station_arm(arm=True, force=False, now_s=self.time_s)
            self.events.append((self.time_s, index, f"re-armed by the pilot ({result})"))

        self._at(at_s, take, f"take vehicle {index} over")
        if rearm_after_s is not None:
            start = self.time_s if at_s is None else at_s
            self._at(start + rearm_after_s, rearm, f"re-arm vehicle {index}")

    def drop_link(
        self,
        index: int,
        link: LinkName = "all",
        at_s: float | None = None,
        duration_s: float | None = None,
    ) -> None:
        """Vehicle ``index``'s ``link`` carries nothing from ``at_s`` (default now) for
        ``duration_s`` (default: for good)."""
        self._autopilot(index)
        if link not in ("api", "gcs", "all"):
            raise ValueError(f"unknown link {link!r}; use 'api', 'gcs' or 'all'")

        def set_up(up: bool) -> Callable[[], None]:
            return lambda: self._set_links_up(index, link, up)

        start = self.time_s if at_s is None else at_s
        self._at(at_s, set_up(False), f"drop {link} link of vehicle {index}")
        if duration_s is not None:
            self._at(start + duration_s, set_up(True), f"restore {link} link of vehicle {index}")

    def _set_links_up(self, index: int, link: LinkName, up: bool) -> None:
        for vehicle_link in self._links[index] if self._links else []:
            if link in ("all", vehicle_link.name):
                vehicle_link.up = up
        self.events.append((self.time_s, index, f"{link} link {'restored' if up else 'dropped'}"))

    def fail_sensor(
        self,
        index: int,
        sensor: SensorName,
        at_s: float | None = None,
        duration_s: float | None = None,
    ) -> None:
        """Sensor ``"flow"`` or ``"gps"`` of vehicle ``index`` stops from ``at_s`` (default now)
        for ``duration_s`` (default: for good): the failure ``optical_flow`` or ``gps``
        ``off`` of :meth:`inject_failure`."""
        if sensor not in _SENSOR_UNITS:
            raise ValueError(f"unknown sensor {sensor!r}; use 'flow' or 'gps'")
        self.inject_failure(index, _SENSOR_UNITS[sensor], "off", at_s=at_s, duration_s=duration_s)

    def inject_failure(
        self,
        index: int,
        unit: str,
        failure_type: str = "off",
        *,
        instance: int = 0,
        at_s: float | None = None,
        duration_s: float | None = None,
    ) -> None:
        """Inject PX4's failure ``unit`` / ``failure_type`` (PX4's names, as its ``failure``
        shell command takes them: ``gps off``, ``motor off`` with ``instance`` 1-8 or 0 for
        all, ``battery off``, ``optical_flow``, ``rc_signal``, ``mavlink_signal``; ``ok`` ends
        a failure) into vehicle ``index`` from ``at_s`` (default now), for ``duration_s``
        (default: until an ``ok``). It is what MAV_CMD_INJECT_FAILURE does (see
        :mod:`sitl.failure_injection`), without the SYS_FAILURE_EN check; a combination the
        emulator cannot inject raises ``ValueError`` naming those it can.
        """
        ap = self._autopilot(index)
        if unit not in UNITS:
            raise ValueError(f"unknown failure unit {unit!r}; PX4's are {sorted(UNITS)}")
        if failure_type not in TYPES:
            raise ValueError(f"unknown failure type {failure_type!r}; PX4's are {sorted(TYPES)}")
        unit_id, type_id = UNITS[unit], TYPES[failure_type]
        if not ap.failure_supported(unit_id, type_id, instance):
            supported = ", ".join(
                describe(u, t) for u, types in SUPPORTED.items() for t in sorted(types)
            )
            raise ValueError(
                f"the emulator cannot inject {unit} {failure_type} (instance {instance}); it "
                f"can: {supported} (motor instances 0-8, battery instance 0)"
            )

        def inject(type_id: int) -> Callable[[], None]:
            def apply() -> None:
                ap.inject_failure(unit_id, type_id, instance)
                self.events.append((self.time_s, index, describe(unit_id, type_id)))

            return apply

        what = f"{unit} {failure_type} on vehicle {index}"
        start = self.time_s if at_s is None else at_s
        self._at(at_s, inject(type_id), what)
        if duration_s is not None and type_id != TYPES["ok"]:
            self._at(start + duration_s, inject(TYPES["ok"]), f"{unit} ok on vehicle {index}")

    def deny_arming(
        self,
        index: int,
        count: int = 1,
        reason: str = PX4_ARMING_DENIED_TEXT,
        *,
        at_s: float | None = None,
        retry_window_s: float = 2.0,
    ) -> None:
        """From ``at_s`` (default now), refuse vehicle ``index``'s next ``count`` arm attempts
        the way PX4 refuses an arm when a health check fails: COMMAND_ACK TEMPORARILY_REJECTED
        and a CRITICAL STATUSTEXT ``reason``, on every retransmission of a refused attempt
        within ``retry_window_s`` simulated seconds (see :class:`sitl.config.DenyArmingFault`).
        """
        ap = self._autopilot(index)
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count!r}")
        if not reason:
            raise ValueError("reason must not be empty")
        if retry_window_s < 0:
            raise ValueError(f"retry_window_s must be >= 0, got {retry_window_s!r}")

        def deny() -> None:
            ap.deny_arming(count, reason, retry_window_s)
            self.events.append((self.time_s, index, f"arming denied x{count}: {reason}"))

        self._at(at_s, deny, f"deny arming of vehicle {index} x{count}")

    def _schedule_fault(
        self, fault: KillFault | LinkDropFault | SensorFault | DenyArmingFault | FailureFault
    ) -> None:
        if isinstance(fault, FailureFault):
            when = fault.model_dump(include={"instance", "at_s", "duration_s"})
            self.inject_failure(fault.vehicle_index, fault.unit, fault.type, **when)
        elif isinstance(fault, KillFault):
            self.kill_vehicle(fault.vehicle_index, fault.at_s)
        elif isinstance(fault, LinkDropFault):
            self.drop_link(fault.vehicle_index, fault.link, fault.at_s, fault.duration_s)
        elif isinstance(fault, DenyArmingFault):
            self.deny_arming(
                fault.vehicle_index,
                fault.count,
                fault.reason,
                at_s=fault.at_s,
                retry_window_s=fault.retry_window_s,
            )
        else:
            self.fail_sensor(fault.vehicle_index, fault.sensor, fault.at_s, fault.duration_s)

    def _at(self, at_s: float | None, action: Callable[[], None], what: str) -> None:
        if at_s is None or (self._run_task is not None and at_s <= self.time_s):
            action()
            logger.info("fault at %.2f s: %s", self.time_s, what)
            return

        def logged() -> None:
            logger.info("fault at %.2f s: %s", self.time_s, what)
            action()

        heapq.heappush(self._schedule, (at_s, next(self._schedule_ids), what, logged))


class _LinkSpec(NamedTuple):
    """One UDP link of a vehicle: its name, local port, remote (host, port), the streams it
    sends, and the setting that moves its port (for a port already in use)."""

    name: str
    local_port: int
    remote: tuple[str, int]
    rates: StreamRates
    setting: str


def _truth_stream_rates(config: EmulatorConfig) -> StreamRates:
    """Like PX4's custom-mode MAVLink instance on SIH's port: HEARTBEAT and the ground truth."""
    return StreamRates(
        **{
            **dict.fromkeys(StreamRates.model_fields, 0.0),
            "heartbeat_hz": 1.0,
            "hil_state_quaternion_hz": config.truth_stream.rate_hz,
        }
    )


def _start_poses(
    config: EmulatorConfig,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Where the vehicles stand at start: NED positions (n, 3) [m] on the ground and yaws (n,)
    [rad]; the configured placements first, the rest on the grid."""
    n = config.vehicles
    start = np.zeros((n, 3))
    yaw = np.zeros(n)
    placement = config.placement
    for i in range(n):
        if i < len(placement.positions):
            p = placement.positions[i]
            start[i] = (p.north_m, p.east_m, 0.0)
            yaw[i] = math.radians(p.yaw_deg)
        else:
            k = i - len(placement.positions)
            row, col = divmod(k, placement.grid_columns)
            start[i] = (row * placement.grid_spacing_m, col * placement.grid_spacing_m, 0.0)
    return start, yaw


def _physics_model(
    config: EmulatorConfig, start: npt.NDArray[np.float64], yaw: npt.NDArray[np.float64]
) -> ph.MulticopterPhysics:
    """The vehicles' kinematic model from ``config.physics`` and ``config.wind`` (seeded)."""
    wind_cfg = config.wind
    wind = ph.Wind(
        config.vehicles,
        (wind_cfg.north_m_s, wind_cfg.east_m_s, 0.0),
        wind_cfg.gust_std_m_s,
        wind_cfg.gust_time_constant_s,
        rng=np.random.default_rng([config.seed, 0x317D]),
    )
    return ph.MulticopterPhysics(
        start,
        yaw,
        time_constant_s=config.physics.velocity_time_constant_s,
        position_gain_1_s=config.physics.position_gain_1_s,
        wind=wind if wind.active else None,
        wind_rejection_time_s=wind_cfg.rejection_time_s,
        drag_1_s=wind_cfg.drag_1_s,
        airspeed_drag_1_s=config.physics.airspeed_drag_1_s,
        velocity_integral_gain_1_s2=config.physics.velocity_integral_gain_1_s2,
        tilt_time_constant_s=config.physics.tilt_time_constant_s,
    )


def _odometry_model(config: EmulatorConfig, start: npt.NDArray[np.float64]) -> Odometry:
    """The vehicles' odometry (noise and drift of ``config.odometry``, seeded)."""
    odo = config.odometry
    return Odometry(
        start,
        position_noise_std_m=odo.position_noise_std_m,
        velocity_noise_std_m_s=odo.velocity_noise_std_m_s,
        drift_bias_std_m_s=odo.drift_bias_std_m_s,
        drift_random_walk_m_s_per_sqrt_s=odo.drift_random_walk_m_s_per_sqrt_s,
        seed=config.seed,
    )


def _gnss_model(config: EmulatorConfig) -> GnssError:
    """The vehicles' GPS error (``config.gps_error``, seeded)."""
    gps = config.gps_error
    return GnssError(
        config.vehicles,
        bias_std_m=gps.bias_std_m,
        bias_time_constant_s=gps.bias_time_constant_s,
        noise_std_m=gps.noise_std_m,
        rng=np.random.default_rng([config.seed, 0x6E55]),
    )


def _armed_flag(ap: Px4Autopilot) -> Callable[[], bool]:
    """Whether ``ap`` is armed, asked when it matters (signing keys change only disarmed)."""
    return lambda: ap.armed


def _protocol(link: VehicleLink) -> VehicleLink:
    """The datagram protocol factory's product: the link already built for this port."""
    return link

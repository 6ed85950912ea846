"""Real PX4 SITL for a scenario: one headless PX4 autopilot (SIH quadrotor) per vehicle.

The bundled emulator (``sitl/``) is a PX4 look-alike; this module starts the real thing, so that
``mission-runner vehicle``/``run`` with per-vehicle urls fly against PX4's own commander, EKF2 and
controllers. Each vehicle ``j`` of the scenario becomes PX4 SITL instance ``first_instance + j``
in a fresh working directory, with its home placed at the vehicle's ``initial_position_m`` around
a base home (the scenario frame's origin), the scenario's ``flight.autopilot_params`` as
``PX4_PARAM_<NAME>`` and, optionally, a simulation speed factor.

PX4 forces MAVLink system id = instance + 1 at every boot, so a vehicle's ``id`` must be its
instance + 1: ids 7, 8 run as instances 6, 7 (``--first-instance 6``). Ports of instance ``i``
(PX4's ``px4-rc.mavlink``):

=================  ==================  =========================================================
link               PX4 binds           PX4 sends to
=================  ==================  =========================================================
API / offboard     14580+i             14540+i (14549 for every i > 9): ``udpin://0.0.0.0:<port>``
GCS                18570+i             14550 (every instance)
SIH ground truth   19450+i             19410+i (HIL_STATE_QUATERNION, 25 Hz)
=================  ==================  =========================================================

PX4 holds the home in float32 parameters (``SIH_LOC_LAT0``/``LON0``): a vehicle starts up to
~0.2 m from its ``initial_position_m`` (latitude steps of 0.42 m); :class:`Px4Instance` carries the
home as PX4 holds it and that ``placement_error_m``.

An instance is ready when PX4 prints ``Ready for takeoff!`` (its arming checks pass, so EKF2 has
a global position). Readiness is read from the console file PX4 writes, not from a MAVLink port:
the API port stays free for the mission runner, which binds it. Instances are stopped with
SIGTERM to their process group, then SIGKILL after 10 s, also when start-up fails half-way.

Command line (``mission_runner.cli`` registers it)::

    mission-runner px4-sitl CONFIG --px4-dir DIR [--first-instance N] [--speed F] [--nice N]
                                   [--realtime] [--work-dir D]

:func:`add_arguments` adds exactly these to a sub-parser, and sets ``handler=command`` (the
CLI's convention, ``arguments.handler(arguments)``):

======================  ===============================================================
argument                meaning
======================  ===============================================================
``config``              positional, :class:`pathlib.Path`: the scenario YAML file
``--px4-dir``           :class:`pathlib.Path`: PX4 checkout or its
                        ``build/px4_sitl_default`` (default: environment
                        ``PX4_SITL_DIR``; required if that is unset)
``--first-instance``    int >= 0, default 0: instance of the first vehicle
``--speed``             float > 0, default 1.0: ``PX4_SIM_SPEED_FACTOR``
``--nice``              int 0..19, default 0: the instances' CPU priority (see
                        :data:`DEFAULT_NICE`)
``--realtime``          flag: let PX4 run its threads real-time (``SCHED_FIFO``) where
                        it may, as it does by default (see :func:`instance_scheduling`)
``--work-dir``          :class:`pathlib.Path`, default None: where the instances' working
                        directories go (kept); default a temporary directory, removed
                        at the end
======================  ===============================================================

Wiring in ``mission_runner/cli/px4_sitl.py``::

    px4 = commands.add_parser("px4-sitl", help="run real PX4 SITL (SIH), one per vehicle")
    px4sitl.add_arguments(px4)

:func:`command` runs the instances until SIGINT/SIGTERM and returns 0; errors are
:class:`~mission_runner.errors.MissionRunnerError` subclasses for the CLI to report.

Exception tree::

    RunnerError                       (mission_runner.runner.errors)
    └── Px4SitlError                  PX4 SITL cannot be started for this scenario (ids, ports,
        │                             parameters, an instance exited); the message says what to do
        ├── Px4BuildNotFoundError     no PX4 SITL binary: build it with make px4_sitl_default
        └── Px4SitlTimeoutError       an instance was not ready in time (also a RunnerTimeoutError)
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import dataclasses
import functools
import logging
import math
import os
import re
import resource
import shutil
import signal
import socket
import struct
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from . import argtypes
from .limits import MAX_CLOCK_SPEED
from .runner.errors import RunnerError, RunnerTimeoutError
from .tasks import first_completed

if TYPE_CHECKING:
    from .config import Scenario

logger = logging.getLogger(__name__)

#: The instances' default niceness (``--nice``), also given to each one's scheduling autogroup
#: (Linux puts every session in its own group and shares the CPU between groups, whatever the
#: niceness of the processes inside them). A simulated autopilot that gets less CPU runs its
#: simulated clock slower, which the mission clock and each vehicle's clock mapping follow; a
#: controller that gets less misses its deadlines. Not lowered by default: with four SIH
#: instances at speed factor 2 on two cores, nice 10 flew one mission of two to its bounds, which
#: is no evidence it helps, and at 1x it slowed SIH's clock from 0.985x to 0.957-0.986x.
DEFAULT_NICE = 0
#: The most a niceness can be on Linux.
MAX_NICE = 19

_T = TypeVar("_T")

#: SIH quadrotor airframe, no external simulator.
SYS_AUTOSTART = "10040"
SIM_MODEL = "sihsim_quadx"
BUILD_SUBDIR = Path("build") / "px4_sitl_default"

DEFAULT_HOME_LAT_DEG = 47.397742
DEFAULT_HOME_LON_DEG = 8.545594
DEFAULT_HOME_ALT_M = 488.0
#: Flat-earth radius, the same as the runner's GPS-to-local conversion (runner/ranges.py), so a
#: vehicle's first fix maps back onto its ``initial_position_m``.
EARTH_RADIUS_M = 6_371_000.0

API_REMOTE_PORT_BASE = 14540
API_LOCAL_PORT_BASE = 14580
#: PX4 sends the API link of every instance above this to one shared port.
LAST_OWN_API_INSTANCE = 9
SHARED_API_PORT = 14549
GCS_LOCAL_PORT_BASE = 18570
GCS_REMOTE_PORT = 14550
TRUTH_REMOTE_PORT_BASE = 19410
TRUTH_LOCAL_PORT_BASE = 19450
PAYLOAD_LOCAL_PORT_BASE = 14280
GIMBAL_LOCAL_PORT_BASE = 13030

#: PX4 creates ``./log`` (a directory, for .ulg files) in its working directory: the console
#: must go to a file of another name, or PX4 exits at once.
CONSOLE_FILE_NAME = "px4_console.log"
READY_LINE = "Ready for takeoff!"
READY_POLL_S = 0.1
STOP_TIMEOUT_S = 10.0
KILL_TIMEOUT_S = 5.0
CONSOLE_TAIL_LINES = 15
MAX_CONSOLE_CHARS = 1_000_000

PARAM_NAME = re.compile(r"^[A-Z0-9_]{1,16}$")
UNKNOWN_PARAM = re.compile(r"Parameter (\w+) not found")


class Px4SitlError(RunnerError):
    """PX4 SITL could not be started or kept running for a scenario; the message says why."""


class Px4BuildNotFoundError(Px4SitlError):
    """The PX4 SITL binary is not where ``--px4-dir`` points."""


class Px4SitlTimeoutError(Px4SitlError, RunnerTimeoutError):
    """An instance did not report ready in time; ``what`` names it and quotes its console."""


# --- Planning (pure) --------------------------------------------------------------------------


def px4_build_dir(px4_dir: str | os.PathLike[str]) -> Path:
    """The ``px4_sitl_default`` build directory of ``px4_dir``: a PX4 checkout (holding
    ``build/px4_sitl_default``) or that build directory itself. Raises
    :class:`Px4BuildNotFoundError` when ``bin/px4`` or ``etc`` is missing there."""
    given = Path(px4_dir).expanduser()
    candidates = [given / BUILD_SUBDIR, given]
    for candidate in candidates:
        if (candidate / "bin" / "px4").is_file() and (candidate / "etc").is_dir():
            return candidate.resolve()
    looked = ", ".join(str(candidate / "bin" / "px4") for candidate in candidates)
    raise Px4BuildNotFoundError(
        f"no PX4 SITL build in {given} (looked for {looked}): build it in the PX4-Autopilot "
        "checkout with `make px4_sitl_default` and pass the checkout (or its "
        "build/px4_sitl_default) as --px4-dir"
    )


def check_instance_ids(vehicle_ids: Sequence[int], first_instance: int) -> None:
    """Raise :class:`Px4SitlError` unless vehicle ``j`` has id ``first_instance + j + 1``: PX4
    forces system id = instance + 1, and the runner addresses a vehicle by its id."""
    if first_instance < 0:
        raise Px4SitlError(f"first instance must be >= 0 (got {first_instance})")
    ids = list(vehicle_ids)
    expected = [first_instance + index + 1 for index in range(len(ids))]
    if ids == expected:
        return
    last = first_instance + len(ids) - 1
    message = (
        f"vehicle ids {ids} do not fit PX4 SITL instances {first_instance}..{last}: PX4 gives "
        f"instance i MAVLink system id i+1, so these instances need ids {expected}; "
    )
    consecutive = ids[0] >= 1 and ids == list(range(ids[0], ids[0] + len(ids)))
    if consecutive:
        message += f"use --first-instance {ids[0] - 1} (first_instance={ids[0] - 1})"
    else:
        message += "renumber the vehicles consecutively (id = instance + 1)"
    raise Px4SitlError(message)


def api_port_of(instance: int) -> int:
    """UDP port PX4 instance ``instance`` sends its API (offboard) link to."""
    if instance > LAST_OWN_API_INSTANCE:
        return SHARED_API_PORT
    return API_REMOTE_PORT_BASE + instance


def offset_lat_lon_deg(
    base_lat_deg: float, base_lon_deg: float, north_m: float, east_m: float
) -> tuple[float, float]:
    """(latitude, longitude) [deg] of the point ``north_m``, ``east_m`` from the base point, flat
    earth (exact to millimetres over a few hundred metres)."""
    lat_deg = base_lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
    lon_deg = base_lon_deg + math.degrees(
        east_m / (EARTH_RADIUS_M * math.cos(math.radians(base_lat_deg)))
    )
    return lat_deg, lon_deg


def px4_float(value: float) -> float:
    """``value`` as PX4 holds it: parameters are float32, so SIH's home latitude moves in steps
    of 2**-18 deg (0.42 m) and its longitude near 8 deg in steps of 0.07 m."""
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


@dataclasses.dataclass(frozen=True)
class Px4Instance:
    """One PX4 SITL instance: which vehicle, where it listens and sends, where it runs.

    ``home_lat_deg``/``home_lon_deg`` are the home as PX4 holds it (float32, see
    :func:`px4_float`); ``placement_error_m`` is how far that is from the vehicle's
    ``initial_position_m`` (up to ~0.2 m)."""

    vehicle_id: int
    instance: int
    home_lat_deg: float
    home_lon_deg: float
    home_alt_m: float
    work_dir: Path
    pid: int | None = None
    ready_after_s: float | None = None
    placement_error_m: float = 0.0

    @property
    def sysid(self) -> int:
        """MAVLink system id (PX4 sets instance + 1 at boot)."""
        return self.instance + 1

    @property
    def api_port(self) -> int:
        """Port the API link arrives at (the mission runner binds it)."""
        return api_port_of(self.instance)

    @property
    def api_url(self) -> str:
        """MAVSDK url of the API link."""
        return f"udpin://0.0.0.0:{self.api_port}"

    @property
    def gcs_port(self) -> int:
        """Port of the vehicle's GCS link (it sends from here to 14550; a GCS can also reach
        it with ``udpout://127.0.0.1:<gcs_port>``)."""
        return GCS_LOCAL_PORT_BASE + self.instance

    @property
    def truth_port(self) -> int:
        """Port SIH's ground truth (HIL_STATE_QUATERNION) arrives at."""
        return TRUTH_REMOTE_PORT_BASE + self.instance

    @property
    def log_path(self) -> Path:
        """PX4's console output (its .ulg flight logs are under ``work_dir/log``)."""
        return self.work_dir / CONSOLE_FILE_NAME

    @property
    def local_ports(self) -> dict[int, str]:
        """UDP ports PX4 binds, with what each is for."""
        return {
            API_LOCAL_PORT_BASE + self.instance: "API link",
            GCS_LOCAL_PORT_BASE + self.instance: "GCS link",
            TRUTH_LOCAL_PORT_BASE + self.instance: "SIH truth link",
            PAYLOAD_LOCAL_PORT_BASE + self.instance: "payload link",
            GIMBAL_LOCAL_PORT_BASE + self.instance: "gimbal link",
        }


def merged_params(
    scenario: Scenario, params: Mapping[str, float | int] | None = None
) -> dict[str, float | int]:
    """The scenario's ``flight.autopilot_params`` overridden by ``params``; names are checked
    (PX4 names: upper case, digits, ``_``, at most 16 characters) since they become
    environment variables."""
    merged: dict[str, float | int] = dict(scenario.flight.autopilot_params)
    merged.update(params or {})
    for name, value in merged.items():
        if not PARAM_NAME.match(name):
            raise Px4SitlError(
                f"parameter name {name!r} is not a PX4 name (A-Z, 0-9, _, at most 16 characters)"
            )
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise Px4SitlError(f"parameter {name}: value must be a finite number (got {value!r})")
    return merged


def plan_instances(
    scenario: Scenario,
    run_dir: Path,
    *,
    first_instance: int = 0,
    home_lat_deg: float = DEFAULT_HOME_LAT_DEG,
    home_lon_deg: float = DEFAULT_HOME_LON_DEG,
    home_alt_m: float = DEFAULT_HOME_ALT_M,
) -> list[Px4Instance]:
    """One :class:`Px4Instance` per vehicle (not started): instance numbers, homes at the
    vehicles' ``initial_position_m`` around the base home (rounded as PX4 will hold them),
    working directories ``run_dir/instance-<i>``."""
    check_instance_ids([vehicle.id for vehicle in scenario.vehicles], first_instance)
    planned = []
    for index, vehicle in enumerate(scenario.vehicles):
        instance = first_instance + index
        north_m, east_m = vehicle.initial_position_m
        exact_lat_deg, exact_lon_deg = offset_lat_lon_deg(
            home_lat_deg, home_lon_deg, north_m, east_m
        )
        lat_deg, lon_deg = px4_float(exact_lat_deg), px4_float(exact_lon_deg)
        error_north_m = math.radians(lat_deg - exact_lat_deg) * EARTH_RADIUS_M
        error_east_m = (
            math.radians(lon_deg - exact_lon_deg)
            * EARTH_RADIUS_M
            * math.cos(math.radians(home_lat_deg))
        )
        planned.append(
            Px4Instance(
                vehicle_id=vehicle.id,
                instance=instance,
                home_lat_deg=lat_deg,
                home_lon_deg=lon_deg,
                home_alt_m=px4_float(home_alt_m),
                work_dir=run_dir / f"instance-{instance}",
                placement_error_m=math.hypot(error_north_m, error_east_m),
            )
        )
    return planned


def _param_text(value: float | int) -> str:
    return str(value) if isinstance(value, int) else repr(float(value))


def instance_environment(
    instance: Px4Instance,
    *,
    speed_factor: float = 1.0,
    params: Mapping[str, float | int] | None = None,
    base_environment: Mapping[str, str] | None = None,
) -> dict[str, str]:
    """The environment PX4 instance ``instance`` starts with: ``base_environment`` (default: this
    process's) without any inherited ``PX4_*`` variable (a stray ``PX4_PARAM_`` in a shell must
    not change a flight), plus airframe, home, speed factor and ``PX4_PARAM_<NAME>``."""
    base = os.environ if base_environment is None else base_environment
    environment = {key: value for key, value in base.items() if not key.startswith("PX4_")}
    environment |= {
        "PX4_SYS_AUTOSTART": SYS_AUTOSTART,
        "PX4_SIM_MODEL": SIM_MODEL,
        "PX4_HOME_LAT": f"{instance.home_lat_deg:.9f}",
        "PX4_HOME_LON": f"{instance.home_lon_deg:.9f}",
        "PX4_HOME_ALT": f"{instance.home_alt_m:.3f}",
    }
    # PX4's rcS rescales its link-loss timeouts whenever the factor is set, even to 1: leave it
    # unset at 1 so real-time instances keep PX4's defaults.
    if speed_factor != 1.0:
        environment["PX4_SIM_SPEED_FACTOR"] = f"{speed_factor:g}"
    for name, value in (params or {}).items():
        environment[f"PX4_PARAM_{name}"] = _param_text(value)
    return environment


def instances_table(instances: Sequence[Px4Instance]) -> str:
    """What runs where, one line per instance, and how to connect to them."""
    header = (
        "vehicle",
        "instance",
        "sysid",
        "api (MAVSDK url)",
        "gcs port",
        "truth port",
        "home lat, lon [deg], alt [m]",
        "pid",
        "ready [s]",
        "console",
    )
    rows = [header]
    for item in instances:
        rows.append(
            (
                str(item.vehicle_id),
                str(item.instance),
                str(item.sysid),
                item.api_url,
                str(item.gcs_port),
                str(item.truth_port),
                f"{item.home_lat_deg:.7f}, {item.home_lon_deg:.7f}, {item.home_alt_m:.1f}",
                "-" if item.pid is None else str(item.pid),
                "-" if item.ready_after_s is None else f"{item.ready_after_s:.1f}",
                str(item.log_path),
            )
        )
    widths = [max(len(row[column]) for row in rows) for column in range(len(header))]
    lines = [
        "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()
        for row in rows
    ]
    lines.append(
        f"every instance's GCS link sends to udp port {GCS_REMOTE_PORT} (QGroundControl, MAVProxy)"
    )
    lines.append("controllers connect to each vehicle's api url, e.g.")
    lines.extend(
        f"  mission-runner vehicle CONFIG --id {item.vehicle_id} --url {item.api_url}"
        for item in instances
    )
    return "\n".join(lines)


# --- Running ----------------------------------------------------------------------------------


def _ports_in_use(ports: Mapping[int, str]) -> list[str]:
    """Which of ``ports`` (UDP, any address) cannot be bound now."""
    busy = []
    for port, what in ports.items():
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            try:
                probe.bind(("0.0.0.0", port))
            except OSError:
                busy.append(f"{port} ({what})")
    return busy


def _signal_group(pid: int, signal_number: signal.Signals) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, signal_number)


#: ``prctl`` option and capability number (linux/prctl.h, linux/capability.h).
_PR_CAPBSET_DROP = 24
_CAP_SYS_NICE = 23
#: The C library's ``prctl``, looked up once in the parent: a child between fork and exec
#: should call, not load.
_prctl: Callable[..., int] | None
try:
    _prctl = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):  # not Linux
    _prctl = None


def instance_scheduling(nice: int, realtime: bool) -> None:
    """In a child about to become an instance (its new session begun), before it execs PX4.

    Unless ``realtime``: no real-time threads. PX4 asks for ``SCHED_FIFO`` for its work queues
    and tasks and falls back to normal threads where that is refused (an ordinary user); as
    root it gets them, and a SITL instance's real-time threads then preempt every ordinary
    process on the machine, the mission's own controllers and range aid among them, whenever
    they wake. Refused here by a real-time priority limit of 0 and, where the parent may drop
    it (root), no ``CAP_SYS_NICE`` in the bounding set (so none after exec). Measured with four
    SIH instances at speed factor 2 on two cores: see docs/benchmarks.md.

    ``nice`` > 0: add it to the niceness, and give the session's scheduling autogroup the
    same (Linux; where there is no autogroup file, or it cannot be written, the niceness alone
    applies)."""
    if not realtime:
        resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
        if _prctl is not None:
            # Fails with EPERM without CAP_SETPCAP, where CAP_SYS_NICE is not held anyway.
            _prctl(_PR_CAPBSET_DROP, _CAP_SYS_NICE, 0, 0, 0)
    if nice:
        os.nice(nice)
        with contextlib.suppress(OSError):
            Path("/proc/self/autogroup").write_text(f"{nice}\n")


class _Running:
    """A started instance: its process and what it has printed so far."""

    def __init__(self, instance: Px4Instance, process: asyncio.subprocess.Process) -> None:
        self.instance = instance
        self.process = process
        self.console = ""
        self._offset = 0

    def read_console(self) -> str:
        """Append what PX4 printed since the last call (a few kB during boot); return all."""
        try:
            with self.instance.log_path.open("rb") as stream:
                stream.seek(self._offset)
                chunk = stream.read()
        except OSError:
            return self.console
        self._offset += len(chunk)
        self.console = (self.console + chunk.decode("utf-8", errors="replace"))[-MAX_CONSOLE_CHARS:]
        return self.console

    def tail(self) -> str:
        lines = self.read_console().rstrip().splitlines()[-CONSOLE_TAIL_LINES:]
        return "\n".join(f"    {line}" for line in lines) or "    (nothing printed)"

    def name(self) -> str:
        return f"PX4 instance {self.instance.instance} (vehicle {self.instance.vehicle_id})"


class Px4SitlInstances:
    """PX4 SITL instances for a scenario's vehicles, as an async context manager that owns
    their processes: entering starts one per vehicle and returns once all are ready; leaving
    (or a failed start) stops every one it started.

    ::

        async with Px4SitlInstances(scenario, "/opt/px4/PX4-Autopilot", first_instance=6) as sitl:
            for instance in sitl.instances:
                ...  # instance.api_url, instance.sysid, ...

    Arguments are checked here, before anything starts: ids against instances (see
    :func:`check_instance_ids`), the build (:func:`px4_build_dir`), parameter names, the speed.
    ``work_dir`` holds a new run directory per entry (kept); without it a temporary directory
    is used and removed on exit. ``params`` override ``scenario.flight.autopilot_params``.
    """

    def __init__(
        self,
        scenario: Scenario,
        px4_dir: str | os.PathLike[str],
        *,
        first_instance: int = 0,
        speed_factor: float = 1.0,
        work_dir: str | os.PathLike[str] | None = None,
        home_lat_deg: float = DEFAULT_HOME_LAT_DEG,
        home_lon_deg: float = DEFAULT_HOME_LON_DEG,
        home_alt_m: float = DEFAULT_HOME_ALT_M,
        params: Mapping[str, float | int] | None = None,
        ready_timeout_s: float = 30.0,
        nice: int = DEFAULT_NICE,
        realtime: bool = False,
    ) -> None:
        check_instance_ids([vehicle.id for vehicle in scenario.vehicles], first_instance)
        if not 0 <= nice <= MAX_NICE:
            raise Px4SitlError(f"nice must be in 0..{MAX_NICE} (got {nice})")
        if not (math.isfinite(speed_factor) and speed_factor > 0):
            raise Px4SitlError(f"speed factor must be a positive number (got {speed_factor})")
        if not ready_timeout_s > 0:
            raise Px4SitlError(f"ready timeout must be > 0 s (got {ready_timeout_s})")
        self.scenario = scenario
        self.build_dir = px4_build_dir(px4_dir)
        self.first_instance = first_instance
        self.speed_factor = speed_factor
        self.params = merged_params(scenario, params)
        self.ready_timeout_s = ready_timeout_s
        self.nice = nice
        self.realtime = realtime
        self._work_dir = None if work_dir is None else Path(work_dir).expanduser()
        self._home = (home_lat_deg, home_lon_deg, home_alt_m)
        self._running: list[_Running] = []
        self._remove_run_dir = False
        self._entered = False
        # What entered instances own (their processes, a temporary run directory), unwound on exit.
        self._stack = contextlib.AsyncExitStack()
        self.run_dir: Path | None = None
        last = first_instance + len(scenario.vehicles) - 1
        if last > LAST_OWN_API_INSTANCE:
            logger.warning(
                "PX4 instances above %d (here up to %d) all send their API link to port %d: "
                "connect to those vehicles through udpin://0.0.0.0:%d, told apart by system id",
                LAST_OWN_API_INSTANCE,
                last,
                SHARED_API_PORT,
                SHARED_API_PORT,
            )

    @property
    def instances(self) -> list[Px4Instance]:
        """The started instances, in vehicle order (empty before entering; after leaving, as
        they ran)."""
        return [running.instance for running in self._running]

    def instance_of(self, vehicle_id: int) -> Px4Instance:
        """The instance flying vehicle ``vehicle_id``."""
        for instance in self.instances:
            if instance.vehicle_id == vehicle_id:
                return instance
        raise KeyError(vehicle_id)

    async def __aenter__(self) -> Px4SitlInstances:
        if self._entered:
            raise Px4SitlError("Px4SitlInstances starts its instances once: make a new one")
        self._entered = True
        async with contextlib.AsyncExitStack() as stack:
            self.run_dir = self._make_run_dir()
            stack.push_async_callback(self._remove_temporary_run_dir)
            # Stops every instance started from here on, also when a later one fails to start
            # or to get ready, or the start is cancelled.
            stack.push_async_callback(self._stop_all)
            lat_deg, lon_deg, alt_m = self._home
            planned = plan_instances(
                self.scenario,
                self.run_dir,
                first_instance=self.first_instance,
                home_lat_deg=lat_deg,
                home_lon_deg=lon_deg,
                home_alt_m=alt_m,
            )
            for instance in planned:
                await self._start(instance)
            await self._wait_ready()
            self._stack = stack.pop_all()
        return self

    async def __aexit__(self, *exc_info: Any) -> None:
        await self._stack.__aexit__(*exc_info)

    async def wait_for_exit(self) -> Px4Instance:
        """Return the first still running instance whose process ends (they are meant to run
        until stopped), with ``pid`` of the process that ended."""
        running = [r for r in self._running if r.process.returncode is None]
        if not running:
            raise Px4SitlError("no PX4 SITL instance is running")
        _, instance = await first_completed(
            {f"px4sitl-wait-{r.instance.instance}": self._exit_of(r) for r in running}
        )
        return instance

    @staticmethod
    async def _exit_of(running: _Running) -> Px4Instance:
        await running.process.wait()
        return running.instance

    def describe_exit(self, instance: Px4Instance) -> str:
        """How an instance ended, with the end of its console."""
        for running in self._running:
            if running.instance.instance == instance.instance:
                return (
                    f"{running.name()} exited with code {running.process.returncode}; "
                    f"the end of {instance.log_path}:\n{running.tail()}"
                )
        return f"PX4 instance {instance.instance} is not one of these"

    # -- start -------------------------------------------------------------------------------

    def _make_run_dir(self) -> Path:
        stamp = time.strftime("%Y%m%d-%H%M%S")
        prefix = f"{self.scenario.name}-px4sitl-{stamp}-"
        if self._work_dir is None:
            self._remove_run_dir = True
            return Path(tempfile.mkdtemp(prefix=prefix))
        self._work_dir.mkdir(parents=True, exist_ok=True)
        # A new directory per run: PX4 keeps parameters, dataman and battery state in its
        # working directory, and a reused one can refuse to arm.
        return Path(tempfile.mkdtemp(prefix=prefix, dir=self._work_dir))

    async def _start(self, instance: Px4Instance) -> None:
        busy = _ports_in_use(instance.local_ports)
        if busy:
            raise Px4SitlError(
                f"PX4 instance {instance.instance} (vehicle {instance.vehicle_id}) cannot start: "
                f"UDP port(s) {', '.join(busy)} in use (another PX4 SITL or emulator on instance "
                f"{instance.instance}?); stop it or choose other instances with --first-instance "
                "(and vehicle ids to match)"
            )
        instance.work_dir.mkdir(parents=True)
        environment = instance_environment(
            instance, speed_factor=self.speed_factor, params=self.params
        )
        binary = self.build_dir / "bin" / "px4"
        with instance.log_path.open("wb") as console:
            process = await asyncio.create_subprocess_exec(
                str(binary),
                "-i",
                str(instance.instance),
                "-d",
                str(self.build_dir / "etc"),
                cwd=instance.work_dir,
                env=environment,
                stdin=asyncio.subprocess.DEVNULL,
                stdout=console,
                stderr=asyncio.subprocess.STDOUT,
                # Own process group: the stop signal reaches PX4 and anything it spawned, and a
                # Ctrl-C in the terminal reaches only this process, which then stops PX4 in order.
                start_new_session=True,
                preexec_fn=functools.partial(instance_scheduling, self.nice, self.realtime),
            )
        started = dataclasses.replace(instance, pid=process.pid)
        self._running.append(_Running(started, process))
        logger.info(
            "started PX4 instance %d for vehicle %d (pid %d) in %s, home %.7f, %.7f "
            "(%.2f m from its initial position, PX4's float32 rounding)",
            started.instance,
            started.vehicle_id,
            process.pid,
            started.work_dir,
            started.home_lat_deg,
            started.home_lon_deg,
            started.placement_error_m,
        )

    async def _wait_ready(self) -> None:
        loop = asyncio.get_running_loop()
        started_s = loop.time()
        pending = list(self._running)
        try:
            async with asyncio.timeout(self.ready_timeout_s):
                while pending:
                    for running in list(pending):
                        console = running.read_console()
                        if READY_LINE in console:
                            pending.remove(running)
                            self._mark_ready(running, loop.time() - started_s)
                        elif running.process.returncode is not None:
                            raise Px4SitlError(
                                f"{running.name()} exited with code "
                                f"{running.process.returncode} during start-up; the end of "
                                f"{running.instance.log_path}:\n{running.tail()}"
                            )
                    if pending:
                        await asyncio.sleep(READY_POLL_S)
        except TimeoutError:
            names = ", ".join(running.name() for running in pending)
            details = "\n".join(
                f"  the end of {running.instance.log_path}:\n{running.tail()}"
                for running in pending
            )
            raise Px4SitlTimeoutError(
                f"{names} to print {READY_LINE!r}\n{details}", self.ready_timeout_s
            ) from None
        self._check_params()

    def _mark_ready(self, running: _Running, ready_after_s: float) -> None:
        running.instance = dataclasses.replace(running.instance, ready_after_s=ready_after_s)
        logger.info("%s ready after %.1f s", running.name(), ready_after_s)

    def _check_params(self) -> None:
        """PX4 reports a parameter it does not have and boots on: a typo in the scenario would
        otherwise pass unnoticed until the runner reads it back."""
        for running in self._running:
            unknown = sorted(set(UNKNOWN_PARAM.findall(running.console)) & set(self.params))
            if unknown:
                raise Px4SitlError(
                    f"PX4 has no parameter(s) {', '.join(unknown)} ({running.name()}, "
                    f"{running.instance.log_path}): fix flight.autopilot_params or params"
                )

    # -- stop --------------------------------------------------------------------------------

    async def _stop_all(self) -> None:
        running = [item for item in self._running if item.process.returncode is None]
        try:
            for item in running:
                _signal_group(item.process.pid, signal.SIGTERM)
            exited = await asyncio.gather(
                *(self._wait_exit(item, STOP_TIMEOUT_S) for item in running)
            )
            stubborn = [item for item, done in zip(running, exited, strict=True) if not done]
            for item in stubborn:
                logger.warning(
                    "%s still runs %.0f s after SIGTERM: SIGKILL", item.name(), STOP_TIMEOUT_S
                )
                _signal_group(item.process.pid, signal.SIGKILL)
            killed = await asyncio.gather(
                *(self._wait_exit(item, KILL_TIMEOUT_S) for item in stubborn)
            )
            for item, done in zip(stubborn, killed, strict=True):
                if not done:
                    logger.error("%s (pid %d) did not end", item.name(), item.process.pid)
        except BaseException:
            # Interrupted while stopping (a second Ctrl-C): never leave an autopilot behind.
            for item in running:
                if item.process.returncode is None:
                    _signal_group(item.process.pid, signal.SIGKILL)
            raise
        for item in running:
            # Anything PX4 left in its group (a start-up script's child) goes with it.
            _signal_group(item.process.pid, signal.SIGKILL)
            logger.info("%s stopped (exit code %s)", item.name(), item.process.returncode)

    @staticmethod
    async def _wait_exit(item: _Running, timeout_s: float) -> bool:
        try:
            async with asyncio.timeout(timeout_s):
                await item.process.wait()
        except TimeoutError:
            return False
        return True

    async def _remove_temporary_run_dir(self) -> None:
        if self._remove_run_dir and self.run_dir is not None:
            await asyncio.to_thread(shutil.rmtree, self.run_dir, ignore_errors=True)
            self._remove_run_dir = False


# --- Command ----------------------------------------------------------------------------------


async def run_px4_sitl_command(
    scenario: Scenario,
    px4_dir: str | os.PathLike[str],
    *,
    first_instance: int = 0,
    speed_factor: float = 1.0,
    work_dir: str | os.PathLike[str] | None = None,
    until: Awaitable[object],
    report: Callable[[str], None] = logger.info,
    ready_timeout_s: float = 30.0,
    nice: int = DEFAULT_NICE,
    realtime: bool = False,
) -> list[Px4Instance]:
    """Start PX4 SITL for ``scenario``, ``report`` the table of what runs where, and keep the
    instances running until ``until`` completes (e.g. a signal event's ``wait()``, which also
    cuts a start-up short); then stop them and return them as they ran (empty if stopped
    before ready). An instance that exits on its own is reported at once and the others fly
    on (a swarm loses one vehicle, not all); :class:`Px4SitlError` is raised in the end, or as
    soon as none is left."""
    ran: list[Px4Instance] = []
    died: list[str] = []

    async def serve() -> None:
        sitl = Px4SitlInstances(
            scenario,
            px4_dir,
            first_instance=first_instance,
            speed_factor=speed_factor,
            work_dir=work_dir,
            ready_timeout_s=ready_timeout_s,
            nice=nice,
            realtime=realtime,
        )
        async with sitl:
            ran.extend(sitl.instances)
            report(
                f"PX4 SITL for scenario {scenario.name}: {len(ran)} instance(s), "
                f"speed factor {speed_factor:g}, in {sitl.run_dir}\n{instances_table(ran)}"
            )
            while len(died) < len(ran):
                # Described at once: a temporary run directory goes with the instances.
                died.append(sitl.describe_exit(await sitl.wait_for_exit()))
                report(f"error: {died[-1]}")
            raise Px4SitlError("every PX4 SITL instance exited")

    async def stop() -> None:
        await until
        report("stopping PX4 SITL" if ran else "stopped before PX4 SITL was ready")

    # Whichever ends first cancels the other: a stop cancels the start or the watch (leaving
    # the instances stops them); the last instance exiting ends the run.
    await first_completed({"px4sitl-run": serve(), "px4sitl-until": stop()})
    if died:
        raise Px4SitlError("\n".join(died))
    return ran


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``px4-sitl`` command's arguments (module docstring) and ``handler=command``."""
    default_px4_dir = os.environ.get("PX4_SITL_DIR")
    parser.add_argument("config", type=Path, help="scenario YAML file")
    parser.add_argument(
        "--px4-dir",
        type=Path,
        default=Path(default_px4_dir) if default_px4_dir else None,
        required=not default_px4_dir,
        help="PX4-Autopilot checkout built with `make px4_sitl_default`, or its "
        "build/px4_sitl_default (default: $PX4_SITL_DIR)",
    )
    parser.add_argument(
        "--first-instance",
        type=argtypes.non_negative_int,
        default=0,
        help="PX4 instance of the first vehicle; vehicle ids must be instance + 1 (default 0)",
    )
    parser.add_argument(
        "--speed",
        type=argtypes.at_most(argtypes.positive_float, MAX_CLOCK_SPEED),
        default=1.0,
        help="simulation speed factor (default 1)",
    )
    parser.add_argument(
        "--nice",
        type=_niceness,
        default=DEFAULT_NICE,
        help=f"lower the instances' CPU priority by this, 0-{MAX_NICE} (default {DEFAULT_NICE}): "
        "where cores are short, the simulation slows (the mission clock follows it) rather "
        "than the mission's own processes missing their deadlines",
    )
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="let PX4 run its threads real-time (SCHED_FIFO) where it may, as root: they then "
        "preempt the mission's own processes on the same machine (default: normal threads)",
    )
    parser.add_argument(
        "--work-dir",
        type=Path,
        default=None,
        help="keep the instances' working directories (console, .ulg logs) here "
        "(default: a temporary directory, removed at the end)",
    )
    parser.set_defaults(handler=command)


def _niceness(text: str) -> int:
    value = argtypes.non_negative_int(text)
    if value > MAX_NICE:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_NICE}, got {value}")
    return value


def _write_stdout(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


async def _run_until_signal(arguments: argparse.Namespace, scenario: Scenario) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for signal_number in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signal_number, stop.set)
    try:
        await run_px4_sitl_command(
            scenario,
            arguments.px4_dir,
            first_instance=arguments.first_instance,
            speed_factor=arguments.speed,
            work_dir=arguments.work_dir,
            nice=arguments.nice,
            realtime=arguments.realtime,
            until=stop.wait(),
            report=_write_stdout,
        )
    finally:
        for signal_number in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(signal_number)


def command(arguments: argparse.Namespace) -> int:
    """``mission-runner px4-sitl``: run the instances until SIGINT/SIGTERM; 0 when stopped so."""
    from .checks import load_scenario  # noqa: PLC0415 - `px4-sitl --help` without the model

    scenario = load_scenario(arguments.config, flying=True)
    asyncio.run(_run_until_signal(arguments, scenario))
    return 0

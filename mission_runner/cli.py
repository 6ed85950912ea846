"""``mission-runner``: the command line.

    mission-runner simulate CONFIG [--out DIR] [--runs N] [--no-figures] [--replay] [--quiet]
    mission-runner sweep CONFIG --set PATH=V1,V2 [--set ...] [--runs N] [--metric NAME]
    mission-runner run CONFIG [--out DIR] [--realtime [--speed F]] [--no-figures] [--replay]
    mission-runner replay OUT_DIR [--every N] [--fps F] [--width PX] [--gif FILE]  animate a run
    mission-runner schema [--out FILE]                   the scenario's JSON Schema
    mission-runner view CONFIG [--port N]                a running mission's bus, live in Foxglove
    mission-runner layout CONFIG [--out FILE]            a Foxglove layout for the scenario's topics
    mission-runner vehicle CONFIG --id N [--url URL] [--out DIR]   one vehicle's controller (MQTT)
    mission-runner ground CONFIG [--start-delay S]       prepare, start and watch vehicle processes
    mission-runner ranges CONFIG [--source sih|gps]      synthesised UWB ranges (simulation aid)
    mission-runner px4-sitl CONFIG --px4-dir DIR         real PX4 SITL (SIH), one per vehicle
    mission-runner emulate CONFIG [sitl options]         emulated vehicles + the scenario's world
    mission-runner control CONFIG hold|resume|land|return|stop [--vehicle N]   operator command
    mission-runner broker-config CONFIG --out DIR        mosquitto config, per-role logins, ACL

Every command that talks on the bus takes ``--bus-key-file FILE`` (the mission's message key;
else ``MISSION_BUS_KEY``, else ``bus.auth.key_file``), ``--bus-credentials FILE`` (broker
logins) and ``--insecure-bus`` (an MQTT bus without a key: closed bench networks only).

Exit codes:

- 0: success (and every ``expect:`` bound met);
- 1: an ``expect:`` bound failed;
- 2: bad input, before any work: the scenario (the message names the YAML path), an option
  (``--speed 0``), ``--out`` (a file, not writable), a batch too large for memory;
- 3: a runtime failure: a vehicle refused, was lost or the mission was aborted, a port is taken
  (the message names the setting that moves it), results could not be written; also an
  unexpected error (its traceback is printed, to be reported);
- 130: interrupted by SIGINT (Ctrl-C), 143: by SIGTERM (the last one received). Both stop the
  same way: a flight lands first (``run``: every vehicle in the air; ``ground``: land sent to
  every vehicle), and ``summary.json`` is written with ``status: interrupted``. A second signal
  stops at once, without waiting for the landing: the vehicles are left to PX4's offboard-loss
  failsafe.

``--out``: a run first removes the earlier run's own files from the folder (summary.json,
timeseries.csv, batch.csv, the figures, tlogs/vehicle_*.tlog: ``outputs.RUN_FILES``), so results
of two runs never mix; any other file there is left alone. ``summary.json`` always says how the run
ended (``status``: running, passed, failed, interrupted or error).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Coroutine, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, ParamSpec, TypeVar

from . import argtypes
from .bus.cli_options import add_bus_arguments, with_bus_access
from .bus.errors import BusConnectionError, BusTimeoutError
from .checks import MAX_MAVLINK_ID, load_scenario
from .config import MAX_CLOCK_SPEED, MAX_NOISE_STD_M, MAX_WAIT_S
from .errors import ConfigError, MissionRunnerError, leaf_errors
from .recording import LogCapture
from .runner.errors import RunnerError

if TYPE_CHECKING:
    from tqdm import tqdm

    from .bus import VehicleStatus
    from .config import Scenario
    from .live import LiveServer
    from .outputs import RunSummary
    from .records import Progress, StepRecord
    from .replay import ReplayFiles
    from .runner.operator import OperatorConsole

P = ParamSpec("P")
T = TypeVar("T")

#: A subcommand: parsed arguments in, exit code out.
Handler = Callable[[argparse.Namespace], int]

EXIT_OK, EXIT_EXPECTATION_FAILED, EXIT_BAD_INPUT, EXIT_RUNTIME_FAILURE = 0, 1, 2, 3
#: The fastest MAVLink stream an option asks of an autopilot [Hz]: PX4's own loops run at 250 Hz
#: to 1 kHz; a faster stream would only flood the link.
MAX_STREAM_HZ = 1000.0
#: 128 + the signal's number, as a shell reports a process that signal ended.
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser(_command_named(sys.argv[1:] if argv is None else argv))
    arguments = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING if getattr(arguments, "quiet", False) else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    _signals.received = "SIGINT"
    try:
        with _terminate_as_interrupt():
            return _unwrapped(arguments.handler, arguments)
    except (RunnerError, BusConnectionError, BusTimeoutError) as error:  # link, broker, vehicle
        print(f"error: {error}", file=sys.stderr)
        return EXIT_RUNTIME_FAILURE
    except _emulator_errors() as error:  # e.g. a port already taken: one line naming the setting
        print(f"error: {error}", file=sys.stderr)
        return EXIT_RUNTIME_FAILURE
    except MissionRunnerError as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"interrupted ({_signals.received})", file=sys.stderr)
        return EXIT_TERMINATED if _signals.received == "SIGTERM" else EXIT_INTERRUPTED
    except OSError as error:  # e.g. the disk filled up while writing results
        print(f"error: {error}", file=sys.stderr)
        return EXIT_RUNTIME_FAILURE
    except Exception:  # a bug: its traceback, but not exit code 1, which means "failed"
        logging.getLogger(__name__).exception("unexpected error; please report it")
        return EXIT_RUNTIME_FAILURE


class _StopSignals:
    """Process-wide, as signal handlers are: which stop signal arrived last, and how to stop
    the asyncio main task that runs (see :func:`_run_async`)."""

    def __init__(self) -> None:
        self.received = "SIGINT"
        #: Called (in the signal handler) with the signal's name while an asyncio main runs.
        self.cancel_main: Callable[[str], None] | None = None


_signals = _StopSignals()


@dataclass(frozen=True)
class _Stopping:
    """What a command says when a stop signal arrives (``{signal}``: its name): the first
    cancels its main task (where a flight lands), ``again`` cancels it a second time (the
    landing is not waited for)."""

    first: str = ""
    again: str = "{signal} again: stopping at once"


#: ``run`` lands its swarm on the first stop signal; on a second the process ends, and so does
#: the emulator in it.
_RUN_STOPPING = _Stopping(
    "run: {signal}: landing every vehicle ({signal} again: stop at once)",
    "run: {signal} again: stopping at once, vehicles left to PX4's offboard-loss failsafe "
    "(the emulated ones end with this process)",
)
#: ``ground`` sends land on the first; a second does not wait for the send: vehicle processes
#: that did not get it fly on, and PX4's offboard-loss failsafe takes any whose process ends.
_GROUND_STOPPING = _Stopping(
    "ground: {signal}: telling every vehicle to land ({signal} again: stop at once)",
    "ground: {signal} again: stopping at once; a vehicle that did not get the land flies on "
    "under its own process, PX4's offboard-loss failsafe takes it if that process stops",
)


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM stops a command as Ctrl-C does: a KeyboardInterrupt, or inside :func:`_run_async`
    the cancellation of its main task first (a flight lands), noted so that the exit code tells
    the two signals apart."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be set (and only run) in the main thread
        return

    def on_terminate(number: int, frame: FrameType | None) -> None:
        _signals.received = "SIGTERM"
        if _signals.cancel_main is not None:
            _signals.cancel_main("SIGTERM")
        else:
            raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def _run_async(coroutine: Coroutine[Any, Any, T], stopping: _Stopping = _Stopping()) -> T:
    """``asyncio.run(coroutine)``; SIGINT and SIGTERM cancel its main task (so a flight lands),
    then raise KeyboardInterrupt. A second signal cancels it again, which ends the landing
    too, never raising inside the event loop (as asyncio's own second Ctrl-C would). SIGTERM
    also where SIGINT is ignored, as in a background job (SIGINT then stays ignored).
    ``stopping`` says what each signal does, on stderr."""
    import asyncio  # noqa: PLC0415 - simulate does without

    stops = 0
    # The result stays out of the main task: asyncio's Runner formats that task (its result
    # included) while restoring SIGINT's handler, a full repr of a flight's arrays (~2 s).
    outcome: list[T] = []

    async def main() -> None:
        task, loop = asyncio.current_task(), asyncio.get_running_loop()

        def say(text: str) -> None:
            print(text, file=sys.stderr, flush=True)

        def cancel(name: str) -> None:  # may be in a signal handler: only hand work to the loop
            nonlocal stops
            stops += 1
            _signals.received = name
            message = stopping.first if stops == 1 else stopping.again
            if message:
                loop.call_soon_threadsafe(say, message.format(signal=name))
            if task is not None:
                loop.call_soon_threadsafe(task.cancel)  # wakes the loop, as asyncio's handler

        # Through the loop: it makes the signal wake it (its wakeup descriptor) whichever thread
        # the kernel hands the signal to. A plain signal.signal handler runs only when the main
        # thread next runs Python, and a loop asleep in epoll for the hour of a landing may not:
        # the process has other threads (numpy's BLAS workers), and one of them may get it.
        handled: list[tuple[signal.Signals, Any]] = []
        if threading.current_thread() is threading.main_thread():
            for number, name in ((signal.SIGINT, "SIGINT"), (signal.SIGTERM, "SIGTERM")):
                previous = signal.getsignal(number)
                if number == signal.SIGINT and previous is signal.SIG_IGN:
                    continue  # a background job's: stays ignored
                loop.add_signal_handler(number, cancel, name)
                handled.append((number, previous))
        _signals.cancel_main = cancel
        try:
            outcome.append(await coroutine)
        finally:
            _signals.cancel_main = None
            for number, previous in handled:
                loop.remove_signal_handler(number)
                signal.signal(number, previous if previous is not None else signal.SIG_DFL)

    try:
        asyncio.run(main())
    except BaseException as error:
        if not stops:
            raise
        if not isinstance(error, asyncio.CancelledError):  # what went wrong while stopping
            logging.getLogger(__name__).warning("while stopping: %r", error)
        raise KeyboardInterrupt from None
    if stops:  # the coroutine ended on its own terms, but the user asked it to stop
        raise KeyboardInterrupt
    return outcome[0]


def _emulator_errors() -> tuple[type[Exception], ...]:
    """The bundled emulator's error base (a separate package: absent errors match nothing)."""
    try:
        from sitl.errors import SitlError  # noqa: PLC0415
    except ImportError:
        return ()
    return (SitlError,)


def _unwrapped(handler: Handler, arguments: argparse.Namespace) -> int:
    """Run ``handler``; an exception group (a task group's failure) is re-raised as its first
    error of ours, so the user reads one line, not a tree of tracebacks."""
    try:
        return handler(arguments)
    except BaseExceptionGroup as group:
        for leaf in leaf_errors(group):
            if isinstance(leaf, (MissionRunnerError, KeyboardInterrupt, *_emulator_errors())):
                raise leaf from group
        raise


def _command_named(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), if any."""
    return next((word for word in argv if not word.startswith("-")), None)


def _parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line; ``emulate``'s and ``px4-sitl``'s options only when ``command`` is one of
    them (or None: every command in full), as they import the emulator and the PX4 launcher,
    half a second of every other command's start on a companion computer's budget."""
    parser = argparse.ArgumentParser(
        prog="mission-runner",
        description="Multi-drone moving-target enclosing: simulate or fly a scenario.",
    )
    commands = parser.add_subparsers(required=True, metavar="COMMAND")

    simulate = commands.add_parser(
        "simulate", help="run a scenario in the paper's discrete-time model"
    )
    simulate.add_argument("config", type=Path, help="scenario YAML file")
    simulate.add_argument(
        "--out", type=Path, default=None, help="output folder (default: out/<scenario name>)"
    )
    simulate.add_argument(
        "--runs",
        type=argtypes.positive_int,
        default=1,
        help="batch of N initial conditions (default 1)",
    )
    simulate.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    simulate.add_argument("--quiet", action="store_true", help="no progress bar, no summary")
    _replay_flag(simulate)
    simulate.set_defaults(handler=_simulate)

    sweeper = commands.add_parser(
        "sweep",
        help="simulate every combination of parameter values (batched) and compare metrics",
    )
    sweeper.add_argument("config", type=Path, help="scenario YAML file")
    sweeper.add_argument(
        "--set",
        dest="axes",
        action="append",
        required=True,
        metavar="PATH=V1,V2",
        type=_axis,
        help="a YAML path and its values, e.g. algorithm.forgetting_factor=0.7,0.98 or "
        "vehicles[*].speed_limit_m_s=10,12 (repeat for a grid)",
    )
    sweeper.add_argument("--runs", type=argtypes.positive_int, default=100, help="runs per point")
    sweeper.add_argument(
        "--metric",
        default="tail_tracking_error_rms_m",
        help="metric of the figure (default tail_tracking_error_rms_m; sweep.csv has them all)",
    )
    sweeper.add_argument(
        "--out", type=Path, default=None, help="output folder (default: out/<name>-sweep)"
    )
    sweeper.add_argument("--no-figures", action="store_true", help="skip sweep.png")
    sweeper.add_argument("--quiet", action="store_true", help="no progress, no table")
    sweeper.set_defaults(handler=_sweep)

    run = commands.add_parser(
        "run", help="fly a scenario: emulated PX4 vehicles through MAVSDK, in lockstep by default"
    )
    run.add_argument("config", type=Path, help="scenario YAML file")
    run.add_argument(
        "--out", type=Path, default=None, help="output folder (default: out/<scenario name>-run)"
    )
    run.add_argument(
        "--realtime", action="store_true", help="real-time clock instead of the scenario's"
    )
    run.add_argument(
        "--speed",
        type=argtypes.at_most(argtypes.positive_float, MAX_CLOCK_SPEED),
        default=None,
        help=f"real-time speed factor (> 0, <= {MAX_CLOCK_SPEED:g})",
    )
    run.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    run.add_argument("--quiet", action="store_true", help="no progress view, no summary")
    _replay_flag(run)
    _live_flags(run)
    add_bus_arguments(run)
    run.set_defaults(handler=_run)

    replay = commands.add_parser(
        "replay",
        help="animate a run (simulate, run or ground output folder) from its recording.mcap: "
        "replay.gif, and replay.mp4 where ffmpeg is on the PATH",
    )
    replay.add_argument("out_dir", type=Path, help="the run's output folder")
    replay.add_argument(
        "--every", type=argtypes.positive_int, default=1, help="one frame every N steps (default 1)"
    )
    replay.add_argument(
        "--fps",
        type=argtypes.at_most(argtypes.positive_float, 100.0),  # GIF frames last >= 10 ms
        default=20.0,
        help="frames per second (default 20, at most 100)",
    )
    replay.add_argument(
        "--width",
        type=argtypes.at_most(argtypes.positive_int, 7680),  # 8K: every frame is held in memory
        default=800,
        help="frame width in pixels (default 800, at most 7680)",
    )
    replay.add_argument(
        "--trail",
        type=argtypes.positive_int,
        default=None,
        help="trail length in steps (default: all)",
    )
    replay.add_argument(
        "--gif", type=Path, default=None, help="where the GIF goes (default OUT_DIR/replay.gif)"
    )
    replay.add_argument("--no-mp4", action="store_true", help="no MP4 even if ffmpeg is there")
    replay.set_defaults(handler=_replay)

    vehicle = commands.add_parser(
        "vehicle", help="one vehicle's controller as its own process (talks over MQTT only)"
    )
    vehicle.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    vehicle.add_argument(
        "--id",
        type=argtypes.at_most(argtypes.positive_int, MAX_MAVLINK_ID),
        required=True,
        help="this vehicle's id (its MAVLink system id, 1..255)",
    )
    vehicle.add_argument(
        "--url", help="MAVSDK connection URL (default: the scenario's, else PX4 SITL's)"
    )
    vehicle.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default: out/<name>-mission/vehicle_<id>)",
    )
    add_bus_arguments(vehicle)
    vehicle.set_defaults(handler=_vehicle)

    ground = commands.add_parser(
        "ground", help="ground station for vehicle processes: start the mission, show progress"
    )
    ground.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    ground.add_argument(
        "--start-delay",
        type=argtypes.at_most(argtypes.non_negative_float, MAX_WAIT_S),
        default=2.0,
        help="seconds from ready to k = 0",
    )
    ground.add_argument(
        "--out",
        type=Path,
        default=None,
        help="mission folder where the vehicles and the range aid write (default: "
        "out/<name>-mission): the ground station merges them into summary.json and figures",
    )
    ground.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    _live_flags(ground)
    add_bus_arguments(ground)
    ground.set_defaults(handler=_ground)

    view = commands.add_parser(
        "view",
        help="serve a running mission's bus (vehicle processes over MQTT) to Foxglove over its "
        "WebSocket protocol, until Ctrl-C",
    )
    view.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    view.add_argument("--host", default="127.0.0.1", help="address to serve on")
    view.add_argument(
        "--port", type=argtypes.port_or_zero, default=8765, help="port (0: any free one)"
    )
    add_bus_arguments(view)
    view.set_defaults(handler=_view)

    layout = commands.add_parser(
        "layout", help="print a Foxglove layout for the scenario's recording and live view"
    )
    layout.add_argument("config", type=Path, help="scenario YAML file (for its vehicle ids)")
    layout.add_argument("--out", type=Path, default=None, help="write it there instead")
    layout.set_defaults(handler=_layout)

    ranges = commands.add_parser(
        "ranges",
        help="SIMULATION AID: publish UWB-like ranges synthesised from a simulator's ground "
        "truth (--source sih) or the vehicles' GPS (--source gps) for vehicles without UWB",
    )
    ranges.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    ranges.add_argument(
        "--source",
        choices=("sih", "gps"),
        default="sih",
        help="sih: HIL_STATE_QUATERNION ground truth (PX4 SIH, or the emulator's truth stream) "
        "on UDP <truth-port-base> + id - 1; gps: GLOBAL_POSITION_INT through MAVSDK (--url)",
    )
    ranges.add_argument(
        "--truth-port-base",
        type=argtypes.port,
        default=19410,
        help="UDP port of vehicle id 1's truth",
    )
    ranges.add_argument(
        "--truth-rate",
        type=argtypes.at_most(argtypes.non_negative_float, MAX_STREAM_HZ),
        default=None,
        help="with --source sih: ground-truth rate to ask of each instance, Hz (PX4 SIH streams "
        "25; at least the --vision rate; 0: leave it; default 50)",
    )
    ranges.add_argument(
        "--vision",
        type=argtypes.at_most(argtypes.non_negative_float, MAX_STREAM_HZ),
        default=0.0,
        metavar="HZ",
        help="with --source sih: also send each instance a vision odometry (ODOMETRY, VIO, local "
        "NED) made from its truth at this rate, for EKF2 to fuse (EKF2_EV_CTRL); 0: none "
        "(default)",
    )
    ranges.add_argument(
        "--vision-noise",
        type=argtypes.at_most(argtypes.non_negative_float, MAX_NOISE_STD_M),
        nargs=2,
        default=(0.02, 0.05),
        metavar=("POSITION_M", "VELOCITY_M_S"),
        help="white noise (std) of the vision odometry's position and velocity (0.02 0.05)",
    )
    ranges.add_argument(
        "--url",
        action="append",
        default=None,
        help="with --source gps: MAVSDK URL(s) where every vehicle is heard, e.g. a GCS link "
        "udpin://0.0.0.0:14550",
    )
    ranges.add_argument(
        "--out",
        type=Path,
        default=None,
        help="where the truth at every t_k is written, for scoring only "
        "(default: out/<name>-mission/truth)",
    )
    add_bus_arguments(ranges)
    ranges.set_defaults(handler=_ranges)

    schema = commands.add_parser(
        "schema",
        help="print the scenario file's JSON Schema (for an editor's YAML language server)",
    )
    schema.add_argument("--out", type=Path, default=None, help="write it there instead")
    schema.set_defaults(handler=_schema)

    operate = commands.add_parser(
        "control",
        help="operator command to the running mission of vehicle processes: hold, resume, land, "
        "return or stop, for every vehicle or one",
    )
    operate.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    from .runner.operator import OPERATOR_COMMANDS  # noqa: PLC0415 - one vocabulary

    operate.add_argument("command", choices=[command.value for command in OPERATOR_COMMANDS])
    operate.add_argument(
        "--vehicle", type=argtypes.positive_int, default=None, help="one vehicle's id"
    )
    operate.add_argument("--reason", default=None, help="a note the vehicles log and report")
    add_bus_arguments(operate)
    operate.set_defaults(handler=_control)

    broker = commands.add_parser(
        "broker-config",
        help="write a mosquitto configuration for the scenario's mission: listener, optional "
        "TLS, one login per role (random passwords, 0600 credentials file), an ACL (each "
        "vehicle publishes only its own topics, only the ground station commands) and a bus key",
    )
    broker.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    broker.add_argument("--out", type=Path, required=True, help="folder to write the files in")
    broker.add_argument(
        "--port", type=argtypes.port, default=None, help="listener port (default: bus.mqtt.port)"
    )
    broker.add_argument("--bind", default=None, help="listen on this address only")
    broker.add_argument("--tls-cert", type=Path, default=None, help="broker certificate (PEM)")
    broker.add_argument("--tls-key", type=Path, default=None, help="its private key (PEM)")
    broker.add_argument(
        "--tls-ca", type=Path, default=None, help="CA file, for clients with certificates"
    )
    broker.add_argument(
        "--no-bus-key", action="store_true", help="keep the mission's existing bus key"
    )
    broker.set_defaults(handler=_broker_config)

    emulate = commands.add_parser(
        "emulate",
        help="emulated PX4 vehicles with the scenario's target and UWB ranging on its bus, for "
        "vehicle processes (what 'sitl --scenario' did)",
    )
    if command in (None, "emulate"):
        from . import emulate as emulated  # noqa: PLC0415 - the emulator, for this command only

        emulated.add_arguments(emulate)
        add_bus_arguments(emulate)

    px4 = commands.add_parser(
        "px4-sitl",
        help="start real PX4 SITL (SIH), one instance per vehicle of the scenario, until Ctrl-C",
    )
    if command in (None, "px4-sitl"):
        from . import px4sitl  # noqa: PLC0415 - the PX4 launcher, for this command only

        px4sitl.add_arguments(px4)
    return parser


def _axis(text: str) -> Any:
    import yaml  # noqa: PLC0415 - fast `--help`

    from .sim.sweep import Axis  # noqa: PLC0415

    try:
        return Axis.parse(text)
    except (ValueError, yaml.YAMLError) as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _schema(arguments: argparse.Namespace) -> int:
    from .config import scenario_json_schema  # noqa: PLC0415

    return _print_json(scenario_json_schema(), arguments.out)


def _layout(arguments: argparse.Namespace) -> int:
    import json  # noqa: PLC0415

    from .layout import foxglove_layout  # noqa: PLC0415

    scenario = load_scenario(arguments.config)
    layout = foxglove_layout([vehicle.id for vehicle in scenario.vehicles])
    return _print_json(json.loads(layout.to_json()), arguments.out)


def _print_json(document: object, out: Path | None) -> int:
    """``document`` as indented JSON on stdout, or written to ``out``."""
    import json  # noqa: PLC0415

    text = json.dumps(document, indent=2) + "\n"
    if out is None:
        sys.stdout.write(text)
    else:
        from .paths import write_atomic  # noqa: PLC0415

        write_atomic(out, text)
    return EXIT_OK


def _live_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--live",
        action="store_true",
        help="serve the mission to Foxglove over its WebSocket protocol while it flies",
    )
    parser.add_argument("--live-host", default="127.0.0.1", help="address to serve on")
    parser.add_argument(
        "--live-port", type=argtypes.port_or_zero, default=8765, help="port (0: any free one)"
    )


def _live_server(arguments: argparse.Namespace, scenario: Scenario) -> LiveServer | None:
    """The ``--live`` server, not yet started (None without ``--live``)."""
    if not getattr(arguments, "live", False):
        return None
    from .live import LiveServer  # noqa: PLC0415

    return LiveServer(scenario, host=arguments.live_host, port=arguments.live_port)


def _every(callbacks: Sequence[Callable[P, None]]) -> Callable[P, None]:
    """One callback calling each of ``callbacks`` in turn."""

    def call(*args: P.args, **kwargs: P.kwargs) -> None:
        for callback in callbacks:
            callback(*args, **kwargs)

    return call


def _view(arguments: argparse.Namespace) -> int:
    from .live import LiveLog, LiveServer, serve_bus  # noqa: PLC0415

    scenario = with_bus_access(load_scenario(arguments.config), arguments)
    if scenario.bus.kind != "mqtt":
        raise ConfigError(
            str(arguments.config),
            [
                (
                    "bus.kind",
                    "view watches a mission's MQTT bus: set mqtt (an in-process mission is "
                    "watched with 'mission-runner run --live')",
                )
            ],
        )
    with LiveServer(scenario, host=arguments.host, port=arguments.port) as server:
        print(f"view: {server.url} (Foxglove: Open connection); Ctrl-C to stop", flush=True)
        live_log = LiveLog(server.channels)
        with live_log.attached():
            _run_async(
                serve_bus(
                    scenario,
                    server.channels,
                    client_id=f"{scenario.name}-view",
                    on_time=live_log.stamp,
                )
            )
    return EXIT_OK


def _replay_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--replay",
        action="store_true",
        help="also animate the run: replay.gif (and replay.mp4 where ffmpeg is on the PATH)",
    )


def _replay(arguments: argparse.Namespace) -> int:
    from .replay import write_replay  # noqa: PLC0415 - matplotlib is slow to import

    files = write_replay(
        arguments.out_dir,
        gif=arguments.gif,
        every=arguments.every,
        fps=arguments.fps,
        width_px=arguments.width,
        trail_steps=arguments.trail,
        mp4=not arguments.no_mp4,
    )
    print(_replay_text(files))
    return EXIT_OK


def _replay_text(files: ReplayFiles) -> str:
    width, height = files.size_px
    written = f"{files.gif}" + (f" and {files.mp4}" if files.mp4 else " (no ffmpeg: no MP4)")
    return (
        f"replay: {files.frames} frames of {width}x{height} px in {files.render_s:.1f} s: {written}"
    )


def _simulate(arguments: argparse.Namespace) -> int:
    from .outputs import RUN_FILES, RunSummary, prepare_out_dir  # noqa: PLC0415 - fast `--help`
    from .sim.simulator import check_memory, simulate  # noqa: PLC0415

    scenario = load_scenario(arguments.config)
    check_memory(scenario, arguments.runs, str(arguments.config))
    out_dir = prepare_out_dir(arguments.out or Path("out") / scenario.name, RUN_FILES)
    progress = _progress(scenario.timing.steps, arguments.quiet, f"{scenario.name}")
    capture = LogCapture()
    with (
        RunSummary(out_dir, scenario, config_path=arguments.config, runs=arguments.runs) as record,
        capture.attached(),
    ):

        def on_step(done: int, total: int) -> None:
            record.steps_done = done
            capture.stamp(done * scenario.timing.step_s)
            progress.update_to(done, total)

        started = time.perf_counter()
        try:
            result = simulate(scenario, runs=arguments.runs, on_step=on_step)
        finally:
            progress.close()
        document = record.write_results(
            result,
            wall_time_s=time.perf_counter() - started,
            figures=not arguments.no_figures,
            logs=capture.lines,
        )
    if not arguments.quiet:
        print(_summary_text(document, out_dir))
        print(_ranging_text(scenario))
    _maybe_replay(arguments, out_dir)
    return EXIT_OK if document["expectations"]["passed"] else EXIT_EXPECTATION_FAILED


def _ranging_text(scenario: Scenario) -> str:
    """Which ranges a step of the scenario has (its UWB scheme and airtime)."""
    from .sensors import ranging_plan  # noqa: PLC0415 - fast `--help`

    return ranging_plan(len(scenario.vehicles), scenario.sensors, scenario.timing.step_s)


def _maybe_replay(arguments: argparse.Namespace, out_dir: Path) -> None:
    """``--replay``: animate what was just written."""
    if arguments.replay:
        from .replay import write_replay  # noqa: PLC0415

        files = write_replay(out_dir)
        if not arguments.quiet:
            print(_replay_text(files))


def _sweep(arguments: argparse.Namespace) -> int:
    import numpy as np  # noqa: PLC0415 - fast `--help`

    from .config import METRICS  # noqa: PLC0415
    from .outputs import prepare_out_dir, write_atomic  # noqa: PLC0415
    from .sim.sweep import sweep, sweep_csv  # noqa: PLC0415

    if arguments.metric not in METRICS:
        print(f"error: --metric must be one of {', '.join(METRICS)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    scenario = load_scenario(arguments.config)
    out_dir = prepare_out_dir(
        arguments.out or Path("out") / f"{scenario.name}-sweep", ("sweep.csv", "sweep.png")
    )
    total = math.prod(len(axis.values) for axis in arguments.axes)
    progress = _progress(total, arguments.quiet, f"{scenario.name} sweep")
    try:
        points = sweep(
            scenario,
            arguments.axes,
            arguments.runs,
            source=str(arguments.config),
            on_point=progress.update_to,
        )
    finally:
        progress.close()
    write_atomic(out_dir / "sweep.csv", sweep_csv(points))
    if not arguments.no_figures:
        from .figures import write_sweep_figure  # noqa: PLC0415 - matplotlib is slow to import

        write_sweep_figure(points, arguments.metric, out_dir / "sweep.png")
    if not arguments.quiet:
        print(f"{arguments.metric}: median [p5, p95] over {arguments.runs} runs")
        for point in points:
            values = np.asarray(point.metrics[arguments.metric], dtype=float)
            low, median, high = np.percentile(values, [5, 50, 95])
            label = ", ".join(f"{path}={value}" for path, value in point.values.items())
            print(f"  {label}: {median:.4g} [{low:.4g}, {high:.4g}]")
        print(f"results in {out_dir}/ (sweep.csv{'' if arguments.no_figures else ', sweep.png'})")
    return EXIT_OK


def _run(arguments: argparse.Namespace) -> int:
    from .checks import validate_scenario  # noqa: PLC0415
    from .figure_process import FigureProcess  # noqa: PLC0415
    from .outputs import RUN_FILES, RunSummary, prepare_out_dir  # noqa: PLC0415
    from .runner.mission import fly  # noqa: PLC0415
    from .sim.simulator import check_memory  # noqa: PLC0415

    scenario = load_scenario(arguments.config, flying=True)
    if arguments.realtime or arguments.speed is not None:
        data = scenario.model_dump(mode="json")
        data["flight"]["clock"] = "realtime"
        data["flight"]["speed"] = 1.0 if arguments.speed is None else arguments.speed
        scenario = validate_scenario(data, str(arguments.config))
    scenario = with_bus_access(scenario, arguments)
    check_memory(scenario, 1, str(arguments.config))  # the flight's scored result
    out_dir = prepare_out_dir(arguments.out or Path("out") / f"{scenario.name}-run", RUN_FILES)
    tlogs = out_dir / "tlogs"
    tlogs.mkdir(exist_ok=True)
    view = None if arguments.quiet else _FlightView(scenario)
    capture = LogCapture()
    with (
        FigureProcess() as figure_process,
        RunSummary(out_dir, scenario, config_path=arguments.config) as record,
    ):
        last_step = scenario.timing.steps - 1

        def on_step(vehicle_id: int, step: StepRecord) -> None:
            record.steps_done = max(record.steps_done, step.step + 1)
            capture.stamp(step.time_s)
            if step.step == last_step and not arguments.no_figures:
                # matplotlib's import while the vehicles land (paced: the CPU has time then)
                figure_process.start()

        step_callbacks: list[Callable[[int, StepRecord], None]] = [on_step]
        progress_callbacks: list[Callable[[Progress], None]] = [view] if view is not None else []
        with contextlib.ExitStack() as stack:
            stack.enter_context(capture.attached())
            server = _live_server(arguments, scenario)
            if server is not None:
                from .live import FlightFeed, LiveLog  # noqa: PLC0415

                stack.enter_context(server)
                print(f"live: {server.url} (Foxglove: Open connection)", flush=True)
                feed = FlightFeed(scenario, server.channels)
                live_log = stack.enter_context(LiveLog(server.channels).attached())
                step_callbacks += [feed.on_step, lambda _, step: live_log.stamp(step.time_s)]
                progress_callbacks.append(feed.on_progress)
            try:
                outcome = _run_async(
                    fly(
                        scenario,
                        emulator_overrides={"tlog_dir": str(tlogs)},
                        on_step=_every(step_callbacks),
                        on_progress=_every(progress_callbacks),
                        console=_operator_console("run"),
                    ),
                    _RUN_STOPPING,
                )
            finally:
                if view is not None:
                    view.close()
        document = record.write_results(
            outcome.result,
            wall_time_s=outcome.wall_time_s,
            figures=not arguments.no_figures,
            vehicles=outcome.vehicles,
            records=outcome.records,
            start_s=outcome.start_s,
            logs=capture.lines,
            bus_security=outcome.bus_security,
            figure_process=None if arguments.no_figures else figure_process,
        )
    if not arguments.quiet:
        print(_summary_text(document, out_dir))
        print(_ranging_text(scenario))
        mission_s = scenario.timing.steps * scenario.timing.step_s
        print(
            f"flown: {mission_s:g} s of mission in {outcome.mission_wall_time_s:.2f} s wall "
            f"({mission_s / outcome.mission_wall_time_s:.1f}x real time); MAVLink logs in {tlogs}/"
        )
    _maybe_replay(arguments, out_dir)
    return EXIT_OK if document["expectations"]["passed"] else EXIT_EXPECTATION_FAILED


def _vehicle(arguments: argparse.Namespace) -> int:
    from .outputs import (  # noqa: PLC0415
        VEHICLE_FILES,
        Status,
        bus_security,
        bus_security_line,
        prepare_out_dir,
        write_vehicle_run,
    )
    from .runner.process import VehicleRun, run_vehicle  # noqa: PLC0415

    scenario = with_bus_access(load_scenario(arguments.config, flying=True), arguments)
    # No summary.json until the end: the ground station takes one as "this vehicle is done".
    out_dir = prepare_out_dir(
        arguments.out or _mission_dir(scenario) / f"vehicle_{arguments.id}", VEHICLE_FILES
    )
    run = VehicleRun(arguments.id)
    capture = LogCapture()
    status: Status = "error"
    try:
        with capture.attached():
            _run_async(
                run_vehicle(
                    scenario,
                    arguments.id,
                    url=arguments.url,
                    run=run,
                    on_step=lambda _, record: capture.stamp(record.time_s),
                )
            )
        status = "passed" if run.state == "done" else "error"
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    finally:
        write_vehicle_run(
            run,
            out_dir,
            config_path=arguments.config,
            status=status,
            scenario=scenario,
            logs=capture.lines,
        )
    following = sum(record.state == "following" for record in run.records)
    print(
        f"vehicle {arguments.id}: {run.state}, {len(run.records)} steps, {following} following "
        f"the law, {run.skipped_steps} skipped; autopilot clock "
        f"{run.autopilot_clock_rate or 1:.4f}x, mission clock {run.clock_rate:.4f}x; "
        f"results in {out_dir}/" + (f"\n  {run.detail}" if run.detail else "")
    )
    security = {
        "bus_security": bus_security(
            run.bus_messages,
            {run.vehicle_id: run.ranges_rejected},
            {run.vehicle_id: run.commands_rejected},
        )
    }
    line = bus_security_line(security)
    if line:
        print(f"vehicle {arguments.id}: {line}")
    return EXIT_OK if run.state == "done" else EXIT_RUNTIME_FAILURE


def _ground(arguments: argparse.Namespace) -> int:
    from .outputs import (  # noqa: PLC0415
        RUN_FILES,
        RunSummary,
        bus_security,
        bus_security_line,
        prepare_out_dir,
    )
    from .runner.process import run_ground, wait_and_merge  # noqa: PLC0415
    from .runner.scoring import mission_records  # noqa: PLC0415

    scenario = with_bus_access(load_scenario(arguments.config, flying=True), arguments)
    mission_dir = prepare_out_dir(arguments.out or _mission_dir(scenario), RUN_FILES)

    last_state: dict[int, str] = {}
    shown_to: dict[int, int] = {}  # the step from which a vehicle's progress is shown again

    def show(status: VehicleStatus) -> None:
        """A line at each change of state, else every 40 steps (the first status at or past
        each multiple: statuses come on change and periodically, not every step)."""
        vehicle = status.vehicle_id
        changed = last_state.get(vehicle) != status.state
        last_state[vehicle] = status.state
        if changed or status.step >= shown_to.get(vehicle, 0):
            shown_to[vehicle] = (status.step // 40 + 1) * 40
            detail = f": {status.detail}" if status.detail else ""
            print(
                f"vehicle {status.vehicle_id}: {status.state} (step {status.step}){detail}",
                flush=True,
            )

    capture = LogCapture()

    def on_status(status: VehicleStatus) -> None:
        capture.stamp(status.time_s)
        show(status)

    with (
        RunSummary(mission_dir, scenario, config_path=arguments.config) as record,
        capture.attached(),
        contextlib.ExitStack() as stack,
    ):
        ground = run_ground(
            scenario,
            start_delay_s=arguments.start_delay,
            on_status=on_status,
            console=_operator_console("ground"),
        )
        server = _live_server(arguments, scenario)
        if server is None:
            outcome = _run_async(ground, _GROUND_STOPPING)
        else:
            from .live import LiveLog, alongside  # noqa: PLC0415

            stack.enter_context(server)
            print(f"live: {server.url} (Foxglove: Open connection)", flush=True)
            live_log = stack.enter_context(LiveLog(server.channels).attached())
            outcome = _run_async(
                alongside(
                    ground,
                    scenario,
                    server.channels,
                    client_id=f"{scenario.name}-ground-view",
                    on_time=live_log.stamp,
                ),
                _GROUND_STOPPING,
            )
            stack.close()  # the live view ends with the mission, before the merge
        done = len(outcome.statuses) - len(outcome.lost)
        lost = ", ".join(
            f"{i} ({outcome.statuses[i].state}: {outcome.statuses[i].detail})" for i in outcome.lost
        )
        stale = outcome.stale_steps
        print(
            f"ground: mission {outcome.mission_id} over; {done} vehicle(s) done, lost: "
            f"{lost or 'none'}; mission clock {outcome.clock_rate:.4f}x; steps held or skipped "
            f"on stale or missing data: {'unknown' if stale is None else stale} of "
            f"{scenario.timing.steps * len(scenario.vehicles)}",
            flush=True,
        )
        if outcome.bus_drops:
            drops = ", ".join(f"{i} ({n}x)" for i, n in sorted(outcome.bus_drops.items()))
            print(
                f"ground: dropped off the bus (last will) and heard again, so not lost: {drops}",
                flush=True,
            )
        security = bus_security(outcome.bus_messages, {})
        line = bus_security_line({"bus_security": security})
        if line:  # what each vehicle dropped is in its own summary
            print(f"ground: {line}", flush=True)
        result = _run_async(wait_and_merge(scenario, mission_dir, outcome))
        if result is None:
            print(
                f"ground: no truth in {mission_dir}/truth/ (no simulator): tracking and estimate "
                "errors unavailable; per-vehicle results in the vehicles' folders"
            )
            return _score_without_truth(scenario, record, outcome.statuses, stale)
        document = record.write_results(
            result,
            figures=not arguments.no_figures,
            vehicles={
                i: {"state": status.state, "detail": status.detail}
                | (
                    {"bus": f"dropped off {outcome.bus_drops[i]}x (last will), heard again"}
                    if i in outcome.bus_drops
                    else {}
                )
                for i, status in outcome.statuses.items()
            },
            records=mission_records(mission_dir, (v.id for v in scenario.vehicles)),
            start_s=outcome.start_s or 0.0,
            logs=capture.lines,
            bus_security=security,
        )
    print(_summary_text(document, mission_dir))
    return EXIT_OK if document["expectations"]["passed"] else EXIT_EXPECTATION_FAILED


def _score_without_truth(
    scenario: Scenario,
    record: RunSummary,
    statuses: Mapping[int, VehicleStatus],
    stale_steps: int | None = None,
) -> int:
    """A mission without truth (real vehicles) is scored on what the ground station saw: how
    many vehicles finished in the formation (reported ``done``) and how many steps they held or
    skipped on stale or missing data (``stale_steps``, from their reports; None: unknown).
    Expectations that need the truth are listed as not checked, and the status says so:
    ``unchecked``, never ``passed``."""
    from .metrics import check_expectations  # noqa: PLC0415

    observed = {"vehicles_in_formation_at_end": sum(s.state == "done" for s in statuses.values())}
    if stale_steps is not None:
        observed["steps_on_stale_data"] = stale_steps
    checkable = {name: bound for name, bound in scenario.expect.items() if name in observed}
    failures = check_expectations(checkable, observed)
    unchecked = sorted(set(scenario.expect) - set(observed))
    record.finish(
        "failed" if failures else "unchecked" if unchecked else "passed",
        "no truth (no simulator): expectations on errors not checked",
        metrics=observed,
        vehicles={
            str(i): {"state": s.state, "detail": s.detail} for i, s in sorted(statuses.items())
        },
        expectations={
            "checked": sorted(checkable),
            "passed": not failures,
            "failures": failures,
            "not_checked": unchecked,
        },
    )
    for failure in failures:
        print(f"ground: expectation failed: {failure}")
    if unchecked:
        print(f"ground: not checked without truth: {', '.join(unchecked)}")
    return EXIT_EXPECTATION_FAILED if failures else EXIT_OK


def _control(arguments: argparse.Namespace) -> int:
    import asyncio  # noqa: PLC0415

    from .runner.operator import OperatorInputError, operator_command  # noqa: PLC0415
    from .runner.process import send_control  # noqa: PLC0415

    scenario = with_bus_access(load_scenario(arguments.config), arguments)
    try:  # before connecting: a command for a vehicle not in the scenario is bad input
        operator_command(
            arguments.command,
            [v.id for v in scenario.vehicles],
            vehicle_id=arguments.vehicle,
            reason=arguments.reason,
        )
    except OperatorInputError as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    mission_id = asyncio.run(
        send_control(
            scenario, arguments.command, vehicle_id=arguments.vehicle, reason=arguments.reason
        )
    )
    who = f"vehicle {arguments.vehicle}" if arguments.vehicle else "every vehicle"
    print(f"control: {arguments.command} sent to {who} of mission {mission_id}")
    return EXIT_OK


def _operator_console(prefix: str) -> OperatorConsole:
    """The operator's typed commands on stdin: what was sent on stdout, mistakes on stderr."""
    from .runner.operator import HELP, OperatorConsole  # noqa: PLC0415

    def say(text: str) -> None:
        print(f"{prefix}: {text}", flush=True)

    def complain(text: str) -> None:
        print(f"{prefix}: error: {text}", file=sys.stderr, flush=True)

    if sys.stdin is not None and sys.stdin.isatty():
        say(f"type a command and Enter. {HELP}")
    return OperatorConsole(say, complain)


def _broker_config(arguments: argparse.Namespace) -> int:
    from .bus.broker import TlsListener, write_broker_config  # noqa: PLC0415
    from .errors import ConfigError  # noqa: PLC0415

    scenario = load_scenario(arguments.config)
    source = str(arguments.config)
    if scenario.bus.kind != "mqtt":
        raise ConfigError(source, [("bus.kind", "a broker is for bus.kind: mqtt")])
    if (arguments.tls_cert is None) != (arguments.tls_key is None):
        raise ConfigError("broker-config", [("--tls-cert/--tls-key", "give both or neither")])
    tls = None
    if arguments.tls_cert is not None:
        tls = TlsListener(arguments.tls_cert, arguments.tls_key, arguments.tls_ca)
    files = write_broker_config(
        arguments.out,
        scenario.bus.topics(scenario.name),
        [vehicle.id for vehicle in scenario.vehicles],
        port=arguments.port or scenario.bus.mqtt.port,
        bind_address=arguments.bind,
        tls=tls,
        write_bus_key=not arguments.no_bus_key,
        max_message_bytes=scenario.bus.auth.max_message_bytes,
    )
    print(f"broker-config: users {', '.join(files.users)}")
    print(f"  start the broker:   mosquitto -c {files.config}")
    print(f"  broker logins:      {files.credentials} (0600; each machine needs its own line)")
    if not arguments.no_bus_key:
        print(f"  message key:        {files.bus_key} (0600; every process: --bus-key-file)")
    print(f"  access control:     {files.acl}")
    return EXIT_OK


def _mission_dir(scenario: Scenario) -> Path:
    """Where a mission of vehicle processes writes by default: one folder for all of them."""
    return Path("out") / f"{scenario.name}-mission"


def _ranges(arguments: argparse.Namespace) -> int:
    from .outputs import TRUTH_FILES, prepare_out_dir  # noqa: PLC0415
    from .runner.ranges import TRUTH_RATE_HZ, VisionSettings, run_range_provider  # noqa: PLC0415
    from .runner.scoring import write_truth_csv  # noqa: PLC0415

    scenario = with_bus_access(load_scenario(arguments.config, flying=True), arguments)
    out_dir = prepare_out_dir(arguments.out or _mission_dir(scenario) / "truth", TRUTH_FILES)
    print(
        f"ranges: SIMULATION AID - ranges are synthesised from {arguments.source.upper()} "
        "positions, not measured",
        flush=True,
    )
    stats = _run_async(
        run_range_provider(
            scenario,
            source=arguments.source,
            urls=arguments.url or ["udpin://0.0.0.0:14550"],
            truth_port_base=arguments.truth_port_base,
            truth_rate_hz=TRUTH_RATE_HZ
            if arguments.truth_rate is None
            else arguments.truth_rate or None,
            vision=VisionSettings(arguments.vision, *arguments.vision_noise)
            if arguments.vision
            else None,
            seed=scenario.seed,
        )
    )
    write_truth_csv(stats.truth, [v.id for v in scenario.vehicles], out_dir / "truth.csv")
    lateness = ", ".join(f"{k} {v:.1f} ms" for k, v in stats.lateness_percentiles_ms().items())
    print(
        f"ranges: {stats.steps} steps ({stats.skipped} skipped: past their deadline), "
        f"{stats.ranges} ranges published, "
        f"{stats.missing_vehicles} vehicle-steps without a position, {stats.unsent} messages "
        f"dropped (not handed to the broker in time); after t_k: {lateness}; "
        "positions per second: "
        + ", ".join(f"{i}: {rate:.1f}" for i, rate in stats.position_rates_hz.items())
        + (
            "; vision odometry per second: "
            + ", ".join(f"{i}: {rate:.1f}" for i, rate in stats.vision_rates_hz.items())
            if stats.vision_rates_hz
            else ""
        )
    )
    return EXIT_OK if stats.ranges else EXIT_RUNTIME_FAILURE


class _FlightView:
    """Live view of a flight: a line per second of mission time and at every change of a
    vehicle's state (an operator sees a hold take effect), or a bar on a terminal."""

    def __init__(self, scenario: Scenario) -> None:
        self._every = max(1, round(1.0 / scenario.timing.step_s))
        self._bar = _Progress(scenario.timing.steps, False, scenario.name)
        self._states: dict[int, str] = {}

    def __call__(self, progress: Progress) -> None:
        self._bar.update_to(progress.step + 1, progress.steps)
        changed, self._states = progress.states != self._states, dict(progress.states)
        if progress.step % self._every and progress.step != progress.steps - 1 and not changed:
            return
        states = " ".join(f"v{i}:{state}" for i, state in progress.states.items())
        line = (
            f"k={progress.step:4d}  {states}  tracking {progress.tracking_error_m:7.3f} m  "
            f"estimates {progress.localization_error_m:7.4f} m"
        )
        self._bar.write(line)

    def close(self) -> None:
        self._bar.close()


class _Progress:
    """A tqdm bar on stderr when it is a terminal; nothing otherwise."""

    def __init__(self, total: int, quiet: bool, label: str) -> None:
        self._bar: tqdm[Any] | None = None
        if not quiet and sys.stderr.isatty():
            from tqdm import tqdm  # noqa: PLC0415

            self._bar = tqdm(total=total, desc=label, unit="step", leave=False)

    def update_to(self, done: int, total: int) -> None:
        if self._bar is not None:
            self._bar.update(done - self._bar.n)

    def write(self, line: str) -> None:
        """``line`` above the bar, or on stdout when there is no bar."""
        if self._bar is not None:
            self._bar.write(line)
        else:
            print(line, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def _progress(total: int, quiet: bool, label: str) -> _Progress:
    return _Progress(total, quiet, label)


def _summary_text(document: Mapping[str, Any], out_dir: Path) -> str:
    metrics = document["metrics"]
    lines = [
        f"scenario {document['scenario']}: {document['steps']} steps of {document['step_s']} s"
        + (f", {document['runs']} runs" if document["runs"] > 1 else "")
        + (f" in {document['wall_time_s']:.2f} s" if "wall_time_s" in document else ""),
    ]
    width = max(len(name) for name in metrics)
    lines += [f"  {name:<{width}}  {_format(value)}" for name, value in metrics.items()]
    if "batch" in document:
        lines.append(f"  batch ({document['runs']} runs): median / p95 / worst")
        for name, stats in document["batch"].items():
            if isinstance(stats, dict):
                values = [stats.get("median"), stats.get("p95", stats.get("p5")), stats["worst"]]
                text = " / ".join(_format(value) for value in values)
                if stats.get("never_converged"):
                    text += f"  ({stats['never_converged']} never)"
                if stats.get("not_finite"):
                    text += f"  ({stats['not_finite']} not finite)"
                lines.append(f"    {name:<{width}}  {text}")
        lines.append(
            f"    runs passing expectations: {document['batch']['runs_passing_expectations']}"
        )
    ended = {i: v for i, v in document.get("vehicles", {}).items() if v["state"] != "done"}
    if "vehicles" in document:
        lines.append(
            "vehicles: "
            + (
                "all done"
                if not ended
                else "; ".join(f"{i} {v['state']}: {v['detail'] or '-'}" for i, v in ended.items())
            )
        )
    from .outputs import bus_security_line  # noqa: PLC0415

    security = bus_security_line(document)
    if security:
        lines.append(security)
    expectations = document["expectations"]
    if expectations["checked"]:
        verdict = "PASS" if expectations["passed"] else "FAIL"
        lines.append(f"expectations: {verdict} ({len(expectations['checked'])} checked)")
        lines += [f"  failed: {failure}" for failure in expectations["failures"]]
    written = ["summary.json", "timeseries.csv", "recording.mcap", *document.get("figures", [])]
    lines.append(f"results in {out_dir}/ ({', '.join(written)})")
    return "\n".join(lines)


def _format(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


if __name__ == "__main__":
    sys.exit(main())

"""``mission-runner``: the command line.

    mission-runner simulate CONFIG [--out DIR] [--runs N] [--no-figures] [--quiet]
    mission-runner run CONFIG [--out DIR] [--realtime [--speed F]] [--no-figures] [--quiet]
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
- 130: interrupted by SIGINT (Ctrl-C), 143: by SIGTERM. Both stop the same way: a flight lands
  first, and ``summary.json`` is written with ``status: interrupted``.

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
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, TypeVar

from .bus.cli_options import add_bus_arguments, with_bus_access
from .bus.errors import BusConnectionError, BusTimeoutError
from .config import load_scenario
from .errors import MissionRunnerError
from .runner.errors import RunnerError

if TYPE_CHECKING:
    from tqdm import tqdm

    from .bus import VehicleStatus
    from .config import Scenario
    from .runner.controller import StepRecord
    from .runner.mission import Progress

T = TypeVar("T")

#: A subcommand: parsed arguments in, exit code out.
Handler = Callable[[argparse.Namespace], int]

EXIT_OK, EXIT_EXPECTATION_FAILED, EXIT_BAD_INPUT, EXIT_RUNTIME_FAILURE = 0, 1, 2, 3
#: 128 + the signal's number, as a shell reports a process that signal ended.
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
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
    """Process-wide, as signal handlers are: which stop signal arrived, and how to stop the
    asyncio main task that runs (see :func:`_run_async`)."""

    def __init__(self) -> None:
        self.received = "SIGINT"
        self.cancel_main: Callable[[], None] | None = None


_signals = _StopSignals()


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
            _signals.cancel_main()
        else:
            raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def _run_async(coroutine: Coroutine[Any, Any, T]) -> T:
    """``asyncio.run(coroutine)``; SIGTERM cancels its main task as asyncio does on Ctrl-C (so a
    flight lands), then raises KeyboardInterrupt. Also when SIGINT is ignored, as in a
    background job, where asyncio does not install its own handler."""
    import asyncio  # noqa: PLC0415 - simulate does without

    cancelled = False

    async def main() -> T:
        task, loop = asyncio.current_task(), asyncio.get_running_loop()

        def cancel() -> None:
            nonlocal cancelled
            cancelled = True
            if task is not None:
                loop.call_soon_threadsafe(task.cancel)  # wakes the loop, as asyncio's handler

        _signals.cancel_main = cancel
        try:
            return await coroutine
        finally:
            _signals.cancel_main = None

    try:
        result = asyncio.run(main())
    except asyncio.CancelledError:
        if cancelled:
            raise KeyboardInterrupt from None
        raise
    if cancelled:  # the coroutine ended on its own terms, but the user asked it to stop
        raise KeyboardInterrupt
    return result


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
        leaves: list[BaseException] = []

        def collect(error: BaseException) -> None:
            if isinstance(error, BaseExceptionGroup):
                for inner in error.exceptions:
                    collect(inner)
            else:
                leaves.append(error)

        collect(group)
        for leaf in leaves:
            if isinstance(leaf, (MissionRunnerError, KeyboardInterrupt, *_emulator_errors())):
                raise leaf from group
        raise


def _parser() -> argparse.ArgumentParser:
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
        "--runs", type=_positive_int, default=1, help="batch of N initial conditions (default 1)"
    )
    simulate.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    simulate.add_argument("--quiet", action="store_true", help="no progress bar, no summary")
    simulate.set_defaults(handler=_simulate)

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
        "--speed", type=_positive_float, default=None, help="real-time speed factor (> 0)"
    )
    run.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    run.add_argument("--quiet", action="store_true", help="no progress view, no summary")
    add_bus_arguments(run)
    run.set_defaults(handler=_run)

    vehicle = commands.add_parser(
        "vehicle", help="one vehicle's controller as its own process (talks over MQTT only)"
    )
    vehicle.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    vehicle.add_argument("--id", type=_positive_int, required=True, help="this vehicle's id")
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
        "--start-delay", type=_non_negative_float, default=2.0, help="seconds from ready to k = 0"
    )
    ground.add_argument(
        "--out",
        type=Path,
        default=None,
        help="mission folder where the vehicles and the range aid write (default: "
        "out/<name>-mission): the ground station merges them into summary.json and figures",
    )
    ground.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    add_bus_arguments(ground)
    ground.set_defaults(handler=_ground)

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
        "--truth-port-base", type=_port, default=19410, help="UDP port of vehicle id 1's truth"
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

    operate = commands.add_parser(
        "control",
        help="operator command to the running mission of vehicle processes: hold, resume, land, "
        "return or stop, for every vehicle or one",
    )
    operate.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    operate.add_argument("command", choices=("hold", "resume", "land", "return", "stop"))
    operate.add_argument("--vehicle", type=_positive_int, default=None, help="one vehicle's id")
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
        "--port", type=_port, default=None, help="listener port (default: bus.mqtt.port)"
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

    from . import px4sitl  # noqa: PLC0415 - only its argument definitions
    from .world import emulated  # noqa: PLC0415

    emulate = commands.add_parser(
        "emulate",
        help="emulated PX4 vehicles with the scenario's target and UWB ranging on its bus, for "
        "vehicle processes (what 'sitl --scenario' did)",
    )
    emulated.add_arguments(emulate)
    add_bus_arguments(emulate)

    px4 = commands.add_parser(
        "px4-sitl",
        help="start real PX4 SITL (SIH), one instance per vehicle of the scenario, until Ctrl-C",
    )
    px4sitl.add_arguments(px4)
    return parser


def _port(text: str) -> int:
    value = _positive_int(text)
    if value > 65535:
        raise argparse.ArgumentTypeError(f"not a UDP port: {value}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _positive_float(text: str) -> float:
    value = _float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def _non_negative_float(text: str) -> float:
    value = _float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return value


def _simulate(arguments: argparse.Namespace) -> int:
    from .outputs import RUN_FILES, RunSummary, prepare_out_dir  # noqa: PLC0415 - fast `--help`
    from .sim.simulator import check_memory, simulate  # noqa: PLC0415

    scenario = load_scenario(arguments.config)
    check_memory(scenario, arguments.runs, str(arguments.config))
    out_dir = prepare_out_dir(arguments.out or Path("out") / scenario.name, RUN_FILES)
    progress = _progress(scenario.timing.steps, arguments.quiet, f"{scenario.name}")
    with RunSummary(out_dir, scenario, config_path=arguments.config, runs=arguments.runs) as record:

        def on_step(done: int, total: int) -> None:
            record.steps_done = done
            progress.update_to(done, total)

        started = time.perf_counter()
        try:
            result = simulate(scenario, runs=arguments.runs, on_step=on_step)
        finally:
            progress.close()
        document = record.write_results(
            result, wall_time_s=time.perf_counter() - started, figures=not arguments.no_figures
        )
    if not arguments.quiet:
        print(_summary_text(document, out_dir))
    return EXIT_OK if document["expectations"]["passed"] else EXIT_EXPECTATION_FAILED


def _run(arguments: argparse.Namespace) -> int:
    from .config import validate_scenario  # noqa: PLC0415
    from .outputs import RUN_FILES, RunSummary, prepare_out_dir  # noqa: PLC0415
    from .runner.mission import fly  # noqa: PLC0415
    from .sim.simulator import check_memory  # noqa: PLC0415

    scenario = load_scenario(arguments.config)
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
    with RunSummary(out_dir, scenario, config_path=arguments.config) as record:

        def on_step(vehicle_id: int, step: StepRecord) -> None:
            record.steps_done = max(record.steps_done, step.step + 1)

        try:
            outcome = _run_async(
                fly(
                    scenario,
                    emulator_overrides={"tlog_dir": str(tlogs)},
                    on_step=on_step,
                    on_progress=view,
                )
            )
        finally:
            if view is not None:
                view.close()
        document = record.write_results(
            outcome.result,
            wall_time_s=outcome.wall_time_s,
            figures=not arguments.no_figures,
            vehicles=outcome.vehicles,
            bus_security=outcome.bus_security,
        )
    if not arguments.quiet:
        print(_summary_text(document, out_dir))
        mission_s = scenario.timing.steps * scenario.timing.step_s
        print(
            f"flown: {mission_s:g} s of mission in {outcome.mission_wall_time_s:.2f} s wall "
            f"({mission_s / outcome.mission_wall_time_s:.1f}x real time); MAVLink logs in {tlogs}/"
        )
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

    scenario = with_bus_access(load_scenario(arguments.config), arguments)
    # No summary.json until the end: the ground station takes one as "this vehicle is done".
    out_dir = prepare_out_dir(
        arguments.out or _mission_dir(scenario) / f"vehicle_{arguments.id}", VEHICLE_FILES
    )
    run = VehicleRun(arguments.id)
    status: Status = "error"
    try:
        _run_async(run_vehicle(scenario, arguments.id, url=arguments.url, run=run))
        status = "passed" if run.state == "done" else "error"
    except KeyboardInterrupt:
        status = "interrupted"
        raise
    finally:
        write_vehicle_run(run, out_dir, config_path=arguments.config, status=status)
    following = sum(record.state == "following" for record in run.records)
    print(
        f"vehicle {arguments.id}: {run.state}, {len(run.records)} steps, {following} following "
        f"the law, {run.skipped_steps} skipped; autopilot clock "
        f"{run.autopilot_clock_rate or 1:.4f}x, mission clock {run.clock_rate:.4f}x; "
        f"results in {out_dir}/" + (f"\n  {run.detail}" if run.detail else "")
    )
    security = {
        "bus_security": bus_security(run.bus_messages, {run.vehicle_id: run.ranges_rejected})
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

    scenario = with_bus_access(load_scenario(arguments.config), arguments)
    mission_dir = prepare_out_dir(arguments.out or _mission_dir(scenario), RUN_FILES)

    last_state: dict[int, str] = {}

    def show(status: VehicleStatus) -> None:
        changed = last_state.get(status.vehicle_id) != status.state
        last_state[status.vehicle_id] = status.state
        if changed or status.step % 40 == 0:
            detail = f": {status.detail}" if status.detail else ""
            print(
                f"vehicle {status.vehicle_id}: {status.state} (step {status.step}){detail}",
                flush=True,
            )

    with RunSummary(mission_dir, scenario, config_path=arguments.config) as record:
        outcome = _run_async(
            run_ground(scenario, start_delay_s=arguments.start_delay, on_status=show)
        )
        done = len(outcome.statuses) - len(outcome.lost)
        lost = ", ".join(
            f"{i} ({outcome.statuses[i].state}: {outcome.statuses[i].detail})" for i in outcome.lost
        )
        print(
            f"ground: mission {outcome.mission_id} over; {done} vehicle(s) done, lost: "
            f"{lost or 'none'}; mission clock {outcome.clock_rate:.4f}x",
            flush=True,
        )
        security = bus_security(outcome.bus_messages, {})
        line = bus_security_line({"bus_security": security})
        if line:  # what each vehicle dropped is in its own summary
            print(f"ground: {line}", flush=True)
        result = _run_async(wait_and_merge(scenario, mission_dir, outcome))
        if result is None:
            record.finish("passed", "no truth (no simulator): expectations not checked")
            print(
                f"ground: no truth in {mission_dir}/truth/ (no simulator): tracking and estimate "
                "errors unavailable; per-vehicle results in the vehicles' folders"
            )
            return EXIT_OK
        document = record.write_results(
            result,
            figures=not arguments.no_figures,
            vehicles={
                i: {"state": status.state, "detail": status.detail}
                for i, status in outcome.statuses.items()
            },
            bus_security=security,
        )
    print(_summary_text(document, mission_dir))
    return EXIT_OK if document["expectations"]["passed"] else EXIT_EXPECTATION_FAILED


def _control(arguments: argparse.Namespace) -> int:
    import asyncio  # noqa: PLC0415

    from .bus import ControlCommand  # noqa: PLC0415
    from .runner.process import send_control  # noqa: PLC0415

    scenario = with_bus_access(load_scenario(arguments.config), arguments)
    command = ControlCommand(arguments.command)
    mission_id = asyncio.run(
        send_control(scenario, command, vehicle_id=arguments.vehicle, reason=arguments.reason)
    )
    who = f"vehicle {arguments.vehicle}" if arguments.vehicle else "every vehicle"
    print(f"control: {command.value} sent to {who} of mission {mission_id}")
    return EXIT_OK


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
    from .runner.ranges import run_range_provider  # noqa: PLC0415
    from .runner.scoring import write_truth_csv  # noqa: PLC0415

    scenario = with_bus_access(load_scenario(arguments.config), arguments)
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
            seed=scenario.seed,
        )
    )
    write_truth_csv(stats.truth, [v.id for v in scenario.vehicles], out_dir / "truth.csv")
    lateness = ", ".join(f"{k} {v:.1f} ms" for k, v in stats.lateness_percentiles_ms().items())
    print(
        f"ranges: {stats.steps} steps, {stats.ranges} ranges published, "
        f"{stats.missing_vehicles} vehicle-steps without a position; after t_k: {lateness}"
    )
    return EXIT_OK if stats.ranges else EXIT_RUNTIME_FAILURE


class _FlightView:
    """Live view of a flight: a line per second of mission time (or a bar on a terminal)."""

    def __init__(self, scenario: Scenario) -> None:
        self._every = max(1, round(1.0 / scenario.timing.step_s))
        self._bar = _Progress(scenario.timing.steps, False, scenario.name)

    def __call__(self, progress: Progress) -> None:
        self._bar.update_to(progress.step + 1, progress.steps)
        if progress.step % self._every and progress.step != progress.steps - 1:
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
    written = ["summary.json", "timeseries.csv", *document.get("figures", [])]
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

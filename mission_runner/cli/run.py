"""``mission-runner run``."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .. import argtypes
from ..limits import MAX_CLOCK_SPEED
from .common import EXIT_EXPECTATION_FAILED, EXIT_OK, every, live_server, operator_console
from .options import add_bus_arguments, add_live_flags, add_replay_flag
from .output import FlightView, maybe_replay, ranging_text, summary_text
from .stopping import RUN_STOPPING, run_async

if TYPE_CHECKING:
    from ..config import Scenario
    from ..metrics import SimulationResult
    from ..records import Progress, StepRecord
    from ..runner.mission import FlightOutcome


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    add_replay_flag(run)
    add_live_flags(run)
    add_bus_arguments(run)
    run.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    from ..figure_process import (  # noqa: PLC0415 - fast `--help`
        FigureProcess,
        RecordingProcess,
    )
    from ..outputs import RUN_FILES, RunSummary, prepare_out_dir  # noqa: PLC0415 - fast `--help`
    from ..recording import RECORDING, LogCapture  # noqa: PLC0415 - fast `--help`
    from ..runner.mission import fly  # noqa: PLC0415 - fast `--help`

    scenario = _scenario(arguments)
    out_dir = prepare_out_dir(arguments.out or Path("out") / f"{scenario.name}-run", RUN_FILES)
    tlogs = out_dir / "tlogs"
    tlogs.mkdir(exist_ok=True)
    view = None if arguments.quiet else FlightView(scenario)
    capture = LogCapture()
    with (
        FigureProcess() as figure_process,
        RecordingProcess() as recording_process,
        RunSummary(out_dir, scenario, config_path=arguments.config) as record,
    ):

        def on_step(vehicle_id: int, step: StepRecord) -> None:
            record.steps_done = max(record.steps_done, step.step + 1)
            capture.stamp(step.time_s)
            if step.step == 0:
                # The workers import while the mission flies: this process keeps one core busy,
                # the other has time (MAVSDK's threads use a tenth of it).
                recording_process.start()
                if not arguments.no_figures:
                    figure_process.start()

        def on_mission_end(
            result: SimulationResult, records: Mapping[int, Sequence[StepRecord]], start_s: float
        ) -> None:
            # Drawn and recorded while the vehicles land
            if not arguments.no_figures:
                figure_process.submit(result, out_dir)
            recording_process.submit_mission(
                result, out_dir / RECORDING, records=records, start_s=start_s, logs=capture.lines
            )

        step_callbacks: list[Callable[[int, StepRecord], None]] = [on_step]
        progress_callbacks: list[Callable[[Progress], None]] = [view] if view is not None else []
        with contextlib.ExitStack() as stack:
            stack.enter_context(capture.attached())
            _attach_live(stack, arguments, scenario, step_callbacks, progress_callbacks)
            try:
                outcome = run_async(
                    fly(
                        scenario,
                        emulator_overrides={"tlog_dir": str(tlogs)},
                        on_step=every(step_callbacks),
                        on_progress=every(progress_callbacks),
                        on_mission_end=on_mission_end,
                        console=operator_console("run"),
                    ),
                    RUN_STOPPING,
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
            recording_process=recording_process,
        )
    if not arguments.quiet:
        _print_flight(scenario, document, outcome, out_dir)
    maybe_replay(arguments, out_dir)
    return EXIT_OK if document["expectations"]["passed"] else EXIT_EXPECTATION_FAILED


def _scenario(arguments: argparse.Namespace) -> Scenario:
    """The scenario to fly: ``--realtime`` and ``--speed`` applied, the bus options attached,
    its scored result checked to fit in memory."""
    from ..bus.cli_options import with_bus_access  # noqa: PLC0415 - fast `--help`
    from ..checks import load_scenario, validate_scenario  # noqa: PLC0415 - fast `--help`
    from ..sim.simulator import check_memory  # noqa: PLC0415 - fast `--help`

    scenario = load_scenario(arguments.config, flying=True)
    if arguments.realtime or arguments.speed is not None:
        data = scenario.model_dump(mode="json")
        data["flight"]["clock"] = "realtime"
        data["flight"]["speed"] = 1.0 if arguments.speed is None else arguments.speed
        scenario = validate_scenario(data, str(arguments.config))
    scenario = with_bus_access(scenario, arguments)
    check_memory(scenario, 1, str(arguments.config))  # the flight's scored result
    return scenario


def _attach_live(
    stack: contextlib.ExitStack,
    arguments: argparse.Namespace,
    scenario: Scenario,
    step_callbacks: list[Callable[[int, StepRecord], None]],
    progress_callbacks: list[Callable[[Progress], None]],
) -> None:
    """``--live``: the live view's server on ``stack``, fed by the flight's callbacks."""
    server = live_server(arguments, scenario)
    if server is None:
        return
    from ..live import FlightFeed, LiveLog  # noqa: PLC0415 - fast `--help`

    stack.enter_context(server)
    print(f"live: {server.url} (Foxglove: Open connection)", flush=True)
    feed = FlightFeed(scenario, server.channels)
    live_log = stack.enter_context(LiveLog(server.channels).attached())
    step_callbacks += [feed.on_step, lambda _, step: live_log.stamp(step.time_s)]
    progress_callbacks.append(feed.on_progress)


def _print_flight(
    scenario: Scenario, document: Mapping[str, Any], outcome: FlightOutcome, out_dir: Path
) -> None:
    print(summary_text(document, out_dir))
    print(ranging_text(scenario))
    mission_s = scenario.timing.steps * scenario.timing.step_s
    print(
        f"flown: {mission_s:g} s of mission in {outcome.mission_wall_time_s:.2f} s wall "
        f"({mission_s / outcome.mission_wall_time_s:.1f}x real time); MAVLink logs in "
        f"{out_dir / 'tlogs'}/"
    )

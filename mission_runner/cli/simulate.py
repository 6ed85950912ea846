"""``mission-runner simulate``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .. import argtypes
from .common import EXIT_EXPECTATION_FAILED, EXIT_OK
from .options import add_replay_flag
from .output import ProgressBar, maybe_replay, ranging_text, summary_text


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    add_replay_flag(simulate)
    simulate.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    from ..checks import load_scenario  # noqa: PLC0415 - fast `--help`
    from ..outputs import RUN_FILES, RunSummary, prepare_out_dir  # noqa: PLC0415 - fast `--help`
    from ..recording import LogCapture  # noqa: PLC0415 - fast `--help`
    from ..sim.simulator import check_memory, simulate  # noqa: PLC0415 - fast `--help`

    scenario = load_scenario(arguments.config)
    check_memory(scenario, arguments.runs, str(arguments.config))
    out_dir = prepare_out_dir(arguments.out or Path("out") / scenario.name, RUN_FILES)
    progress = ProgressBar(scenario.timing.steps, arguments.quiet, f"{scenario.name}")
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
        print(summary_text(document, out_dir))
        print(ranging_text(scenario))
    maybe_replay(arguments, out_dir)
    return EXIT_OK if document["expectations"]["passed"] else EXIT_EXPECTATION_FAILED

"""``mission-runner sweep``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .. import argtypes
from .common import EXIT_BAD_INPUT, EXIT_OK
from .output import ProgressBar

if TYPE_CHECKING:
    from ..metrics import SweepPoint


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    sweeper.add_argument(
        "--cluster",
        default=None,
        metavar="ADDRESS",
        help="where the combinations run: a Dask scheduler (tcp://host:8786), 'local' (a Dask "
        "LocalCluster on this machine) or 'none' (here, one after another); default: a "
        "LocalCluster for 4000 simulator steps in all or more when Dask is installed, else here",
    )
    sweeper.add_argument(
        "--workers",
        type=argtypes.positive_int,
        default=None,
        help="a LocalCluster's worker processes (default: the cores, at most the combinations)",
    )
    sweeper.add_argument(
        "--connect-timeout",
        type=argtypes.positive_float,
        default=10.0,
        metavar="S",
        help="how long a --cluster scheduler has to answer (default 10 s)",
    )
    sweeper.add_argument("--no-figures", action="store_true", help="skip sweep.png")
    sweeper.add_argument("--quiet", action="store_true", help="no progress, no table")
    sweeper.set_defaults(handler=command)


def _axis(text: str) -> Any:
    import yaml  # noqa: PLC0415 - fast `--help`

    from ..sim.sweep import Axis  # noqa: PLC0415 - fast `--help`

    try:
        return Axis.parse(text)
    except (ValueError, yaml.YAMLError) as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def command(arguments: argparse.Namespace) -> int:
    from ..checks import load_scenario  # noqa: PLC0415 - fast `--help`
    from ..config import METRICS  # noqa: PLC0415 - fast `--help`
    from ..outputs import prepare_out_dir  # noqa: PLC0415 - fast `--help`
    from ..paths import write_atomic  # noqa: PLC0415 - fast `--help`
    from ..sim.executors import open_executor  # noqa: PLC0415 - fast `--help`
    from ..sim.sweep import combinations, run_sweep, sweep_csv  # noqa: PLC0415 - fast `--help`

    if arguments.metric not in METRICS:
        print(f"error: --metric must be one of {', '.join(METRICS)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    scenario = load_scenario(arguments.config)
    out_dir = prepare_out_dir(
        arguments.out or Path("out") / f"{scenario.name}-sweep", ("sweep.csv", "sweep.png")
    )
    found = combinations(scenario, arguments.axes, arguments.runs, source=str(arguments.config))
    steps = sum(combination.steps for combination in found)
    progress = ProgressBar(len(found), arguments.quiet, f"{scenario.name} sweep")
    try:
        with open_executor(
            arguments.cluster, arguments.workers, steps, len(found), arguments.connect_timeout
        ) as executor:
            points = run_sweep(found, executor, on_point=progress.update_to)
    finally:
        progress.close()
    write_atomic(out_dir / "sweep.csv", sweep_csv(points))
    if not arguments.no_figures:
        from ..figures import write_sweep_figure  # noqa: PLC0415 - matplotlib is slow to import

        write_sweep_figure(points, arguments.metric, out_dir / "sweep.png")
    if not arguments.quiet:
        print(_table(points, arguments.metric, arguments.runs))
        print(f"results in {out_dir}/ (sweep.csv{'' if arguments.no_figures else ', sweep.png'})")
    return EXIT_OK


def _table(points: Sequence[SweepPoint], metric: str, runs: int) -> str:
    """``metric``'s median and 5-95 % range per combination, a line each."""
    import numpy as np  # noqa: PLC0415 - fast `--help`

    lines = [f"{metric}: median [p5, p95] over {runs} runs"]
    for point in points:
        values = np.asarray(point.metrics[metric], dtype=float)
        low, median, high = np.percentile(values, [5, 50, 95])
        label = ", ".join(f"{path}={value}" for path, value in point.values.items())
        lines.append(f"  {label}: {median:.4g} [{low:.4g}, {high:.4g}]")
    return "\n".join(lines)

"""``mission-runner ranges``."""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import argtypes
from ..limits import MAX_NOISE_STD_M
from .common import EXIT_OK, EXIT_RUNTIME_FAILURE, default_mission_dir
from .options import add_bus_arguments
from .stopping import run_async

#: The fastest MAVLink stream an option asks of an autopilot [Hz]: PX4's own loops run at 250 Hz
#: to 1 kHz; a faster stream would only flood the link.
MAX_STREAM_HZ = 1000.0


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    _add_truth_options(ranges)
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
    ranges.set_defaults(handler=command)


def _add_truth_options(ranges: argparse.ArgumentParser) -> None:
    """``--source sih``: where the truth is, how often, and the vision odometry made of it."""
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


def command(arguments: argparse.Namespace) -> int:
    from ..bus.cli_options import with_bus_access  # noqa: PLC0415 - fast `--help`
    from ..checks import load_scenario  # noqa: PLC0415 - fast `--help`
    from ..outputs import TRUTH_FILES, prepare_out_dir  # noqa: PLC0415 - fast `--help`
    from ..runner.ranges import TRUTH_RATE_HZ, VisionSettings, run_range_provider  # noqa: PLC0415 - fast `--help`
    from ..runner.scoring import write_truth_csv  # noqa: PLC0415 - fast `--help`

    scenario = with_bus_access(load_scenario(arguments.config, flying=True), arguments)
    out_dir = prepare_out_dir(arguments.out or default_mission_dir(scenario) / "truth", TRUTH_FILES)
    print(
        f"ranges: SIMULATION AID - ranges are synthesised from {arguments.source.upper()} "
        "positions, not measured",
        flush=True,
    )
    stats = run_async(
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
            + f"; kept {stats.vision_after_steps_s:.1f} s after the last step while the "
            f"vehicles landed ({stats.vehicles_done} of {len(scenario.vehicles)} done)"
            if stats.vision_rates_hz
            else ""
        )
    )
    return EXIT_OK if stats.ranges else EXIT_RUNTIME_FAILURE

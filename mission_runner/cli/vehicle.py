"""``mission-runner vehicle``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from .. import argtypes
from ..limits import MAX_MAVLINK_ID
from .common import EXIT_OK, EXIT_RUNTIME_FAILURE, default_mission_dir, startup_heap
from .options import add_bus_arguments
from .stopping import run_async

if TYPE_CHECKING:
    from ..records import VehicleRun


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    vehicle.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    with startup_heap():
        from ..bus.cli_options import with_bus_access  # noqa: PLC0415 - fast `--help`
        from ..checks import load_scenario  # noqa: PLC0415 - fast `--help`
        from ..outputs import VEHICLE_FILES, Status, prepare_out_dir, write_vehicle_run  # noqa: PLC0415 - fast `--help`
        from ..recording import LogCapture  # noqa: PLC0415 - fast `--help`
        from ..records import ControllerState, VehicleRun  # noqa: PLC0415 - fast `--help`
        from ..runner.process import run_vehicle  # noqa: PLC0415 - fast `--help`

        scenario = with_bus_access(load_scenario(arguments.config, flying=True), arguments)
    # No summary.json until the end: the ground station takes one as "this vehicle is done".
    out_dir = prepare_out_dir(
        arguments.out or default_mission_dir(scenario) / f"vehicle_{arguments.id}", VEHICLE_FILES
    )
    run = VehicleRun(arguments.id)
    capture = LogCapture()
    status: Status = "error"
    try:
        with capture.attached():
            run_async(
                run_vehicle(
                    scenario,
                    arguments.id,
                    url=arguments.url,
                    run=run,
                    on_step=lambda _, record: capture.stamp(record.time_s),
                )
            )
        status = "passed" if run.state == ControllerState.DONE else "error"
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
    _report(run, out_dir)
    return EXIT_OK if run.state == ControllerState.DONE else EXIT_RUNTIME_FAILURE


def _report(run: VehicleRun, out_dir: Path) -> None:
    """How the vehicle's mission went, on stdout; what its bus dropped, if anything."""
    from ..outputs import bus_security, bus_security_line  # noqa: PLC0415 - fast `--help`
    from ..records import ControllerState  # noqa: PLC0415 - fast `--help`

    following = sum(record.state == ControllerState.FOLLOWING for record in run.records)
    print(
        f"vehicle {run.vehicle_id}: {run.state}, {len(run.records)} steps, {following} following "
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
        print(f"vehicle {run.vehicle_id}: {line}")

"""``mission-runner ground``."""

from __future__ import annotations

import argparse
from collections.abc import Coroutine, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .. import argtypes
from ..limits import MAX_WAIT_S
from .common import (
    EXIT_EXPECTATION_FAILED,
    EXIT_OK,
    default_mission_dir,
    live_server,
    operator_console,
)
from .options import add_bus_arguments, add_live_flags
from .output import summary_text
from .stopping import GROUND_STOPPING, run_async

if TYPE_CHECKING:
    from ..bus import VehicleStatus
    from ..config import Scenario
    from ..outputs import RunSummary
    from ..runner.process import GroundOutcome


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    add_live_flags(ground)
    add_bus_arguments(ground)
    ground.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    from ..bus.cli_options import with_bus_access  # noqa: PLC0415 - fast `--help`
    from ..checks import load_scenario  # noqa: PLC0415 - fast `--help`
    from ..outputs import RUN_FILES, RunSummary, prepare_out_dir  # noqa: PLC0415 - fast `--help`
    from ..recording import LogCapture  # noqa: PLC0415 - fast `--help`
    from ..runner.process import run_ground, wait_and_merge  # noqa: PLC0415 - fast `--help`
    from ..runner.scoring import mission_records  # noqa: PLC0415 - fast `--help`

    scenario = with_bus_access(load_scenario(arguments.config, flying=True), arguments)
    mission_dir = prepare_out_dir(arguments.out or default_mission_dir(scenario), RUN_FILES)
    capture = LogCapture()
    show = _StatusView()

    def on_status(status: VehicleStatus) -> None:
        capture.stamp(status.time_s)
        show(status)

    with (
        RunSummary(mission_dir, scenario, config_path=arguments.config) as record,
        capture.attached(),
    ):
        ground = run_ground(
            scenario,
            start_delay_s=arguments.start_delay,
            on_status=on_status,
            console=operator_console("ground"),
        )
        outcome = _fly(arguments, scenario, ground)
        security = _report(scenario, outcome)
        result = run_async(wait_and_merge(scenario, mission_dir, outcome))
        if result is None:
            print(
                f"ground: no truth in {mission_dir}/truth/ (no simulator): tracking and estimate "
                "errors unavailable; per-vehicle results in the vehicles' folders"
            )
            return score_without_truth(scenario, record, outcome.statuses, outcome.stale_steps)
        document = record.write_results(
            result,
            figures=not arguments.no_figures,
            vehicles=_vehicle_results(outcome),
            records=mission_records(mission_dir, (v.id for v in scenario.vehicles)),
            start_s=outcome.start_s or 0.0,
            logs=capture.lines,
            bus_security=security,
        )
    print(summary_text(document, mission_dir))
    return EXIT_OK if document["expectations"]["passed"] else EXIT_EXPECTATION_FAILED


class _StatusView:
    """A line at each change of a vehicle's state, else every 40 steps (the first status at or
    past each multiple: statuses come on change and periodically, not every step)."""

    def __init__(self) -> None:
        self._last_state: dict[int, str] = {}
        self._shown_to: dict[int, int] = {}  # the step from which progress is shown again

    def __call__(self, status: VehicleStatus) -> None:
        vehicle = status.vehicle_id
        changed = self._last_state.get(vehicle) != status.state
        self._last_state[vehicle] = status.state
        if changed or status.step >= self._shown_to.get(vehicle, 0):
            self._shown_to[vehicle] = (status.step // 40 + 1) * 40
            detail = f": {status.detail}" if status.detail else ""
            print(
                f"vehicle {status.vehicle_id}: {status.state} (step {status.step}){detail}",
                flush=True,
            )


def _fly(
    arguments: argparse.Namespace, scenario: Scenario, ground: Coroutine[Any, Any, GroundOutcome]
) -> GroundOutcome:
    """The mission of ``ground``, with ``--live`` the live view beside it until it ends (before
    the merge)."""
    server = live_server(arguments, scenario)
    if server is None:
        return run_async(ground, GROUND_STOPPING)
    from ..live import LiveLog, alongside  # noqa: PLC0415 - fast `--help`

    with server:
        print(f"live: {server.url} (Foxglove: Open connection)", flush=True)
        with LiveLog(server.channels).attached() as live_log:
            return run_async(
                alongside(
                    ground,
                    scenario,
                    server.channels,
                    client_id=f"{scenario.name}-ground-view",
                    on_time=live_log.stamp,
                ),
                GROUND_STOPPING,
            )


def _report(scenario: Scenario, outcome: GroundOutcome) -> dict[str, Any]:
    """What the ground station saw of the mission, on stdout; its bus security figures."""
    from ..outputs import bus_security, bus_security_line  # noqa: PLC0415 - fast `--help`

    done = len(outcome.statuses) - len(outcome.lost)
    lost = ", ".join(
        f"{i} ({outcome.statuses[i].state}: {outcome.statuses[i].detail})" for i in outcome.lost
    )
    stale = outcome.stale_steps
    clock = f"{outcome.clock_rate:.4f}x"
    if outcome.clock_changes:
        clock += (
            f" at the start, {outcome.clock_rate_at_end or 0:.4f}x at the end after "
            f"{outcome.clock_changes} change(s) following the autopilots"
        )
    print(
        f"ground: mission {outcome.mission_id} over; {done} vehicle(s) done, lost: "
        f"{lost or 'none'}; mission clock {clock}; steps held or skipped "
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
    return security


def _vehicle_results(outcome: GroundOutcome) -> dict[int, dict[str, str]]:
    return {
        i: {"state": status.state, "detail": status.detail}
        | (
            {"bus": f"dropped off {outcome.bus_drops[i]}x (last will), heard again"}
            if i in outcome.bus_drops
            else {}
        )
        for i, status in outcome.statuses.items()
    }


def score_without_truth(
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
    from ..metrics import check_expectations  # noqa: PLC0415 - fast `--help`
    from ..records import ControllerState  # noqa: PLC0415 - fast `--help`

    done = sum(s.state == ControllerState.DONE for s in statuses.values())
    observed = {"vehicles_in_formation_at_end": done}
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

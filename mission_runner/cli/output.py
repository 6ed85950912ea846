"""What a command prints: progress on a terminal, a run's summary, a replay's files."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tqdm import tqdm

    from ..config import Scenario
    from ..records import Progress
    from ..replay import ReplayFiles


def replay_text(files: ReplayFiles) -> str:
    width, height = files.size_px
    written = f"{files.gif}" + (f" and {files.mp4}" if files.mp4 else " (no ffmpeg: no MP4)")
    return (
        f"replay: {files.frames} frames of {width}x{height} px in {files.render_s:.1f} s: {written}"
    )


def ranging_text(scenario: Scenario) -> str:
    """Which ranges a step of the scenario has (its UWB scheme and airtime)."""
    from ..sensors import ranging_plan  # noqa: PLC0415 - fast `--help`
    from ..wiring import RangingGraph  # noqa: PLC0415 - fast `--help`

    ranging = RangingGraph.of(scenario)  # its frame: a ring's closing edges are slots too
    graph = None if ranging is None else ranging.frame
    return ranging_plan(len(scenario.vehicles), scenario.sensors, scenario.timing.step_s, graph)


def maybe_replay(arguments: argparse.Namespace, out_dir: Path) -> None:
    """``--replay``: animate what was just written."""
    if arguments.replay:
        from ..replay import write_replay  # noqa: PLC0415 - fast `--help`

        files = write_replay(out_dir)
        if not arguments.quiet:
            print(replay_text(files))


class FlightView:
    """Live view of a flight: a line per second of mission time and at every change of a
    vehicle's state (an operator sees a hold take effect), or a bar on a terminal."""

    def __init__(self, scenario: Scenario) -> None:
        self._every = max(1, round(1.0 / scenario.timing.step_s))
        self._bar = ProgressBar(scenario.timing.steps, False, scenario.name)
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


class ProgressBar:
    """A tqdm bar on stderr when it is a terminal; nothing otherwise."""

    def __init__(self, total: int, quiet: bool, label: str) -> None:
        self._bar: tqdm[Any] | None = None
        if not quiet and sys.stderr.isatty():
            from tqdm import tqdm  # noqa: PLC0415 - fast `--help`

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


def summary_text(document: Mapping[str, Any], out_dir: Path) -> str:
    from ..records import ControllerState  # noqa: PLC0415 - fast `--help`

    metrics = document["metrics"]
    lines = [
        f"scenario {document['scenario']}: {document['steps']} steps of {document['step_s']} s"
        + (f", {document['runs']} runs" if document["runs"] > 1 else "")
        + (f" in {document['wall_time_s']:.2f} s" if "wall_time_s" in document else ""),
    ]
    width = max(len(name) for name in metrics)
    lines += [f"  {name:<{width}}  {format_value(value)}" for name, value in metrics.items()]
    if "batch" in document:
        lines.append(f"  batch ({document['runs']} runs): median / p95 / worst")
        for name, stats in document["batch"].items():
            if isinstance(stats, dict):
                values = [stats.get("median"), stats.get("p95", stats.get("p5")), stats["worst"]]
                text = " / ".join(format_value(value) for value in values)
                if stats.get("never_converged"):
                    text += f"  ({stats['never_converged']} never)"
                if stats.get("not_finite"):
                    text += f"  ({stats['not_finite']} not finite)"
                lines.append(f"    {name:<{width}}  {text}")
        lines.append(
            f"    runs passing expectations: {document['batch']['runs_passing_expectations']}"
        )
    vehicles = document.get("vehicles", {})
    ended = {i: v for i, v in vehicles.items() if v["state"] != ControllerState.DONE}
    if "vehicles" in document:
        lines.append(
            "vehicles: "
            + (
                "all done"
                if not ended
                else "; ".join(f"{i} {v['state']}: {v['detail'] or '-'}" for i, v in ended.items())
            )
        )
    from ..outputs import bus_security_line  # noqa: PLC0415 - fast `--help`

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


def format_value(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)

"""Write a run's results: ``timeseries.csv``, ``summary.json``, ``recording.mcap`` (see
:mod:`.recording`) and the figures.

Every file is written to a temporary name and renamed into place, so a crash or Ctrl-C never leaves
a half-written result that looks complete. The folder is made ready before any work
(:func:`prepare_out_dir`: it takes files, and an earlier run's results are gone from it), and
``summary.json`` always says how the run ended (:class:`RunSummary`): ``status`` is ``running``
while it runs (all a SIGKILL leaves), then ``passed``, ``failed`` (an ``expect:`` bound),
``interrupted`` (SIGINT or SIGTERM) or ``error``.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import platform
import sys
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from . import __version__
from .errors import OutputError, error_reason
from .metrics import MetricValue, check_expectations, distribution, run_metrics
from .paths import PathName, write_atomic

if TYPE_CHECKING:
    from .config import Scenario
    from .figure_process import FigureProcess, RecordingProcess
    from .metrics import SimulationResult
    from .recording import LogLine
    from .records import StepRecord, VehicleRun

logger = logging.getLogger(__name__)

#: How a run ended, as ``summary.json`` says (``running`` until it ends).
#: unchecked: the run ended and nothing that could be checked failed, but some expectations
#: need what the run could not measure (the truth of a real flight).
Status = Literal["running", "passed", "failed", "unchecked", "interrupted", "error"]

#: What ``simulate``, ``run`` and ``ground`` write into their folder (fnmatch patterns relative to
#: it). A new run removes these first, so its results never sit beside an earlier run's (the
#: batch.csv of another batch, the figures of a run that had them); nothing else there is touched.
RUN_FILES = (
    "summary.json",
    "timeseries.csv",
    "batch.csv",
    "xy.png",
    "phases.png",
    "localization_error.png",
    "tracking_error.png",
    "batch_tracking_error.png",
    "tlogs/vehicle_*.tlog",
    "recording.mcap",
    "replay.gif",
    "replay.mp4",
)
#: What a vehicle process writes into its folder.
VEHICLE_FILES = ("summary.json", "steps.csv", "recording.mcap")
#: What the range aid writes into its folder.
TRUTH_FILES = ("truth.csv",)


def prepare_out_dir(out_dir: PathName, files: Sequence[str]) -> Path:
    """Make ``out_dir`` ready for a run, before any work: create it, check that it takes files,
    and remove an earlier run's ``files`` (patterns as in :data:`RUN_FILES`, with their
    temporary twins). Raises :class:`OutputError` naming the folder and the reason."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"output folder {out_dir} is a file, not a folder")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(dir=out_dir, prefix=".write-check-")
        os.close(handle)
        os.unlink(probe)
        for pattern in files:
            folder, _, name = pattern.rpartition("/")
            for path in [*out_dir.glob(pattern), *(out_dir / folder).glob(f".{name}.partial")]:
                if not path.is_dir():
                    path.unlink()
    except OSError as error:
        reason = error.strerror or str(error)
        raise OutputError(f"output folder {out_dir} cannot be written: {reason}") from None
    return out_dir


def versions() -> dict[str, str]:
    """Versions that matter to reproduce a result."""
    return {
        "mission_runner": __version__,
        "numpy": np.__version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
    }


def timeseries_csv(result: SimulationResult, run: int = 0) -> str:
    """CSV text of one run: one row per step k = 0..K."""
    ids = [vehicle.id for vehicle in result.scenario.vehicles]
    header = [
        "step",
        "time_s",
        "target_north_m",
        "target_east_m",
        "tracking_error_m",
        "localization_error_m",
        "phase_spacing_error_rad",
        "consensus_speed_m_s",
        "localization_rms_m",
        "gated_ranges",
    ]
    for vehicle in ids:
        header += [
            f"v{vehicle}_north_m",
            f"v{vehicle}_east_m",
            f"v{vehicle}_phase_rad",
            f"v{vehicle}_cmd_north_m_s",
            f"v{vehicle}_cmd_east_m_s",
            f"v{vehicle}_live",
        ]
    steps = result.commands_m_s.shape[1]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)

    def number(value: float | None) -> str:
        return "" if value is None or not np.isfinite(value) else f"{value:.9g}"

    for k in range(steps + 1):
        last = k == steps
        row = [
            k,
            number(result.times_s[k]),
            number(result.target_m[k, 0]),
            number(result.target_m[k, 1]),
            number(result.tracking_error_m[run, k]),
            None if last else number(result.localization_error_m[run, k]),
            number(result.phase_spacing_error_rad[run, k]),
            None if last else number(result.consensus_speed_m_s[run, k]),
            None if last else number(result.localization_rms_m[run, k]),
            None if last else int(result.gated_ranges[run, k]),
        ]
        for index in range(len(ids)):
            position = result.positions_m[run, k, index]
            command = (None, None) if last else result.commands_m_s[run, k, index]
            row += [
                number(position[0]),
                number(position[1]),
                number(result.phases_rad[run, k, index]),
                number(command[0]),
                number(command[1]),
                int(result.live[run, k, index]),
            ]
        writer.writerow(["" if value is None else value for value in row])
    return buffer.getvalue()


def summary(
    result: SimulationResult,
    *,
    config_path: PathName | None = None,
    wall_time_s: float | None = None,
    vehicles: Mapping[int, Mapping[str, str]] | None = None,
    bus_security: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The summary dict: run 0's metrics, expectations, batch distribution, parameters, versions;
    for a flight, how each vehicle ended (``vehicles``: ``{id: {"state", "detail"}}``) and what
    the bus and the controllers dropped (``bus_security``, see :func:`bus_security`)."""
    scenario = result.scenario
    metrics = run_metrics(result)
    first = {name: _plain(values[0]) for name, values in metrics.items()}
    # Raw values, so that a diverged metric fails as "inf", not as "not measured".
    failures = check_expectations(scenario.expect, {name: v[0] for name, v in metrics.items()})
    document: dict[str, Any] = {
        "status": "failed" if failures else "passed",
        **_about(scenario, config_path, result.runs),
        "metrics": first,
        "expectations": {
            "checked": sorted(name for name in scenario.expect if name in first),
            "passed": not failures,
            "failures": failures,
        },
        **_provenance(scenario),
    }
    if result.runs > 1:
        document["batch"] = {name: distribution(values, name) for name, values in metrics.items()}
        per_run = [
            not check_expectations(
                scenario.expect, {name: values[run] for name, values in metrics.items()}
            )
            for run in range(result.runs)
        ]
        document["batch"]["runs_passing_expectations"] = int(sum(per_run))
    if vehicles is not None:
        document["vehicles"] = {str(i): dict(v) for i, v in sorted(vehicles.items())}
    if bus_security is not None:
        document["bus_security"] = dict(bus_security)
    if wall_time_s is not None:
        document["wall_time_s"] = round(wall_time_s, 4)
    return _finite(document)


def _finite(value: Any) -> Any:
    """``value`` (nested dicts and lists) with every NaN and infinity replaced by None."""
    if isinstance(value, float | np.floating) and not np.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value


def _json_text(document: Mapping[str, Any]) -> str:
    """``document`` as JSON text, never with NaN or Infinity (which JSON does not have: strict
    readers refuse the file): any left are written as null."""
    return json.dumps(_finite(document), indent=2, allow_nan=False) + "\n"


def bus_security(
    messages: Mapping[str, int],
    ranges_rejected: Mapping[int, Mapping[str, int]],
    commands_rejected: Mapping[int, int] | None = None,
) -> dict[str, Any]:
    """What a summary says about dropped input: ``messages``, the bus's received messages
    accepted and dropped by reason (forged, replayed, ...; ``AuthCounters.as_dict``),
    ``ranges_rejected``, per vehicle id the ranges its controller found impossible, by reason,
    and ``commands_rejected``, per vehicle id the neighbours' setpoints in force (step messages)
    it dropped as faster than any vehicle may fly (``CommandGate``)."""
    dropped = sum(count for reason, count in messages.items() if reason != "accepted")
    return {
        "messages": dict(messages),
        "messages_dropped": dropped,
        "ranges_rejected": {str(i): dict(c) for i, c in sorted(ranges_rejected.items())},
        "commands_rejected": {str(i): c for i, c in sorted((commands_rejected or {}).items())},
    }


def bus_security_line(document: Mapping[str, Any]) -> str | None:
    """One line for the terminal when a summary's ``bus_security`` shows dropped input."""
    security = document.get("bus_security")
    if not security:
        return None
    messages = security["messages"]
    ranges = {
        reason: sum(counts.get(reason, 0) for counts in security["ranges_rejected"].values())
        for reason in ("invalid", "beyond_reach", "jump")
    }
    commands = sum(security.get("commands_rejected", {}).values())
    if not security["messages_dropped"] and not any(ranges.values()) and not commands:
        return None
    parts = [f"{count} {reason}" for reason, count in messages.items() if reason != "accepted"]
    impossible = [f"{count} {reason}" for reason, count in ranges.items() if count]
    return (
        f"bus: dropped {security['messages_dropped']} of "
        f"{security['messages_dropped'] + messages.get('accepted', 0)} messages "
        f"({', '.join(p for p in parts if not p.startswith('0 ')) or 'none'}); impossible "
        f"ranges rejected: {', '.join(impossible) or 'none'}"
        + (f"; impossible neighbour commands dropped: {commands}" if commands else "")
    )


def _about(scenario: Scenario, config_path: PathName | None, runs: int) -> dict[str, Any]:
    """What every summary starts with: which scenario, from which file, how long."""
    return {
        "scenario": scenario.name,
        "description": scenario.description,
        "config": None if config_path is None else str(config_path),
        "seed": scenario.seed,
        "runs": runs,
        "steps": scenario.timing.steps,
        "step_s": scenario.timing.step_s,
    }


def _provenance(scenario: Scenario) -> dict[str, Any]:
    """What every summary ends with, to reproduce it: every parameter and the versions."""
    return {
        "parameters": scenario.model_dump(mode="json", exclude={"expect"}),
        "versions": versions(),
    }


def _plain(value: MetricValue) -> float | int | None:
    """A number for JSON: numpy scalars as Python numbers, NaN and infinities as None."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def write_results(
    result: SimulationResult,
    out_dir: PathName,
    *,
    config_path: PathName | None = None,
    wall_time_s: float | None = None,
    figures: bool = True,
    vehicles: Mapping[int, Mapping[str, str]] | None = None,
    records: Mapping[int, Sequence[StepRecord]] | None = None,
    start_s: float = 0.0,
    logs: Sequence[LogLine] = (),
    bus_security: Mapping[str, Any] | None = None,
    figure_process: FigureProcess | None = None,
    recording_process: RecordingProcess | None = None,
) -> dict[str, Any]:
    """Write timeseries.csv, summary.json, recording.mcap and (optionally) the figures into
    ``out_dir``. A flight passes its controllers' ``records`` and ``start_s`` (the mission clock
    at k = 0) for the recording; ``logs`` are the run's log lines. With ``figure_process``
    (``recording_process``) the figures (the recording) are written there while this writes the
    rest; summary.json is written last, once they are all in.

    Returns the summary dict.
    """
    from .recording import RECORDING, write_recording  # noqa: PLC0415 - foxglove loads a library

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    document = summary(
        result,
        config_path=config_path,
        wall_time_s=wall_time_s,
        vehicles=vehicles,
        bus_security=bus_security,
    )
    drawing = figure_process if figures else None
    if drawing is not None:
        drawing.submit(result, out_dir)
    expectations = document["expectations"]
    verdict = None
    if expectations["checked"]:
        verdict = "expectations: " + ("PASS" if expectations["passed"] else "FAIL")
        verdict += "".join(f"; failed: {failure}" for failure in expectations["failures"])
    recording: dict[str, Any] = {
        "records": records,
        "start_s": start_s,
        "logs": logs,
        "verdict": verdict,
    }
    if recording_process is not None:
        recording_process.submit(result, out_dir / RECORDING, **recording)
    write_atomic(out_dir / "timeseries.csv", timeseries_csv(result))
    if recording_process is None:
        write_recording(result, out_dir / RECORDING, **recording)
    if result.runs > 1:
        write_atomic(out_dir / "batch.csv", batch_csv(result))
    if recording_process is not None:
        recording_process.collect(result, out_dir / RECORDING)
    if drawing is not None:
        document["figures"] = drawing.collect(result, out_dir)
    elif figures:
        from .figures import write_figures  # noqa: PLC0415 - matplotlib is slow to import

        document["figures"] = write_figures(result, out_dir)
    write_atomic(out_dir / "summary.json", _json_text(document))
    return document


def batch_csv(result: SimulationResult) -> str:
    """One row per run with its headline metrics."""
    metrics = run_metrics(result)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["run", *metrics])
    for run in range(result.runs):
        writer.writerow([run, *(f"{values[run]:.9g}" for values in metrics.values())])
    return buffer.getvalue()


def write_vehicle_run(
    run: VehicleRun,
    out_dir: PathName,
    *,
    config_path: PathName | None = None,
    status: Status | None = None,
    scenario: Scenario | None = None,
    logs: Sequence[LogLine] = (),
) -> dict[str, Any]:
    """One vehicle process's outputs: ``steps.csv`` (per step: state, phase, command, consensus,
    neighbours used, lateness of the setpoint, odometry, peers whose range the estimator gated as
    an outlier, the target as the vehicle knew it, every estimate), ``recording.mcap`` (the same
    and ``logs``, see :mod:`.recording`) and ``summary.json`` (how the process ended, final
    state, counts including gated ranges, the autopilot's clock fit, parameters applied).
    Written atomically."""
    from .recording import RECORDING, write_vehicle_recording  # noqa: PLC0415 - foxglove, mcap

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(out_dir / "steps.csv", _steps_csv(run.records))
    write_vehicle_recording(
        run.vehicle_id, run.records, out_dir / RECORDING, scenario=scenario, logs=logs
    )
    document = _vehicle_summary(run, config_path=config_path, status=status)
    write_atomic(out_dir / "summary.json", _json_text(document))
    return document


#: steps.csv's columns before the estimates (``estimate_<peer>_<north|east>_m``).
_STEP_COLUMNS = (
    "step",
    "time_s",
    "state",
    "phase_rad",
    "velocity_north_m_s",
    "velocity_east_m_s",
    "velocity_down_m_s",
    "consensus_north_m_s",
    "consensus_east_m_s",
    "neighbours_used",
    "setpoint_lateness_s",
    "odometry_lateness_s",
    "message_lateness_s",
    "inputs_lateness_s",
    "odometry_north_m",
    "odometry_east_m",
    "odometry_down_m",
    "gated_ranges",
    "target",
)


def _steps_csv(records: Sequence[StepRecord]) -> str:
    """A vehicle's ``steps.csv``: one row per step record, every peer ever estimated a pair of
    estimate columns (empty at the steps without that estimate)."""
    peers = sorted({peer for record in records for peer in record.estimates_m})
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(
        [
            *_STEP_COLUMNS,
            *(f"estimate_{peer}_{axis}_m" for peer in peers for axis in ("north", "east")),
        ]
    )
    for record in records:
        writer.writerow(_step_row(record, peers))
    return buffer.getvalue()


def _step_row(record: StepRecord, peers: Sequence[int]) -> list[object]:
    """``record`` as a row of steps.csv, with the estimates of ``peers``."""
    estimates = []
    for peer in peers:
        value = record.estimates_m.get(peer)
        estimates += ["", ""] if value is None else [f"{value[0]:.6f}", f"{value[1]:.6f}"]
    return [
        record.step,
        f"{record.time_s:.6f}",
        record.state,
        f"{record.phase_rad:.9f}",
        *(f"{v:.6f}" for v in record.velocity_ned_m_s),
        *(f"{v:.6f}" for v in record.consensus_m_s),
        " ".join(str(peer) for peer in record.neighbours_used),
        f"{record.setpoint_sent_s - record.time_s:.6f}",
        *(
            f"{at_s - record.time_s:.6f}"
            for at_s in (record.odometry_ready_s, record.message_sent_s, record.inputs_ready_s)
        ),
        *(f"{v:.6f}" for v in record.odometry_m),
        " ".join(str(peer) for peer in record.gated),
        record.target,
        *estimates,
    ]


def _vehicle_summary(
    run: VehicleRun, *, config_path: PathName | None = None, status: Status | None = None
) -> dict[str, Any]:
    """What a vehicle process's ``summary.json`` holds (see :func:`write_vehicle_run`)."""
    states: dict[str, int] = {}
    for record in run.records:
        states[record.state] = states.get(record.state, 0) + 1

    def after_t_k(at_s: Callable[[StepRecord], float]) -> dict[str, float] | None:
        """p50/p99/max of ``at_s(record) - t_k`` over the steps that got that far [s]."""
        values = [at_s(r) - r.time_s for r in run.records if np.isfinite(at_s(r))]
        if not values:
            return None
        return {
            "p50": float(np.percentile(values, 50)),
            "p99": float(np.percentile(values, 99)),
            "max": float(np.max(values)),
        }

    return {
        "status": status,
        "vehicle_id": run.vehicle_id,
        "mission_id": run.mission_id,
        "state": run.state,
        "detail": run.detail,
        "steps": len(run.records),
        "steps_by_state": states,
        "skipped_steps": run.skipped_steps,
        "gated_ranges": sum(len(record.gated) for record in run.records),
        "start_s": run.start_s,
        "mission_clock_rate": run.clock_rate,
        "autopilot_clock_rate": run.autopilot_clock_rate,
        "setpoints_scale_bounded": run.setpoints_scale_bounded,
        "autopilot_clock_residual_s": run.clock_residual_s,
        "setpoint_lateness_s": after_t_k(lambda r: r.setpoint_sent_s),
        # Where that lateness comes from, in the order a step goes: the own odometry at t_k in,
        # the own step message out, every input in (or the deadline).
        "step_timing_after_t_k_s": {
            "odometry": after_t_k(lambda r: r.odometry_ready_s),
            "message_sent": after_t_k(lambda r: r.message_sent_s),
            "inputs": after_t_k(lambda r: r.inputs_ready_s),
        },
        "autopilot_params": run.params,
        "bus_security": bus_security(
            run.bus_messages,
            {run.vehicle_id: run.ranges_rejected},
            {run.vehicle_id: run.commands_rejected},
        ),
        "config": None if config_path is None else str(config_path),
        "versions": versions(),
    }


class RunSummary:
    """``summary.json`` of one run in ``out_dir``, however the run ends.

    Entering writes ``status: running``; :meth:`write_results` writes the results (``passed`` or
    ``failed``); leaving without them writes ``interrupted`` (KeyboardInterrupt: SIGINT, or
    SIGTERM as the command line turns it) or ``error`` (with the error's message), with what is
    known: the scenario, every parameter and ``steps_done`` (set it as the run goes)::

        with RunSummary(out_dir, scenario, config_path=path) as record:
            result = simulate(scenario)
            record.write_results(result)
    """

    def __init__(
        self, out_dir: Path, scenario: Scenario, *, config_path: PathName | None, runs: int = 1
    ) -> None:
        self.out_dir = out_dir
        self.steps_done = 0
        self.document: dict[str, Any] | None = None
        self._scenario = scenario
        self._config_path = config_path
        self._runs = runs

    def __enter__(self) -> RunSummary:
        self._write("running", "")
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if self.document is not None:
            return
        if kind is not None and issubclass(kind, KeyboardInterrupt):
            status: Status = "interrupted"
            detail = "stopped by SIGINT or SIGTERM"
        else:
            status = "error"
            detail = "ended without results" if error is None else error_reason(error)
        try:
            self.finish(status, detail)
        except OSError as failure:  # the run's own error is the one to report
            logger.error("could not write %s/summary.json: %s", self.out_dir, failure)

    def write_results(
        self,
        result: SimulationResult,
        *,
        wall_time_s: float | None = None,
        figures: bool = True,
        vehicles: Mapping[int, Mapping[str, str]] | None = None,
        records: Mapping[int, Sequence[StepRecord]] | None = None,
        start_s: float = 0.0,
        logs: Sequence[LogLine] = (),
        bus_security: Mapping[str, Any] | None = None,
        figure_process: FigureProcess | None = None,
        recording_process: RecordingProcess | None = None,
    ) -> dict[str, Any]:
        """:func:`write_results` into this run's folder; returns the summary dict."""
        self.document = write_results(
            result,
            self.out_dir,
            config_path=self._config_path,
            wall_time_s=wall_time_s,
            figures=figures,
            vehicles=vehicles,
            records=records,
            start_s=start_s,
            logs=logs,
            bus_security=bus_security,
            figure_process=figure_process,
            recording_process=recording_process,
        )
        return self.document

    def finish(self, status: Status, detail: str = "", **known: Any) -> None:
        """Write a summary without results: ``status``, ``detail`` and what is known (``known``:
        more top-level entries, e.g. the metrics and expectations that could be checked)."""
        self.document = self._write(status, detail, known)

    def _write(
        self, status: Status, detail: str, known: Mapping[str, Any] | None = None
    ) -> dict[str, Any]:
        document = {
            "status": status,
            "detail": detail,
            **_about(self._scenario, self._config_path, self._runs),
            "steps_done": self.steps_done,
            **(known or {}),
            **_provenance(self._scenario),
        }
        write_atomic(self.out_dir / "summary.json", _json_text(document))
        return document

"""Scoring a flight against ground truth, the same way for every flight path: the in-process
mission (the emulator's world samples) and vehicle processes (the range aid's truth from SIH or the
emulator, and each vehicle's ``steps.csv``). The truth is used only here, after the fact; no
controller ever reads it.
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..enclosing.target import OBSERVED, STATUS_NAMES
from ..metrics import SimulationResult, closest_pair, score
from ..paths import write_atomic
from ..records import FORMATION_STATES, STALE_STATES, ControllerState, StepRecord, TruthSample

if TYPE_CHECKING:
    from ..config import Scenario
    from ..paths import PathName


def estimate_errors(
    ids: Sequence[int], records: Mapping[int, StepRecord], sample: TruthSample
) -> list[float]:
    """|phat_ij - p_ij| of every estimate in ``records`` against truth ``sample``."""
    errors = []
    for vehicle_id, record in records.items():
        own = sample.positions_m[ids.index(vehicle_id)]
        for peer, estimate in record.estimates_m.items():
            other = sample.target_m if peer == 0 else sample.positions_m[ids.index(peer)]
            errors.append(float(np.hypot(*(estimate - (own - other)))))
    return errors


def worst_estimate(
    ids: Sequence[int], records: Mapping[int, StepRecord], sample: TruthSample
) -> float:
    """max |phat_ij - p_ij| over the estimates in ``records`` against truth ``sample``."""
    return max(estimate_errors(ids, records, sample), default=0.0)


def score_flight(
    scenario: Scenario,
    samples: Sequence[TruthSample],
    records: Mapping[int, Sequence[StepRecord]],
    disarmed: int | None,
    *,
    final_phases: Mapping[int, float] | None = None,
    disarmed_in_air: int | None = None,
) -> SimulationResult:
    """Score a flight from truth samples (``step``, ``time_s``, ``target_m (2,)``,
    ``positions_m (n, 2)``, ``alive (n,)``) and the controllers' records ``{id: [StepRecord]}``;
    ``disarmed``: vehicles landed and disarmed at the end (None: unknown; a vehicle disarmed in
    the air fell, it did not land: ``disarmed_in_air`` counts those); ``final_phases``: each
    controller's phase after its last step, ``{id: rad}``.

    A vehicle counts in the formation at step k when it is alive and its controller followed
    the law at k (not holding on stale data, not failed safe; a formation that lost its target
    still counts, so that the tracking error shows how far off it is). The target's status at
    step k is the worst any controller had (lost if any declared it lost).
    """
    steps = scenario.timing.steps
    samples = samples[: steps + 1]
    ids = [vehicle.id for vehicle in scenario.vehicles]
    columns = _RecordColumns.empty(len(samples), len(ids))
    truth_by_step = {s.step: s for s in samples}
    for column, vehicle_id in enumerate(ids):
        for record in records.get(vehicle_id, []):
            k = record.step
            if k >= len(samples):
                continue
            last = k == len(samples) - 1  # no command after the last sample
            errors = [] if last else estimate_errors(ids, {vehicle_id: record}, truth_by_step[k])
            columns.add(column, record, errors)
        final = (final_phases or {}).get(vehicle_id)
        if final is not None and len(samples) == steps + 1:
            columns.end_with(column, final)
    positions = np.stack([s.positions_m for s in samples])[None]
    live = np.stack([s.alive for s in samples])[None] & columns.following
    gaps = positions[..., :, None, :] - positions[..., None, :, :]
    distance = np.sqrt(np.sum(gaps * gaps, axis=-1))
    out = {
        "positions_m": positions,
        "phases_rad": np.where(live, columns.phases, np.nan),
        "commands_m_s": columns.commands,
        "live": live,
        "localization_error_m": columns.localization,
        "localization_rms_m": columns.localization_rms(),
        "gated_ranges": columns.gated,
        "consensus_speed_m_s": columns.consensus,
        "separation_m": closest_pair(distance, live),
        "target_status": columns.target_status,
    }
    times = np.array([s.time_s for s in samples]) - samples[0].time_s
    target = np.stack([s.target_m for s in samples])
    extra = _extra_metrics(live, records, steps, disarmed, disarmed_in_air)
    return score(scenario, times, target, out, extra)


@dataclass
class _RecordColumns:
    """What the controllers' records say, step by vehicle column, for :func:`score_flight`:
    ``count`` truth samples, so ``count - 1`` steps of commands."""

    phases: NDArray[np.float64]
    following: NDArray[np.bool_]
    commands: NDArray[np.float64]
    consensus: NDArray[np.float64]
    localization: NDArray[np.float64]
    square_errors: list[list[float]]
    gated: NDArray[np.int64]
    target_status: NDArray[np.int8]

    @classmethod
    def empty(cls, count: int, n: int) -> _RecordColumns:
        steps = max(count - 1, 0)
        return cls(
            phases=np.full((1, count, n), np.nan),
            following=np.zeros((1, count, n), dtype=bool),
            commands=np.zeros((1, steps, n, 2)),
            consensus=np.zeros((1, steps)),
            localization=np.zeros((1, steps)),
            square_errors=[[] for _ in range(steps)],
            gated=np.zeros((1, steps), dtype=np.int64),
            target_status=np.full((1, steps), OBSERVED, dtype=np.int8),
        )

    def add(self, column: int, record: StepRecord, errors: list[float]) -> None:
        """Vehicle ``column``'s record of its step (within the samples); ``errors``: its
        estimates' errors against the truth of that step (none at the last sample)."""
        k = record.step
        self.phases[0, k, column] = record.phase_rad
        self.following[0, k, column] = record.state in FORMATION_STATES
        if k >= self.commands.shape[1]:
            return
        self.commands[0, k, column] = record.velocity_ned_m_s[:2]
        self.consensus[0, k] = max(self.consensus[0, k], float(np.hypot(*record.consensus_m_s)))
        self.localization[0, k] = max(self.localization[0, k], *errors, 0.0)
        self.square_errors[k] += [error * error for error in errors]
        self.gated[0, k] += len(record.gated)
        if record.target:
            status = STATUS_NAMES.index(record.target)
            self.target_status[0, k] = max(self.target_status[0, k], status)

    def end_with(self, column: int, final_phase: float) -> None:
        """The phase after the last step, where no record has it, as the last step followed."""
        if np.isnan(self.phases[0, -1, column]):
            self.phases[0, -1, column] = final_phase
            self.following[0, -1, column] = self.following[0, -2, column]

    def localization_rms(self) -> NDArray[np.float64]:
        """Per step, the RMS of every estimate's error (0 where none was recorded)."""
        return np.array(
            [[np.sqrt(np.mean(squares)) if squares else 0.0 for squares in self.square_errors]]
        )


def _extra_metrics(
    live: NDArray[np.bool_],
    records: Mapping[int, Sequence[StepRecord]],
    steps: int,
    disarmed: int | None,
    disarmed_in_air: int | None,
) -> dict[str, NDArray[np.int64]]:
    extra = {
        "vehicles_in_formation_at_end": np.array([int(live[0, -1].sum())]),
        # Steps not flown by the law for want of fresh data (held or skipped): a formation that
        # froze for 30 s under a flood still ended in formation and was reported "done".
        "steps_on_stale_data": np.array(
            [sum(r.state in STALE_STATES for rs in records.values() for r in rs[:steps])]
        ),
    }
    if disarmed is not None:
        extra["vehicles_disarmed_at_end"] = np.array([disarmed])
    if disarmed_in_air is not None:
        extra["vehicles_disarmed_in_air"] = np.array([disarmed_in_air])
    return extra


def write_truth_csv(samples: Iterable[TruthSample], ids: Sequence[int], path: PathName) -> None:
    """Truth samples as CSV: step, time_s, target_north_m, target_east_m, then per vehicle
    ``v<id>_north_m``, ``v<id>_east_m`` (empty where unknown)."""

    lines = [
        ",".join(
            ["step", "time_s", "target_north_m", "target_east_m"]
            + [f"v{i}_{axis}_m" for i in ids for axis in ("north", "east")]
        )
    ]
    for sample in samples:
        row = [str(sample.step), f"{sample.time_s:.6f}", *(f"{v:.6f}" for v in sample.target_m)]
        for position, alive in zip(sample.positions_m, sample.alive, strict=True):
            row += [f"{v:.6f}" for v in position] if alive else ["", ""]
        lines.append(",".join(row))
    write_atomic(path, "\n".join(lines) + "\n")


#: A vehicle's truth missing for at most this many steps between two known positions is
#: interpolated (:func:`fill_truth_gaps`); a longer gap, or one with no end, stays unknown.
TRUTH_GAP_STEPS = 8


def fill_truth_gaps(
    samples: Sequence[TruthSample], max_gap_steps: int = TRUTH_GAP_STEPS
) -> list[TruthSample]:
    """``samples`` (one per step, in order) with each vehicle's unknown positions filled in
    linearly between the known ones around them, for gaps of at most ``max_gap_steps``.

    The range aid writes no position for a step it skipped (past its deadline on a loaded
    machine: 4 of 1280 vehicle-steps in a 320-step flight). Left unknown, a step where every
    vehicle's position is missing put the formation's centre at the origin: a 30.7 m tracking
    error at one step gave a tail RMS of 3.4 m to a formation 0.06-0.12 m off. A vehicle
    lost for good has no later position, so its gap is not filled."""
    if not samples:
        return []
    positions = np.stack([s.positions_m for s in samples])  # (steps, n, 2)
    alive = np.stack([s.alive for s in samples])  # (steps, n)
    for column in range(alive.shape[1]):
        known = np.flatnonzero(alive[:, column])
        for before, after in itertools.pairwise(known):
            if 1 < after - before <= max_gap_steps + 1:
                k = np.arange(before + 1, after)
                weight = ((k - before) / (after - before))[:, None]
                positions[k, column] = (1 - weight) * positions[before, column] + weight * (
                    positions[after, column]
                )
                alive[k, column] = True
    return [
        dataclasses.replace(sample, positions_m=positions[i], alive=alive[i])
        for i, sample in enumerate(samples)
    ]


def read_truth_csv(path: PathName, ids: Sequence[int]) -> list[TruthSample]:
    """The samples written by :func:`write_truth_csv`."""
    samples = []
    with open(path, newline="", encoding="utf-8") as handle:
        for row in csv.DictReader(handle):
            positions, alive = [], []
            for i in ids:
                north, east = row[f"v{i}_north_m"], row[f"v{i}_east_m"]
                alive.append(north != "")
                positions.append((float(north or "nan"), float(east or "nan")))
            samples.append(
                TruthSample(
                    int(row["step"]),
                    float(row["time_s"]),
                    np.array([float(row["target_north_m"]), float(row["target_east_m"])]),
                    np.array(positions),
                    np.array(alive),
                )
            )
    return samples


def _ned(row: Mapping[str, str], column: str) -> tuple[float, float, float]:
    """The north, east and down columns ``column.format(axis)`` of a CSV row, as numbers."""
    north, east, down = (float(row[column.format(axis)]) for axis in ("north", "east", "down"))
    return north, east, down


def read_steps_csv(path: PathName) -> list[StepRecord]:
    """A vehicle process's ``steps.csv`` back as :class:`StepRecord` objects."""
    records = []
    with open(path, newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        columns = reader.fieldnames or ()  # None only for an empty file: no steps
        peers = sorted(
            {int(name.split("_")[1]) for name in columns if name.startswith("estimate_")}
        )
        for row in reader:
            estimates = {}
            for peer in peers:
                north = row[f"estimate_{peer}_north_m"]
                if north != "":
                    estimates[peer] = np.array(
                        [float(north), float(row[f"estimate_{peer}_east_m"])]
                    )
            used = tuple(int(p) for p in row["neighbours_used"].split())
            gated = tuple(int(p) for p in (row.get("gated_ranges") or "").split())
            records.append(
                StepRecord(
                    step=int(row["step"]),
                    time_s=float(row["time_s"]),
                    state=ControllerState(row["state"]),
                    velocity_ned_m_s=_ned(row, "velocity_{}_m_s"),
                    consensus_m_s=(
                        float(row["consensus_north_m_s"]),
                        float(row["consensus_east_m_s"]),
                    ),
                    phase_rad=float(row["phase_rad"]),
                    neighbours_used=used,
                    estimates_m=estimates,
                    setpoint_sent_s=float(row["time_s"]) + float(row["setpoint_lateness_s"]),
                    odometry_m=_ned(row, "odometry_{}_m"),
                    gated=gated,
                    target=row.get("target") or "",
                )
            )
    return records


def merge_mission(scenario: Scenario, mission_dir: PathName) -> SimulationResult | None:
    """Score a mission of vehicle processes from what they wrote under ``mission_dir``
    (``vehicle_<id>/steps.csv``, ``truth/truth.csv``). Returns a SimulationResult, or None when
    the truth is not there (a mission without a simulator has no truth to score against). Short
    gaps in the truth are interpolated (:func:`fill_truth_gaps`)."""
    mission_dir = Path(mission_dir)
    ids = [v.id for v in scenario.vehicles]
    truth = mission_dir / "truth" / "truth.csv"
    if not truth.exists():
        return None
    records = mission_records(mission_dir, ids)
    return score_flight(scenario, fill_truth_gaps(read_truth_csv(truth, ids)), records, None)


def mission_records(mission_dir: PathName, ids: Iterable[int]) -> dict[int, list[StepRecord]]:
    """Every vehicle's records from its ``vehicle_<id>/steps.csv`` under ``mission_dir`` (those
    that wrote one)."""
    records = {}
    for vehicle_id in ids:
        steps = Path(mission_dir) / f"vehicle_{vehicle_id}" / "steps.csv"
        if steps.exists():
            records[vehicle_id] = read_steps_csv(steps)
    return records

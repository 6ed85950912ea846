"""Figures like the paper's: XY paths, relative phases, localization error, tracking error.

Rendered with matplotlib's non-interactive Agg backend straight to PNG files.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import io

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from .paths import PathName, write_atomic
from .scenario import omega_of

if TYPE_CHECKING:
    from collections.abc import Sequence

    from .metrics import SimulationResult, SweepPoint


def write_figures(result: SimulationResult, out_dir: PathName, run: int = 0) -> list[str]:
    """Write the figures of run ``run`` (and the batch band if there are several runs).

    Returns the list of file names written.
    """
    out_dir = Path(out_dir)
    names = []
    for name, draw in (
        ("xy.png", _xy),
        ("phases.png", _phases),
        ("localization_error.png", _localization),
        ("tracking_error.png", _tracking),
    ):
        figure = draw(result, run)
        _save(figure, out_dir / name)
        names.append(name)
    if result.runs > 1:
        _save(_batch(result), out_dir / "batch_tracking_error.png")
        names.append("batch_tracking_error.png")
    return names


def _save(figure: Figure, path: Path) -> None:

    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=120)
    plt.close(figure)
    write_atomic(path, buffer.getvalue())


def _labels(result: SimulationResult) -> list[str]:
    return [f"vehicle {vehicle.id}" for vehicle in result.scenario.vehicles]


def _xy(result: SimulationResult, run: int) -> Figure:
    figure, axes = plt.subplots(figsize=(7, 5.5), layout="constrained")
    positions, live = result.positions_m[run], result.live[run]
    colours = plt.cm.tab10(np.arange(positions.shape[1]) % 10)
    for index, label in enumerate(_labels(result)):
        path = np.where(live[:, index, None], positions[:, index], np.nan)
        axes.plot(path[:, 1], path[:, 0], lw=0.8, color=colours[index], label=label)
        axes.plot(*positions[0, index, ::-1], "o", mfc="none", color=colours[index])
        alive = np.flatnonzero(live[:, index])
        if alive.size:
            end = positions[alive[-1], index]
            marker = "o" if alive[-1] == len(live) - 1 else "x"
            axes.plot(end[1], end[0], marker, color=colours[index], ms=8)
    count = np.maximum(live.sum(axis=-1, keepdims=True), 1)
    centroid = np.sum(np.where(live[..., None], positions, 0), axis=1) / count
    axes.plot(result.target_m[:, 1], result.target_m[:, 0], "k--", lw=1.5, label="target")
    axes.plot(centroid[:, 1], centroid[:, 0], color="crimson", lw=1.2, label="centroid")
    axes.plot(*result.target_m[-1, ::-1], "k^", ms=9)
    axes.set_xlabel("east [m]")
    axes.set_ylabel("north [m]")
    axes.set_aspect("equal", adjustable="datalim")
    axes.set_title(f"{result.scenario.name}: paths (hollow = start, x = lost)")
    axes.legend(fontsize=8, loc="best")
    axes.grid(alpha=0.3)
    return figure


def _phases(result: SimulationResult, run: int) -> Figure:
    figure, axes = plt.subplots(figsize=(7, 4), layout="constrained")
    omega = np.array([omega_of(result.scenario, v) for v in result.scenario.vehicles])
    relative = result.phases_rad[run] - result.times_s[:, None] * omega
    relative = np.where(result.live[run], relative, np.nan)
    for index, label in enumerate(_labels(result)):
        axes.plot(result.times_s, relative[:, index], label=label)
    axes.set_xlabel("time [s]")
    axes.set_ylabel(r"$\theta_i - kT\omega_i$ [rad]")
    axes.set_title("relative phases")
    axes.legend(fontsize=8)
    axes.grid(alpha=0.3)
    return figure


def _log_plot(
    times: NDArray[np.float64], values: NDArray[np.float64], title: str, ylabel: str
) -> Figure:
    figure, axes = plt.subplots(figsize=(7, 4), layout="constrained")
    axes.semilogy(times, np.maximum(values, 1e-16))
    axes.set_xlabel("time [s]")
    axes.set_ylabel(ylabel)
    axes.set_title(title)
    axes.grid(alpha=0.3, which="both")
    return figure


def _localization(result: SimulationResult, run: int) -> Figure:
    return _log_plot(
        result.times_s[:-1],
        result.localization_error_m[run],
        r"relative localization error $\max_{ij} \|\hat p_{ij} - p_{ij}\|$",
        "error [m]",
    )


def _tracking(result: SimulationResult, run: int) -> Figure:
    return _log_plot(
        result.times_s,
        result.tracking_error_m[run],
        r"formation tracking error $\|\bar p\|$ (centroid to target)",
        "error [m]",
    )


def _batch(result: SimulationResult) -> Figure:
    figure, axes = plt.subplots(figsize=(7, 4), layout="constrained")
    error = np.maximum(result.tracking_error_m, 1e-16)
    low, median, high = np.percentile(error, [5, 50, 95], axis=0)
    axes.fill_between(result.times_s, low, high, alpha=0.3, label="5-95 %")
    axes.semilogy(result.times_s, median, label="median")
    axes.semilogy(result.times_s, error.max(axis=0), lw=0.7, color="crimson", label="worst")
    axes.set_xlabel("time [s]")
    axes.set_ylabel("tracking error [m]")
    axes.set_title(f"tracking error over {result.runs} runs")
    axes.legend(fontsize=8)
    axes.grid(alpha=0.3, which="both")
    return figure


def write_sweep_figure(points: Sequence[SweepPoint], metric: str, path: PathName) -> None:
    """``metric`` against the first swept path's values: the median over runs with the 5-95 and
    25-75 percentile bands, one line per combination of the other paths."""
    paths = list(points[0].values)
    first, others = paths[0], paths[1:]
    groups: dict[str, list[SweepPoint]] = {}
    for point in points:
        label = ", ".join(f"{p}={point.values[p]}" for p in others) or metric
        groups.setdefault(label, []).append(point)
    numeric = all(isinstance(p.values[first], int | float) for p in points)
    figure, axes = plt.subplots(figsize=(7, 4.5))
    for label, group in groups.items():
        ticks = [p.values[first] for p in group]
        x = np.asarray(ticks, dtype=float) if numeric else np.arange(len(group), dtype=float)
        values = [np.asarray(p.metrics[metric], dtype=float) for p in group]
        low, quarter, median, three, high = np.array(
            [np.percentile(v, [5, 25, 50, 75, 95]) for v in values]
        ).T
        (line,) = axes.plot(x, median, marker="o", label=label)
        axes.fill_between(x, low, high, color=line.get_color(), alpha=0.15, linewidth=0)
        axes.fill_between(x, quarter, three, color=line.get_color(), alpha=0.3, linewidth=0)
        if not numeric:
            axes.set_xticks(x, [str(t) for t in ticks])
    axes.set_xlabel(first)
    axes.set_ylabel(metric)
    runs = len(next(iter(points[0].metrics.values())))
    axes.set_title(f"median, 25-75 % and 5-95 % of {runs} runs")
    if len(groups) > 1:
        axes.legend(fontsize="small")
    axes.grid(True, alpha=0.3)
    _save(figure, Path(path))

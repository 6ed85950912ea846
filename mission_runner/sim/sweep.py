"""Parameter sweeps over the batched simulator: every combination of ``--set path=v1,v2`` values,
each simulated ``runs`` times, every metric's distribution per combination.

A path is the YAML path a user edits (``algorithm.forgetting_factor``,
``vehicles[0].speed_limit_m_s``, ``vehicles[*].speed_limit_m_s`` for every vehicle); a value is
read as YAML (``0.98``, ``ekf``, ``null``). Each combination is validated like a scenario file,
so a bad value is reported at its path before anything runs.
Each combination is then one pure function call (:func:`combination_metrics`), run here or on a
Dask cluster by an executor (``executors.py``).
"""

from __future__ import annotations

import copy
import csv
import io
import itertools
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from ..checks import validate_scenario
from ..config import Scenario
from ..errors import ConfigError
from ..metrics import SweepPoint, run_metrics
from .executors import Executor, InProcess
from .simulator import check_memory, simulate

_PART = re.compile(r"([^.\[\]]+)|\[(\d+|\*)\]")


@dataclass(frozen=True)
class Axis:
    """One ``--set``: the YAML path and the values it takes."""

    path: str
    values: tuple[Any, ...]

    @classmethod
    def parse(cls, text: str) -> Axis:
        """``path=v1,v2,...`` -> Axis; values read as YAML scalars. Raises ValueError."""
        path, equals, values = text.partition("=")
        if not equals or not path or not values:
            raise ValueError(f"expected PATH=V1,V2,... (got {text!r})")
        _parts(path)
        return cls(path, tuple(yaml.safe_load(value) for value in values.split(",")))


def _parts(path: str) -> list[str | int]:
    """``vehicles[0].speed_limit_m_s`` -> ``["vehicles", 0, "speed_limit_m_s"]`` (``*``: all)."""
    parts: list[str | int] = []
    position = 0
    for match in _PART.finditer(path):
        if match.start() != position and path[position : match.start()] != ".":
            raise ValueError(f"not a YAML path: {path!r}")
        key, index = match.groups()
        parts.append(key if key is not None else (index if index == "*" else int(index)))
        position = match.end()
    if position != len(path) or not parts or not isinstance(parts[0], str):
        raise ValueError(f"not a YAML path: {path!r}")
    return parts


def set_path(data: dict[str, Any], path: str, value: Any) -> None:
    """Set ``path`` in the parsed scenario ``data`` to ``value`` (creating mappings on the way;
    ``[*]`` sets every item of a list). Raises KeyError naming the path when it leads nowhere."""
    parts = _parts(path)

    def walk(node: Any, rest: list[str | int]) -> None:
        key, *more = rest
        if key == "*":
            if not isinstance(node, list) or not more:
                raise KeyError(f"{path}: [*] needs a list and a field after it")
            for item in node:
                walk(item, more)
            return
        if isinstance(key, int):
            if not isinstance(node, list) or key >= len(node):
                raise KeyError(f"{path}: no item [{key}]")
        elif not isinstance(node, dict):
            raise KeyError(f"{path}: {key!r} is not under a mapping")
        if not more:
            node[key] = value
            return
        if isinstance(node, dict) and node.get(key) is None:
            node[key] = {}
        walk(node[key], more)

    walk(data, parts)


@dataclass(frozen=True)
class Combination:
    """One combination of a sweep's values, ready to run: the validated scenario and how many
    runs to batch. What it computes depends on nothing else (the seed is in the scenario)."""

    values: dict[str, Any]
    scenario: Scenario
    runs: int
    name: str  # its file, values and seed, for an error about it

    @property
    def steps(self) -> int:
        return self.scenario.timing.steps


def combinations(
    scenario: Scenario, axes: Sequence[Axis], runs: int, source: str = "<scenario>"
) -> list[Combination]:
    """Every combination of ``axes`` values applied to ``scenario``, each validated as a file
    would be (a :class:`ConfigError` names the path and the combination) and its memory checked."""
    base = scenario.model_dump(mode="json")
    found = []
    for combination in itertools.product(*(axis.values for axis in axes)):
        data = copy.deepcopy(base)
        values = {axis.path: value for axis, value in zip(axes, combination, strict=True)}
        for path, value in values.items():
            try:
                set_path(data, path, value)
            except KeyError as error:
                raise ConfigError(source, [(path, str(error.args[0]))]) from None
        label = f"{source} with " + ", ".join(f"{path}={value}" for path, value in values.items())
        point = validate_scenario(data, label)
        check_memory(point, runs, source)
        found.append(Combination(values, point, runs, f"{label} (seed {point.seed})"))
    return found


def combination_metrics(combination: Combination) -> dict[str, NDArray[Any]]:
    """Every metric of ``combination``'s runs, ``{name: (runs,)}``: a pure function of it, so
    that a worker elsewhere computes what this process would."""
    return run_metrics(simulate(combination.scenario, runs=combination.runs))


def run_sweep(
    found: Sequence[Combination],
    executor: Executor | None = None,
    on_point: Callable[[int, int], None] | None = None,
) -> list[SweepPoint]:
    """Simulate every combination on ``executor`` (default: here, one after another); the
    points come in ``found``'s order wherever and in whatever order they ran."""
    metrics = (executor or InProcess()).map_in_order(
        combination_metrics, found, [c.name for c in found], on_point
    )
    return [SweepPoint(c.values, m) for c, m in zip(found, metrics, strict=True)]


def sweep(
    scenario: Scenario,
    axes: Sequence[Axis],
    runs: int,
    source: str = "<scenario>",
    *,
    on_point: Callable[[int, int], None] | None = None,
    executor: Executor | None = None,
) -> list[SweepPoint]:
    """Simulate every combination of ``axes`` values ``runs`` times. Every combination is
    validated first (a :class:`ConfigError` names the path and the combination)."""
    return run_sweep(combinations(scenario, axes, runs, source), executor, on_point)


def sweep_csv(points: Sequence[SweepPoint]) -> str:
    """One row per combination: its values, then per metric the median, p5 and p95 over runs."""
    if not points:
        return ""
    paths = list(points[0].values)
    names = list(points[0].metrics)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(
        ["runs", *paths, *(f"{name}_{stat}" for name in names for stat in ("median", "p5", "p95"))]
    )
    for point in points:
        row: list[Any] = [len(next(iter(point.metrics.values())))]
        row += [point.values[path] for path in paths]
        for name in names:
            values = np.asarray(point.metrics[name], dtype=float)
            row += [f"{v:.6g}" for v in np.percentile(values, [50, 5, 95])]
        writer.writerow(row)
    return buffer.getvalue()

"""Parameter sweeps over the batched simulator: every combination of ``--set path=v1,v2`` values,
each simulated ``runs`` times, every metric's distribution per combination.

A path is the YAML path a user edits (``algorithm.forgetting_factor``,
``vehicles[0].speed_limit_m_s``, ``vehicles[*].speed_limit_m_s`` for every vehicle); a value is
read as YAML (``0.98``, ``ekf``, ``null``). Each combination is validated like a scenario file,
so a bad value is reported at its path before anything runs.
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

from ..checks import validate_scenario
from ..config import Scenario
from ..errors import ConfigError
from ..metrics import SweepPoint, run_metrics
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


def sweep(
    scenario: Scenario,
    axes: Sequence[Axis],
    runs: int,
    source: str = "<scenario>",
    on_point: Callable[[int, int], None] | None = None,
) -> list[SweepPoint]:
    """Simulate every combination of ``axes`` values ``runs`` times. Every combination is
    validated first (a :class:`ConfigError` names the path and the combination)."""
    base = scenario.model_dump(mode="json")
    combinations = list(itertools.product(*(axis.values for axis in axes)))
    scenarios = []
    for combination in combinations:
        data = copy.deepcopy(base)
        values = {axis.path: value for axis, value in zip(axes, combination, strict=True)}
        for path, value in values.items():
            try:
                set_path(data, path, value)
            except KeyError as error:
                raise ConfigError(source, [(path, str(error.args[0]))]) from None
        label = ", ".join(f"{path}={value}" for path, value in values.items())
        point = validate_scenario(data, f"{source} with {label}")
        check_memory(point, runs, source)
        scenarios.append((values, point))
    points = []
    for index, (values, point) in enumerate(scenarios):
        points.append(SweepPoint(values, run_metrics(simulate(point, runs=runs))))
        if on_point is not None:
            on_point(index + 1, len(scenarios))
    return points


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

"""A scenario file read, parsed and validated: the bounded YAML reader, the model's field checks
and the rules that span fields (the target's path and the shape over the run's times, the
vehicles' start, the emulator's settings). Every problem is reported at the YAML path to edit.

Above the model (:mod:`.config`), the scenario's geometry (:mod:`.scenario`) and the settings
built from it (:mod:`.wiring`), which these checks evaluate.
"""

from __future__ import annotations

import json
import logging
import math
import os
import selectors
import stat
import time
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from numpy.typing import NDArray
from pydantic import ValidationError

from .config import (
    MAX_COORDINATE_M,
    MIN_SPACING_M,
    ExpressionPath,
    ExpressionSignal,
    Problem,
    Scenario,
    ShapeConfig,
)
from .enclosing.graph import components, edge_problems
from .errors import ConfigError
from .expressions import compile_expression
from .limits import MAX_MAVLINK_ID
from .scenario import shape_matrices, signal_values, target_positions
from .wiring import emulator_settings, neighbour_graph

if TYPE_CHECKING:
    from .paths import PathName


logger = logging.getLogger(__name__)

#: A scenario file is a few kilobytes; the cap makes ``/dev/zero`` or a wrong, huge file end at
#: once instead of being read (and parsed) into memory.
MAX_FILE_BYTES = 1 << 20
#: The deepest a scenario nests is about six levels (``flight.emulator.physics.wind...``); beyond
#: this the YAML composer would recurse out of the stack.
MAX_DEPTH = 32
#: Values after YAML aliases are expanded: a few aliases to aliases (the "billion laughs") would
#: otherwise make validation walk billions of values.
MAX_NODES = 1_000_000


#: How long a scenario that is not a regular file (a named pipe, ``<(generate)``, a terminal) may
#: take to arrive [s]: a pipe nobody writes to would otherwise block the command for ever.
READ_TIMEOUT_S = 5.0


def load_scenario(path: PathName, *, flying: bool = False) -> Scenario:
    """Read and validate a scenario file. Raises :class:`ConfigError` listing every problem.
    ``flying``: also what only a flight needs (:func:`flight_problems`)."""
    file = Path(path)
    try:
        raw = _read_bounded(file, READ_TIMEOUT_S)
    except OSError as error:
        reason = error.strerror or str(error)
        raise ConfigError(str(file), [("", f"cannot read file: {reason}")]) from None
    if raw is None:
        problem = (
            f"not a regular file, and nothing more came from it within {READ_TIMEOUT_S:g} s "
            "(a named pipe nobody writes to?)"
        )
        raise ConfigError(str(file), [("", problem)])
    if len(raw) > MAX_FILE_BYTES:
        raise ConfigError(str(file), [("", _too_large())])
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line = raw[: error.start].count(b"\n") + 1
        byte = raw[error.start]
        problem = f"not UTF-8 text: byte 0x{byte:02x} on line {line} (save the file as UTF-8)"
        raise ConfigError(str(file), [("", problem)]) from None
    scenario = parse_scenario(text, source=str(file))
    if flying:
        problems = flight_problems(scenario)
        if problems:
            raise ConfigError(str(file), problems)
    return scenario


def _read_bounded(file: Path, timeout_s: float) -> bytes | None:
    """Up to ``MAX_FILE_BYTES + 1`` bytes of ``file``; None if it is not a regular file and
    gives no bytes for ``timeout_s`` before its end. Raises OSError."""
    # Non-blocking open: opening a named pipe for reading otherwise waits for a writer.
    descriptor = os.open(file, os.O_RDONLY | os.O_NONBLOCK)
    try:
        regular = stat.S_ISREG(os.fstat(descriptor).st_mode)
        chunks: list[bytes] = []
        size = 0
        deadline_s = time.monotonic() + timeout_s
        # poll, not epoll: epoll refuses character devices such as /dev/zero.
        with getattr(selectors, "PollSelector", selectors.SelectSelector)() as selector:
            selector.register(descriptor, selectors.EVENT_READ)
            while size <= MAX_FILE_BYTES:
                remaining_s = max(0.0, deadline_s - time.monotonic())
                if not regular and not selector.select(remaining_s):
                    return None
                try:
                    chunk = os.read(descriptor, MAX_FILE_BYTES + 1 - size)
                except BlockingIOError:  # woken, but another reader took the bytes
                    continue
                if not chunk:  # the end (a pipe: readable with nothing left, the writer closed)
                    break
                chunks.append(chunk)
                size += len(chunk)
        return b"".join(chunks)
    finally:
        os.close(descriptor)


def flight_problems(scenario: Scenario) -> list[Problem]:
    """What a scenario valid for the numeric model cannot fly: vehicle ids beyond MAVLink's, a
    ring graph with a vehicle that goes silent without being lost (:func:`_silent_in_ring`)."""
    return _silent_in_ring(scenario) + [
        (
            f"vehicles[{index}].id",
            f"{vehicle.id} is not a MAVLink system id (1..{MAX_MAVLINK_ID}); a flying vehicle's "
            "id is its autopilot's system id",
        )
        for index, vehicle in enumerate(scenario.vehicles)
        if vehicle.id > MAX_MAVLINK_ID
    ]


def _silent_in_ring(scenario: Scenario) -> list[Problem]:
    """A ring closes over a vehicle its neighbours stop hearing, but the radios' schedule
    closes it only over a vehicle that is lost (the emulator's truth): over one whose link is
    lost or that is taken over, the controllers would couple two vehicles that never range each
    other."""
    if scenario.algorithm.graph.kind != "ring":
        return []
    return [
        (
            f"events[{index}]",
            f"{event.kind} cannot be flown on a ring graph: the controllers close the ring over "
            "the vehicle that goes silent, the radios keep ranging it and not the closing pair; "
            "fly it with another algorithm.graph kind, or make it vehicle_lost",
        )
        for index, event in enumerate(scenario.events)
        if event.kind in {"link_lost", "taken_over"}
    ]


def parse_scenario(text: str, source: str = "<string>") -> Scenario:
    """Validate scenario YAML text; see :func:`load_scenario`."""
    if len(text) > MAX_FILE_BYTES:
        raise ConfigError(source, [("", _too_large())])
    try:
        data = yaml.load(text, Loader=_BoundedLoader)  # a SafeLoader with limits
    except _StructureError as error:
        raise ConfigError(source, [(error.path, error.problem)]) from None
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(error, "problem", None) or str(error)
        raise ConfigError(source, [("", f"{where}not valid YAML: {problem}")]) from None
    if not isinstance(data, dict):
        raise ConfigError(source, [("", "must be a mapping of keys to values")])
    problems = list(_non_finite(data, ()))
    if problems:  # before the model, which would report them again, less precisely
        raise ConfigError(source, problems)
    return validate_scenario(data, source)


def _too_large() -> str:
    return f"larger than {MAX_FILE_BYTES >> 10} KiB: not a scenario file"


class _StructureError(Exception):
    """A YAML document the scenario loader refuses before building it (``path``: where)."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe loader with bounds: nesting depth, values after aliases expand, no alias
    cycles, and no duplicate keys (PyYAML keeps the last one silently)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._path: list[int | str] = []
        self._depth = 0
        self._nodes = 0
        self._sizes: dict[int, int] = {}  # id(node) -> values in it, once composed

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            anchored = self.anchors.get(self.peek_event().anchor)  # type: ignore[no-untyped-call]
            if anchored is not None and id(anchored) not in self._sizes:
                raise _StructureError(self._where(), "an alias refers to a value containing it")
            node = super().compose_node(parent, index)
            self._count(self._sizes.get(id(node), 1))
            return node
        # ``index``: an int in a sequence, the key's node for a mapping value, None for a key.
        part = index if isinstance(index, int) else getattr(index, "value", None)
        if part is not None:
            self._path.append(part if isinstance(part, int) else str(part))
        self._depth += 1
        if self._depth > MAX_DEPTH:
            raise _StructureError(self._where(), f"nested deeper than {MAX_DEPTH} levels")
        before = self._nodes
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
            if part is not None:
                self._path.pop()
        self._count(1)
        self._sizes[id(node)] = self._nodes - before
        return node

    def compose_mapping_node(self, anchor: Any) -> yaml.MappingNode:
        node = super().compose_mapping_node(anchor)
        seen: set[tuple[str, str]] = set()
        for key, _ in node.value:
            if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                if (key.tag, key.value) in seen:
                    line = key.start_mark.line + 1
                    raise _StructureError(
                        yaml_path([*self._path, key.value]),
                        f"duplicate key (again on line {line}); give each key once",
                    )
                seen.add((key.tag, key.value))
        return node

    def _count(self, nodes: int) -> None:
        self._nodes += nodes
        if self._nodes > MAX_NODES:
            raise _StructureError(self._where(), f"more than {MAX_NODES} values (with aliases)")

    def _where(self) -> str:
        """The YAML path being composed, shortened past a few levels (deep nesting)."""
        shown = yaml_path(self._path[:4])
        return shown + "..." if len(self._path) > 4 else shown


def _non_finite(data: object, location: tuple[int | str, ...]) -> Iterable[Problem]:
    """NaN or an infinity anywhere in the parsed YAML (``.nan``, ``.inf``, ``1e999``), also where
    the model passes values on unchecked (``flight.emulator``)."""
    if isinstance(data, float) and not math.isfinite(data):
        yield yaml_path(location), f"must be a finite number (got {data})"
    elif isinstance(data, dict):
        for key, value in data.items():
            yield from _non_finite(value, (*location, str(key)))
    elif isinstance(data, list):
        for index, value in enumerate(data):
            yield from _non_finite(value, (*location, index))


def validate_scenario(data: dict[str, Any], source: str = "<data>") -> Scenario:
    """Validate already-parsed scenario data (a dict)."""
    try:
        scenario = Scenario.model_validate(data)
    except ValidationError as error:
        raise ConfigError(source, _pydantic_problems(error, data)) from None
    problems = _rule_problems(scenario)
    if problems:
        raise ConfigError(source, problems)
    for where, warning in scenario_warnings(scenario):
        logger.warning("%s: %s: %s", source, where, warning)
    return scenario


def scenario_warnings(scenario: Scenario) -> list[Problem]:
    """What is valid but will not do what the file seems to ask, at the path to edit: a vehicle
    speed limit below the speed the law commands (it then clips the command and the formation
    falls behind while the final sample may still look fine)."""
    step_s, steps = scenario.timing.step_s, scenario.timing.steps
    times = np.arange(steps + 2, dtype=np.float64) * step_s
    with np.errstate(all="ignore"):
        shapes = shape_matrices(scenario.algorithm.shape, times)
        target = target_positions(scenario.target.path, times)
    # |u| <= Ubar + |delta_r / T| + |u_0|, and on the circle |delta_r / T| is at most
    # |A(k+1)| rho omega (the phase turning) + rho |A(k+1) - A(k)| / T + |dT| / T (the shape
    # changing), |.| the largest singular value of the linear part.
    linear = shapes[:, :2, :2]
    stretch = np.linalg.norm(linear, ord=2, axis=(-2, -1))
    reshape = np.linalg.norm(np.diff(linear, axis=0), ord=2, axis=(-2, -1)) / step_s
    shift = np.linalg.norm(np.diff(shapes[:, :2, 2], axis=0), axis=-1) / step_s
    target_speed = float(np.max(np.linalg.norm(np.diff(target, axis=0), axis=-1))) / step_s
    radius_m = scenario.algorithm.radius_m
    warnings: list[Problem] = []
    for index, vehicle in enumerate(scenario.vehicles):
        omega = vehicle.omega_rad_s or scenario.algorithm.omega_rad_s
        circle = radius_m * (omega * stretch[1:] + reshape) + shift
        needed = scenario.algorithm.saturation_m_s + float(np.max(circle)) + target_speed
        if vehicle.speed_limit_m_s < needed:
            source = (
                "vehicles[{index}].omega_rad_s" if vehicle.omega_rad_s else "algorithm.omega_rad_s"
            )
            warnings.append(
                (
                    f"vehicles[{index}].speed_limit_m_s",
                    f"{vehicle.speed_limit_m_s:g} m/s is below the {needed:.3g} m/s the law may "
                    f"command (algorithm.saturation_m_s {scenario.algorithm.saturation_m_s:g} + "
                    f"the circle's {float(np.max(circle)):.3g} from algorithm.radius_m, "
                    f"algorithm.shape and {source.format(index=index)} + target.path's "
                    f"{target_speed:.3g}): commands will be clipped and the formation will lag",
                )
            )
    return warnings


def yaml_path(location: Iterable[int | str]) -> str:
    """``("vehicles", 2, "id")`` -> ``"vehicles[2].id"``."""
    text = ""
    for part in location:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text


def _clean_location(location: Iterable[int | str], data: object) -> tuple[int | str, ...]:
    """Drop pydantic's union-branch markers so the location is the YAML path that was written."""
    cleaned: list[int | str] = []
    node: Any = data  # the parsed YAML below the part reached so far, whatever it holds
    skip_tag = False
    for part in location:
        if skip_tag:
            skip_tag = False
            continue
        if isinstance(part, str) and part.startswith("tagged-union["):
            skip_tag = True
            continue
        if part in ("float", "int", "str", "bool", "[key]") or (
            isinstance(part, str) and part.startswith(("function-", "list["))
        ):
            continue
        # A discriminated union inserts the tag ("line", "sinusoid", ...) into the location.
        if isinstance(node, dict) and part not in node and node.get("kind") == part:
            continue
        cleaned.append(part)
        try:
            node = node[part]
        except (KeyError, IndexError, TypeError):
            node = None
    return tuple(cleaned)


def _pydantic_problems(error: ValidationError, data: object) -> list[Problem]:
    problems = []
    for item in error.errors(include_url=False):
        location = _clean_location(item["loc"], data)
        message = item["msg"]
        if item["type"] == "value_error":
            message = message.removeprefix("Value error, ")
        # A union of a number and a tagged mapping reports both branches; keep the one that
        # matches what was written.
        scalar_branch = item["loc"] and item["loc"][-1] in ("float", "int")
        if scalar_branch and isinstance(item.get("input"), dict):
            continue
        problems.append((yaml_path(location), message))
    return problems


def _rule_problems(scenario: Scenario) -> list[Problem]:
    """Rules that span several fields, each reported at the path a user would edit."""
    problems: list[Problem] = []
    step_s = scenario.timing.step_s
    if scenario.algorithm.beta >= 1 / step_s:
        problems.append(
            (
                "algorithm.beta",
                f"must be < 1/timing.step_s = {1 / step_s:g} (got {scenario.algorithm.beta:g})",
            )
        )
    exchange_s = scenario.sensors.range_exchange_s
    if exchange_s is not None and exchange_s > step_s * (1 + 1e-9):
        problems.append(
            (
                "sensors.range_exchange_s",
                f"must be <= timing.step_s = {step_s:g}: a step must carry at least one ranging "
                f"exchange (got {exchange_s:g})",
            )
        )
    ids = [vehicle.id for vehicle in scenario.vehicles]
    for index, vehicle in enumerate(scenario.vehicles):
        if ids.index(vehicle.id) != index:
            problems.append((f"vehicles[{index}].id", f"duplicate vehicle id {vehicle.id}"))
        if vehicle.speed_limit_m_s <= scenario.algorithm.saturation_m_s:
            problems.append(
                (
                    f"vehicles[{index}].speed_limit_m_s",
                    "must be > algorithm.saturation_m_s (the paper needs Ubar < U_i)",
                )
            )
    if not any(vehicle.senses_target for vehicle in scenario.vehicles):
        problems.append(("vehicles", "at least one vehicle must have senses_target: true"))
    joined_later: set[int] = set()
    for index, event in enumerate(scenario.events):
        where = f"events[{index}]"
        if (event.at_step is None) == (event.at_s is None):
            problems.append((where, "give exactly one of at_step or at_s"))
            continue
        if event.vehicle is None and event.kind != "target_hidden":
            problems.append((f"{where}.vehicle", f"give the vehicle of {event.kind}"))
        elif event.vehicle is not None and event.vehicle not in ids:
            problems.append((f"{where}.vehicle", f"no vehicle with id {event.vehicle}"))
        if event.step(step_s) >= scenario.timing.steps:
            problems.append((where, f"happens after the last step ({scenario.timing.steps})"))
        if event.kind == "vehicle_joins" and event.vehicle is not None:
            joined_later.add(event.vehicle)
        if (event.kind == "sensor_lost") != (event.sensor is not None):
            problems.append((f"{where}.sensor", "give sensor for sensor_lost, and only there"))
        if event.rearm_after_s is not None and event.kind != "taken_over":
            problems.append((f"{where}.rearm_after_s", "only a taken_over event re-arms"))
    sensing_from_start = [
        vehicle.id
        for vehicle in scenario.vehicles
        if vehicle.senses_target and vehicle.id not in joined_later
    ]
    if ids and any(v.senses_target for v in scenario.vehicles) and not sensing_from_start:
        problems.append(("vehicles", "a vehicle sensing the target must be present from k = 0"))
    problems += _time_problems(scenario)
    problems += _start_problems(scenario)
    problems += _emulator_problems(scenario)
    problems += _separation_problems(scenario)
    problems += _graph_problems(scenario)
    return problems


def _graph_problems(scenario: Scenario) -> list[Problem]:
    """The neighbourhood graph's settings fit its kind, its edges are well formed and it is
    connected (the paper's analysis needs a connected graph; a complete one is)."""
    graph, n = scenario.algorithm.graph, len(scenario.vehicles)
    if graph.kind == "complete" and graph.k is None and graph.edges is None:
        return []
    problems: list[Problem] = []
    if graph.kind != "complete" and scenario.safety.min_separation_m is not None:
        problems.append(
            (
                "algorithm.graph",
                "the separation guard (safety.min_separation_m) needs ranges to and estimates "
                "of every vehicle, a sparse graph gives only its neighbours': use kind "
                "complete, or no guard",
            )
        )
    if (graph.kind == "k_nearest") != (graph.k is not None):
        problems.append(("algorithm.graph.k", "give k for kind k_nearest, and only there"))
    if (graph.kind == "edges") != (graph.edges is not None):
        problems.append(("algorithm.graph.edges", "give edges for kind edges, and only there"))
    if graph.kind == "edges" and graph.edges is not None:
        problems += [
            (f"algorithm.graph.edges[{index}]", problem)
            for index, problem in edge_problems(n, graph.edges)
        ]
    if problems:
        return problems
    parts = components(neighbour_graph(scenario))
    if len(parts) > 1:
        named = "vehicles " + " and ".join("{" + ",".join(map(str, part)) + "}" for part in parts)
        problems.append(
            (
                "algorithm.graph",
                f"is not connected: {named} are not connected (indices in vehicles:); "
                "the formation needs every vehicle linked to every other through neighbours",
            )
        )
    return problems


def _separation_problems(scenario: Scenario) -> list[Problem]:
    """A minimum separation the enclosing circle cannot hold is a contradiction, not a guard."""
    separation = scenario.safety.min_separation_m
    n = len(scenario.vehicles)
    if separation is None or n < 2:
        return []
    spacing = 2 * scenario.algorithm.radius_m * math.sin(math.pi / n)
    if separation >= spacing:
        return [
            (
                "safety.min_separation_m",
                f"must be < {spacing:.3g} m, the spacing of {n} vehicles evenly on a circle of "
                f"radius {scenario.algorithm.radius_m:g} m",
            )
        ]
    return []


def _emulator_problems(scenario: Scenario) -> list[Problem]:
    """Check ``flight.emulator`` at load time; the vehicle count is checked when flying (a
    simulate-only scenario may have more vehicles than one emulator process holds)."""
    if not scenario.flight.emulator:
        return []  # and a vehicle process flying PX4 never imports the emulator (0.2 CPU s)
    from sitl.config import EmulatorConfig  # noqa: PLC0415 - the simulator does not need sitl

    data = emulator_settings(scenario, vehicles=1, placement={})
    try:
        # As strict as the rest of the scenario ("2" is not a number): the YAML holds JSON's
        # types, and strict in JSON mode still takes file names as strings.
        EmulatorConfig.model_validate_json(json.dumps(data, default=str), strict=True)
    except ValidationError as error:
        return [
            (yaml_path(("flight", "emulator", *location)), message)
            for location, message in (
                (_clean_location(item["loc"], scenario.flight.emulator), item["msg"])
                for item in error.errors(include_url=False)
            )
        ]
    return []


def _time_problems(scenario: Scenario) -> list[Problem]:
    """The target's path and the shape's signals over the run's times t_k (and one step beyond,
    which the law's feed-forward reads): finite, inside the frame, scales > 0, and a circle on
    which the vehicles fit."""
    step_s, steps = scenario.timing.step_s, scenario.timing.steps
    times = np.arange(steps + 2, dtype=np.float64) * step_s
    if not np.isfinite(times[-1]):
        return [("timing.step_s", "timing.steps x timing.step_s must be a finite duration")]
    problems: list[Problem] = []
    values: dict[str, NDArray[np.float64]] = {}
    for name in ShapeConfig.model_fields:
        signal = getattr(scenario.algorithm.shape, name)
        where = f"algorithm.shape.{name}"
        with np.errstate(all="ignore"):
            value = signal_values(signal, times)
        unfinished = _not_finite(value, times)
        if unfinished:
            expression = isinstance(signal, ExpressionSignal)
            problems.append((where + (".expression" if expression else ""), unfinished))
        elif name.startswith("scale") and np.min(value) <= 0:
            k = int(np.argmin(value))
            problems.append(
                (
                    where,
                    f"must stay finite and > 0 over the whole run ({value[k]:.3g} at "
                    f"t = {times[k]:g} s)",
                )
            )
        else:
            values[name] = value
    if len(values) == len(ShapeConfig.model_fields):
        problems += _circle_problems(scenario, values, times)
    return problems + _target_problems(scenario, times)


def _not_finite(values: NDArray[np.float64], times: NDArray[np.float64]) -> str | None:
    """What is wrong if ``values`` ``(K,)`` at ``times`` ``(K,)`` are not all finite."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return None
    k = int(np.argmax(bad))
    return f"is not finite at t = {times[k]:g} s (evaluates to {values[k]})"


def _circle_problems(
    scenario: Scenario, values: dict[str, NDArray[np.float64]], times: NDArray[np.float64]
) -> list[Problem]:
    """The shaped circle (A [rho cos, rho sin, 1] around the target) stays inside the frame, and
    neighbours on it stay ``MIN_SPACING_M`` apart. ``values``: every shape signal ``(K,)``."""
    radius_m, n = scenario.algorithm.radius_m, len(scenario.vehicles)
    # The linear part [[S_x, H_a S_y], [H_b S_x, S_y]] (enclosing.affine_matrix) stretches a
    # chord by between its smallest and largest singular values (closed form for 2 x 2).
    a, d = values["scale_north"], values["scale_east"]
    b, c = values["shear_a"] * d, values["shear_b"] * a
    with np.errstate(all="ignore"):
        first, second = np.hypot(a + d, c - b), np.hypot(a - d, b + c)
        largest, smallest = (first + second) / 2, np.abs(first - second) / 2
        reach_m = np.hypot(values["translate_north_m"], values["translate_east_m"])
        reach_m = reach_m + radius_m * largest
    problems: list[Problem] = []
    if not np.all(reach_m <= MAX_COORDINATE_M):
        k = int(np.argmax(~(reach_m <= MAX_COORDINATE_M)))
        problems.append(
            (
                "algorithm.shape",
                f"takes the circle {reach_m[k]:.3g} m from the target at t = {times[k]:g} s; "
                f"it must stay within {MAX_COORDINATE_M:g} m",
            )
        )
    if n < 2:
        return problems
    chord_m = 2 * radius_m * math.sin(math.pi / n)
    k = int(np.argmin(smallest))
    if chord_m < MIN_SPACING_M:
        needed = MIN_SPACING_M / (2 * math.sin(math.pi / n))
        problems.append(
            (
                "algorithm.radius_m",
                f"too small for {n} vehicles: neighbours on the circle would be {chord_m:.3g} m "
                f"apart, less than {MIN_SPACING_M:g} m (radius must be >= {needed:.3g} m)",
            )
        )
    elif chord_m * smallest[k] < MIN_SPACING_M:
        problems.append(
            (
                "algorithm.shape",
                f"squeezes the circle so that neighbours may come {chord_m * smallest[k]:.3g} m "
                f"close at t = {times[k]:g} s, less than {MIN_SPACING_M:g} m",
            )
        )
    return problems


def _target_problems(scenario: Scenario, times: NDArray[np.float64]) -> list[Problem]:
    """The target's path is finite and inside the frame at every t_k."""
    path = scenario.target.path
    with np.errstate(all="ignore"):
        if isinstance(path, ExpressionPath):
            axes = [
                ("target.path.north", compile_expression(path.north)(times)),
                ("target.path.east", compile_expression(path.east)(times)),
            ]
        else:
            positions = target_positions(path, times)
            axes = [("target.path", positions[:, 0]), ("target.path", positions[:, 1])]
    problems: list[Problem] = []
    for where, values in axes:
        problem = _not_finite(values, times)
        if problem is None and np.max(np.abs(values)) > MAX_COORDINATE_M:
            k = int(np.argmax(np.abs(values) > MAX_COORDINATE_M))
            problem = (
                f"leaves the frame at t = {times[k]:g} s ({values[k]:.3g} m; coordinates must "
                f"stay within {MAX_COORDINATE_M:g} m)"
            )
        if problem is not None and all(where != known for known, _ in problems):
            problems.append((where, problem))
    return problems


def _start_problems(scenario: Scenario) -> list[Problem]:
    """Vehicles start inside the frame and apart from each other."""
    positions = np.array([vehicle.initial_position_m for vehicle in scenario.vehicles])
    problems: list[Problem] = []
    for index, position in enumerate(positions):
        where = f"vehicles[{index}].initial_position_m"
        if np.max(np.abs(position)) > MAX_COORDINATE_M:
            problems.append((where, f"must be within {MAX_COORDINATE_M:g} m of the origin"))
            continue
        if index == 0:
            continue
        with np.errstate(all="ignore"):
            gaps_m = np.hypot(*(positions[:index] - position).T)
        other = int(np.argmin(gaps_m))
        if gaps_m[other] < MIN_SPACING_M:
            problems.append(
                (
                    where,
                    f"{gaps_m[other]:.3g} m from vehicles[{other}] (id "
                    f"{scenario.vehicles[other].id}): vehicles must start at least "
                    f"{MIN_SPACING_M:g} m apart",
                )
            )
    return problems

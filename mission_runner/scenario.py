"""Evaluate a scenario's time-varying data (target path, affine shape) on arrays of times.

Numpy only; shared by the simulator, the emulator's target and the flying controllers, so every
part of the system sees the same target and the same shape at the same instant.
"""

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .config import (
    CirclePath,
    ConstantSignal,
    ExpressionPath,
    ExpressionSignal,
    LinePath,
    Scenario,
    ShapeConfig,
    Signal,
    SinusoidPath,
    SinusoidSignal,
    TargetPath,
    VehicleConfig,
    WaypointPath,
    WaypointSignal,
)
from .enclosing import affine_matrix
from .expressions import compile_expression


def signal_values(signal: Signal, times_s: ArrayLike) -> NDArray[np.float64]:
    """Values of a signal (a number or a signal model) at ``times_s`` ``(K,)`` -> ``(K,)``."""
    times_s = np.asarray(times_s, dtype=float)
    if isinstance(signal, int | float):
        return np.full(times_s.shape, float(signal))
    if isinstance(signal, ConstantSignal):
        return np.full(times_s.shape, signal.value)
    if isinstance(signal, SinusoidSignal):
        angle = 2 * np.pi * times_s / signal.period_s + signal.phase_rad
        return signal.offset + signal.amplitude * np.sin(angle)
    if isinstance(signal, WaypointSignal):
        points = np.asarray(signal.points)
        return np.interp(times_s, points[:, 0], points[:, 1])
    if isinstance(signal, ExpressionSignal):
        return compile_expression(signal.expression)(times_s)
    raise TypeError(f"not a signal: {signal!r}")


def target_positions(path: TargetPath, times_s: ArrayLike) -> NDArray[np.float64]:
    """The target's ``[north, east]`` at ``times_s`` ``(K,)`` -> ``(K, 2)`` [m]."""
    t = np.asarray(times_s, dtype=float)[:, None]
    if isinstance(path, LinePath):
        return np.asarray(path.start_m) + np.asarray(path.velocity_m_s) * t
    if isinstance(path, SinusoidPath):
        wave = np.sin(2 * np.pi * t / path.period_s + path.phase_rad)
        drift = np.asarray(path.start_m) + np.asarray(path.velocity_m_s) * t
        return drift + np.asarray(path.amplitude_m) * wave
    if isinstance(path, CirclePath):
        angle = 2 * np.pi * t[:, 0] / path.period_s + path.phase_rad
        offset = path.radius_m * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
        return np.asarray(path.center_m) + offset
    if isinstance(path, WaypointPath):
        points = np.asarray(path.points)
        return np.stack(
            [np.interp(t[:, 0], points[:, 0], points[:, axis]) for axis in (1, 2)], axis=-1
        )
    if isinstance(path, ExpressionPath):
        north = compile_expression(path.north)(t[:, 0])
        east = compile_expression(path.east)(t[:, 0])
        return np.stack([north, east], axis=-1)
    raise TypeError(f"not a target path: {path!r}")


def shape_matrices(shape: ShapeConfig, times_s: ArrayLike) -> NDArray[np.float64]:
    """Affine shape matrices at ``times_s`` ``(K,)`` -> ``(K, 3, 3)``."""

    def pair(first: Signal, second: Signal) -> NDArray[np.float64]:
        return np.stack([signal_values(first, times_s), signal_values(second, times_s)], axis=-1)

    return affine_matrix(
        pair(shape.translate_north_m, shape.translate_east_m),
        pair(shape.scale_north, shape.scale_east),
        pair(shape.shear_a, shape.shear_b),
    )


#: k -> the affine shape matrix ``(3, 3)`` at step k.
ShapeSchedule = Callable[[int], NDArray[np.float64]]


def omega_of(scenario: Scenario, vehicle: VehicleConfig) -> float:
    """``vehicle``'s oscillator frequency [rad/s]: its own, else the scenario's."""
    return vehicle.omega_rad_s or scenario.algorithm.omega_rad_s


def shape_schedule(scenario: Scenario) -> ShapeSchedule:
    """k -> the affine shape matrix at step k (held after the last step)."""
    steps = scenario.timing.steps
    shapes = shape_matrices(scenario.algorithm.shape, np.arange(steps + 2) * scenario.timing.step_s)
    return lambda k: shapes[min(k, len(shapes) - 1)]

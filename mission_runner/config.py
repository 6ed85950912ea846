"""The scenario model: one typed YAML file describes a mission, for the simulator, the emulator and
the flying runner alike. It is validated once at load; every problem is reported with its YAML
path (``vehicles[2].initial_phase_rad``) and the rule it breaks, before anything runs or is written.

Planar quantities are ``[north, east]`` pairs in metres (m/s for velocities): the paper's ``[x, y]``
is ``[north, east]`` here. Time-varying values (the target's path, the affine shape) are data:
constants, sinusoids, waypoints or safe expressions of ``t`` (see :mod:`.expressions`); never
Python code.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import selectors
import stat
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, Self, get_args

import numpy as np
import yaml
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from .bus.settings import BusSettings
from .errors import ConfigError
from .expressions import ExpressionError, compile_expression

if TYPE_CHECKING:
    from .outputs import PathName

logger = logging.getLogger(__name__)

#: A scenario problem: the YAML path a user would edit (``vehicles[2].id``) and what is wrong.
Problem = tuple[str, str]

Pair = Annotated[list[float], Field(min_length=2, max_length=2)]
PositiveFloat = Annotated[float, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]

#: Planar coordinates stay within this of the origin [m]: the frame is a local north-east plane,
#: and far beyond it squared ranges lose the precision the estimator works with.
MAX_COORDINATE_M = 1e6
#: Nothing the runner flies is smaller (a Crazyflie is 92 mm across): vehicles closer than this at
#: the start, or as neighbours on the enclosing circle, would touch.
MIN_SPACING_M = 0.1
#: Heights above home [m]: far above any mission a multicopter swarm flies (open-category drones
#: stay below 120 m); beyond it the number is a typo, not a flight.
MAX_ALTITUDE_M = 1000.0
#: Speeds [m/s]: racing multicopters top out near 50 m/s.
MAX_SPEED_M_S = 100.0
#: Accelerations [m/s^2]: 10 g, beyond any multicopter's thrust.
MAX_ACCELERATION_M_S2 = 100.0
#: The law's step [s]: a radio and an odometry give nothing faster than 1 kHz, and a step of a
#: minute leaves nothing to control.
MIN_STEP_S, MAX_STEP_S = 1e-3, 60.0
#: Durations of a run [s]: longer than the longest run (timing.steps <= 1e7 steps of <= 60 s);
#: the bound keeps step counts derived from them integers (1e308 s overflowed).
MAX_DURATION_S = 1e9
#: What one wait of a flight may last [s] (timeouts, delays): an hour is beyond any of them, and
#: the event loop's timers overflow long before 1e300.
MAX_WAIT_S = 3600.0
#: A radio crystal's offset [ppm]: UWB radios are trimmed to a few; 1000 is a broken one.
MAX_CLOCK_OFFSET_PPM = 1000.0
#: A ranging exchange's reply delay or airtime [s]: milliseconds; a second is no UWB radio.
MAX_REPLY_TIME_S = 1.0
#: Frequencies of the oscillators [rad/s]: 100 rad/s is 16 turns a second, beyond any formation.
MAX_RATE_RAD_S = 100.0
#: Phases [rad]: every angle is within one turn; far larger numbers are typos and lose the
#: precision of sin and cos.
MAX_PHASE_RAD = 1000.0
#: Noise figures (standard deviations) [m]: a ranging radio or an odometry worse than this
#: measures nothing.
MAX_NOISE_STD_M = 100.0
#: Gains of the law and of the controllers [1/s, 1/s^2, dimensionless]: far beyond a stable one.
MAX_GAIN = 1000.0
#: Fastest speed factor of the bundled emulator's real-time clock (sitl.config).
MAX_CLOCK_SPEED = 1000.0
#: PX4 parameters are INT32 or REAL32 (MAVLink PARAM_SET): values beyond these do not fit.
INT32_RANGE = (-(2**31), 2**31 - 1)
REAL32_MAX = 3.4028234663852886e38

Phase = Annotated[float, Field(ge=-MAX_PHASE_RAD, le=MAX_PHASE_RAD)]
Altitude = Annotated[float, Field(gt=0, le=MAX_ALTITUDE_M)]
Speed = Annotated[float, Field(gt=0, le=MAX_SPEED_M_S)]
Wait = Annotated[float, Field(gt=0, le=MAX_WAIT_S)]
Distance = Annotated[float, Field(gt=0, le=MAX_COORDINATE_M)]
NoiseStd = Annotated[float, Field(ge=0, le=MAX_NOISE_STD_M)]
Gain = Annotated[float, Field(gt=0, le=MAX_GAIN)]


class Model(BaseModel):
    """Strict, immutable, closed: unknown keys, wrong types and NaN/inf are errors."""

    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False, frozen=True)


def _expression(text: str) -> str:
    try:
        compile_expression(text)
    except ExpressionError as error:
        raise ValueError(str(error)) from None
    return text


def _increasing_times(points: list[list[float]]) -> list[list[float]]:
    if any(b[0] <= a[0] for a, b in itertools.pairwise(points)):
        raise ValueError("times must be strictly increasing")
    return points


Expression = Annotated[str, Field(min_length=1)]


# --- Time-varying scalars -----------------------------------------------------------------------


class ConstantSignal(Model):
    """A value that does not change."""

    kind: Literal["constant"] = Field(title="Kind", description="Signal kind.")
    value: float = Field(title="Value", description="The constant value.")


class SinusoidSignal(Model):
    """offset + amplitude * sin(2 pi t / period_s + phase_rad)."""

    kind: Literal["sinusoid"] = Field(title="Kind", description="Signal kind.")
    offset: float = Field(0.0, title="Offset", description="Mean value.")
    amplitude: float = Field(title="Amplitude", description="Peak deviation from the offset.")
    period_s: PositiveFloat = Field(title="Period", description="Period in seconds.")
    phase_rad: Phase = Field(0.0, title="Phase", description="Phase at t = 0, radians.")


class WaypointSignal(Model):
    """Piecewise-linear through ``[t_s, value]`` points, held constant outside them."""

    kind: Literal["waypoints"] = Field(title="Kind", description="Signal kind.")
    points: Annotated[list[Pair], Field(min_length=1)] = Field(
        title="Points", description="[time_s, value] pairs with strictly increasing times."
    )

    _check = field_validator("points")(_increasing_times)


class ExpressionSignal(Model):
    """A safe arithmetic expression of ``t`` in seconds, e.g. ``1 + 0.5 * sin(pi * t / 12.5)``."""

    kind: Literal["expression"] = Field(title="Kind", description="Signal kind.")
    expression: Expression = Field(title="Expression", description="Expression of t [s].")

    _check = field_validator("expression")(_expression)


Signal = (
    float
    | Annotated[
        ConstantSignal | SinusoidSignal | WaypointSignal | ExpressionSignal,
        Field(discriminator="kind"),
    ]
)


# --- Target paths ---------------------------------------------------------------------------------


class LinePath(Model):
    """p0(t) = start + velocity * t."""

    kind: Literal["line"] = Field(title="Kind", description="Path kind.")
    start_m: Pair = Field([0.0, 0.0], title="Start", description="[north, east] at t = 0 [m].")
    velocity_m_s: Pair = Field(title="Velocity", description="[north, east] velocity [m/s].")


class SinusoidPath(Model):
    """A line plus a sinusoid on each axis: start + v t + amplitude sin(2 pi t / T + phi)."""

    kind: Literal["sinusoid"] = Field(title="Kind", description="Path kind.")
    start_m: Pair = Field([0.0, 0.0], title="Start", description="[north, east] at t = 0 [m].")
    velocity_m_s: Pair = Field([0.0, 0.0], title="Drift", description="Mean velocity [m/s].")
    amplitude_m: Pair = Field(title="Amplitude", description="[north, east] amplitude [m].")
    period_s: PositiveFloat = Field(title="Period", description="Period of the oscillation [s].")
    phase_rad: Phase = Field(0.0, title="Phase", description="Phase at t = 0 [rad].")


class CirclePath(Model):
    """center + radius [cos(2 pi t / T + phi), sin(2 pi t / T + phi)] (north, east)."""

    kind: Literal["circle"] = Field(title="Kind", description="Path kind.")
    center_m: Pair = Field([0.0, 0.0], title="Centre", description="[north, east] [m].")
    radius_m: PositiveFloat = Field(title="Radius", description="Circle radius [m].")
    period_s: PositiveFloat = Field(title="Period", description="Time for one lap [s].")
    phase_rad: Phase = Field(0.0, title="Phase", description="Angle at t = 0 [rad].")


class WaypointPath(Model):
    """Piecewise-linear through ``[t_s, north_m, east_m]`` points, held at the ends."""

    kind: Literal["waypoints"] = Field(title="Kind", description="Path kind.")
    points: Annotated[
        list[Annotated[list[float], Field(min_length=3, max_length=3)]], Field(min_length=1)
    ] = Field(title="Points", description="[time_s, north_m, east_m], increasing times.")

    _check = field_validator("points")(_increasing_times)


class ExpressionPath(Model):
    """north(t) and east(t) as safe expressions of ``t`` in seconds."""

    kind: Literal["expression"] = Field(title="Kind", description="Path kind.")
    north: Expression = Field(title="North", description="North position [m] as f(t).")
    east: Expression = Field(title="East", description="East position [m] as f(t).")

    _check = field_validator("north", "east")(_expression)


TargetPath = Annotated[
    LinePath | SinusoidPath | CirclePath | WaypointPath | ExpressionPath,
    Field(discriminator="kind"),
]


class TargetConfig(Model):
    """The moving target (index 0 of the paper)."""

    path: TargetPath = Field(title="Path", description="The target's planar path.")
    altitude_m: float = Field(
        0.0,
        ge=-MAX_ALTITUDE_M,
        le=MAX_ALTITUDE_M,
        title="Altitude",
        description="Height above home [m].",
    )


# --- Algorithm ------------------------------------------------------------------------------------


class ShapeConfig(Model):
    """Affine shaping of the circle, A = Translation @ Shearing @ Scaling; each entry a signal."""

    translate_north_m: Signal = Field(0.0, title="T_x", description="Translation north [m].")
    translate_east_m: Signal = Field(0.0, title="T_y", description="Translation east [m].")
    scale_north: Signal = Field(1.0, title="S_x", description="Scaling along north (> 0).")
    scale_east: Signal = Field(1.0, title="S_y", description="Scaling along east (> 0).")
    shear_a: Signal = Field(0.0, title="H_a", description="Shear of north by east.")
    shear_b: Signal = Field(0.0, title="H_b", description="Shear of east by north.")


class EstimatorSettingsConfig(Model):
    """The filter estimator's noise model and outlier gate (``algorithm.estimator: ekf``).

    The noise figures default to the scenario's model of the sensors (``sensors:``; a flight's
    odometry: ``flight.emulator.odometry``); on real hardware give the ranging radio's and the
    odometry's own figures here."""

    range_noise_std_m: NoiseStd | None = Field(
        None,
        title="Range noise",
        description="Std of one range [m] the filter assumes (default: from sensors:, the "
        "timestamp noise, pair bias, multipath and clock error in quadrature).",
    )
    range_common_std_m: NoiseStd | None = Field(
        None,
        title="Common range error",
        description="The part of a range's error both ends of a pair read alike [m], which "
        "algorithm.shared_ranges does not average away (default: all of it with "
        "sensors.range_scheme one_exchange_per_pair; with one_exchange_per_direction the pair's "
        "bias and multipath, sensors.range_bias_std_m and range_multipath_std_m in quadrature).",
    )
    displacement_noise_std_m: NoiseStd | None = Field(
        None,
        title="Displacement noise",
        description="Per-axis std of one vehicle's displacement over one step [m] the filter "
        "assumes (default: sensors.displacement_noise_std_m, with sensors.displacement_drift_m_s "
        "x timing.step_s added in quadrature; flown, from the emulator's odometry model "
        "flight.emulator.odometry; on real autopilots give it here).",
    )
    gate_chi2: Annotated[float, Field(gt=0, le=1e6)] | None = Field(
        10.83,
        title="Outlier gate",
        description="A range whose squared innovation exceeds this many innovation variances "
        "is rejected as an outlier (chi-square, 1 degree of freedom: 10.83 rejects 0.1 % of good "
        "ranges); null: no gate.",
    )
    nlos_gate_chi2: PositiveFloat = Field(
        6.63,
        title="Outlier gate under NLOS bursts",
        description="Where sensors: has NLOS bursts (range_outlier_probability and "
        "range_nlos_duration_s > 0) the gate is the smaller of gate_chi2 and this (6.63: 1 % "
        "of good ranges, half of it with gate_long_only), which catches more of a burst's small "
        "biases; a burst's accepted ranges pull an edge for as long as it lasts.",
    )
    gate_patience: Annotated[int, Field(ge=1)] | None = Field(
        None,
        title="Gate patience",
        description="Ranges of one edge rejected in a row after which the edge restarts from "
        "its regression (it has lost track). Default: 10, or with NLOS bursts "
        "(sensors.range_outlier_probability, range_nlos_duration_s) five mean bursts' steps, "
        "so that an edge coasts through a burst (99 % of them) instead of restarting on its "
        "biased ranges.",
    )
    gate_long_only: bool = Field(
        True,
        title="Gate long ranges only",
        description="Gate only ranges longer than predicted: NLOS reads long, never short, so a "
        "range far too short means the estimate is too long and the filter takes it. false: "
        "gate both sides.",
    )
    initial_forgetting_factor: float = Field(
        0.7,
        gt=0,
        le=1,
        title="Start-up beta_f",
        description="Forgetting factor of the cosine-law RLSE that starts each edge.",
    )
    handover_updates: Annotated[int, Field(ge=1)] = Field(
        10,
        title="Hand-over updates",
        description="Start-up RLSE updates before the filter may take an edge over.",
    )
    handover_std_m: Distance = Field(
        2.0,
        title="Hand-over std",
        description="The filter takes an edge over once the start-up RLSE's error bound (1 "
        "sigma, worst direction) is below this [m].",
    )


class AlgorithmConfig(Model):
    """The paper's parameters (ALGORITHM.md)."""

    beta: PositiveFloat = Field(title="beta", description="Consensus gain, < 1/step_s.")
    saturation_m_s: Speed = Field(title="Ubar", description="Bound of the consensus term [m/s].")
    forgetting_factor: float = Field(
        gt=0, le=1, title="beta_f", description="RLSE forgetting factor in (0, 1]."
    )
    omega_rad_s: Annotated[float, Field(gt=0, le=MAX_RATE_RAD_S)] = Field(
        title="omega", description="Natural frequency of the oscillators [rad/s]."
    )
    coupling_gain: Gain = Field(1.0, title="K_l", description="K_l for l < n (> 0).")
    coupling_gain_last: float = Field(
        -1.0, lt=0, ge=-MAX_GAIN, title="K_n", description="K_n (< 0, small in magnitude)."
    )
    radius_m: PositiveFloat = Field(
        le=MAX_COORDINATE_M,
        title="rho",
        description="Circle radius [m]; neighbours on it must be at least 0.1 m apart.",
    )
    initial_gain: PositiveFloat = Field(1.0, title="Gamma(0)", description="Gamma(0) = value * I.")
    estimator: Literal["rlse", "ekf"] = Field(
        "rlse",
        title="Estimator",
        description="Relative localization: rlse, the paper's cosine-law RLSE with forgetting "
        "factor beta_f; ekf, a per-edge extended Kalman filter on range and odometry with an "
        "outlier gate (estimator_settings), started by the RLSE.",
    )
    estimator_settings: EstimatorSettingsConfig = Field(
        EstimatorSettingsConfig(),
        title="Estimator settings",
        description="Noise model and outlier gate of the ekf estimator.",
    )
    shared_ranges: bool = Field(
        False,
        title="Shared ranges",
        description="Vehicles share their measured ranges in their step messages and estimate "
        "each pair from the mean of both ends' ranges (one end's where the other's is missing): "
        "the two estimates of a pair are then exactly opposite, so range noise cancels in the "
        "formation centre. Only with sensors.range_scheme one_exchange_per_direction does the "
        "mean have less variance (half of what is not common to the pair); with one exchange "
        "per pair both ends already read one number. false: the paper's own ranges.",
    )
    shape: ShapeConfig = Field(ShapeConfig(), title="Shape", description="Affine shaping.")
    target_lost_after_s: Annotated[float, Field(gt=0, le=MAX_DURATION_S)] = Field(
        10.0,
        title="Target lost after",
        description="While nobody senses the target every vehicle predicts it (constant "
        "velocity, from the freshest observation); after this long without an observation the "
        "formation declares it lost [s].",
    )
    target_on_lost: Literal["hold", "orbit"] = Field(
        "hold",
        title="On target lost",
        description="What the formation does once the target is lost: hold (every vehicle "
        "hovers in place) or orbit (the law goes on around the target's last estimate).",
    )


class TimingConfig(Model):
    """Discrete time of the law."""

    step_s: float = Field(ge=MIN_STEP_S, le=MAX_STEP_S, title="T", description="Step length [s].")
    steps: Annotated[int, Field(gt=0, le=10_000_000)] = Field(
        title="Steps", description="Number of steps to run."
    )


class VehicleConfig(Model):
    """One vehicle of the swarm."""

    id: Annotated[int, Field(gt=0, le=65535)] = Field(
        title="Id",
        description="Vehicle id (> 0; 0 is the target). Flying vehicles: the MAVLink system id.",
    )
    initial_position_m: Pair = Field(
        title="Initial position", description="[north, east] at k = 0 [m] (truth; never seen)."
    )
    initial_phase_rad: Phase = Field(title="theta(0)", description="Initial oscillator phase.")
    senses_target: bool = Field(
        False, title="Senses target", description="Ranges to the target (edge to index 0)."
    )
    omega_rad_s: Annotated[float, Field(gt=0, le=MAX_RATE_RAD_S)] | None = Field(
        None, title="omega_i", description="This vehicle's own frequency (default: algorithm's)."
    )
    speed_limit_m_s: Speed = Field(
        10.0, title="U_i", description="Horizontal speed bound of the vehicle [m/s]."
    )
    altitude_m: Altitude | None = Field(
        None,
        title="Altitude",
        description="Flying only: height above home it holds [m] (default: flight.altitude_m).",
    )
    url: str | None = Field(
        None,
        title="Connection",
        description="Flying real vehicles only: MAVSDK URL, e.g. udpin://0.0.0.0:14540 or "
        "serial:///dev/ttyACM0:57600. Unset: the bundled emulator.",
    )


class SensorConfig(Model):
    """Measurement imperfections (all off by default: the paper's noise-free model)."""

    range_noise_std_m: NoiseStd = Field(
        0.0, title="Range noise", description="Std of Gaussian range noise [m] (UWB: 0.05-0.1)."
    )
    range_dropout_probability: float = Field(
        0.0, ge=0, lt=1, title="Range dropout", description="Probability a range is missing."
    )
    range_max_m: Distance | None = Field(
        None, title="Range limit", description="Ranges beyond this are not measured [m]."
    )
    range_outlier_probability: float = Field(
        0.0,
        ge=0,
        lt=1,
        title="Range outliers",
        description="Probability a range is an NLOS outlier (the fraction of the time a pair "
        "is in an NLOS burst, range_nlos_duration_s): read long by a bias drawn uniformly from "
        "range_outlier_bias_m.",
    )
    range_outlier_bias_m: Pair = Field(
        [0.3, 3.0],
        title="Outlier bias",
        description="[low, high] of the extra length of an outlying range [m] (UWB through an "
        "obstacle reads long, never short).",
    )
    range_scheme: Literal["one_exchange_per_pair", "one_exchange_per_direction"] = Field(
        "one_exchange_per_pair",
        title="Ranging scheme",
        description="How the radios range: one_exchange_per_pair, one two-way exchange per pair "
        "and step whose range both ends read (the same number at the same instant); "
        "one_exchange_per_direction, each end runs its own exchange (its own timestamp noise, "
        "dropout and clock error; bias, multipath and NLOS common to the pair).",
    )
    range_bias_std_m: NoiseStd = Field(
        0.0,
        title="Pair bias",
        description="Std of a per-pair range bias constant over the mission [m] (what is left "
        "of both radios' antenna delays after calibration; Decawave APS014: one delay tick is "
        "4.7 mm, and the range moves 2.15 mm per degree C).",
    )
    range_multipath_std_m: NoiseStd = Field(
        0.0,
        title="Multipath",
        description="Stationary std of a pair's slowly varying range error [m] (multipath and "
        "the received-level bias of Decawave APS011, +11 to -20 cm over the DW1000's range of "
        "signal levels), a Gauss-Markov process with range_multipath_correlation_s.",
    )
    range_multipath_correlation_s: Annotated[float, Field(gt=0, le=MAX_DURATION_S)] = Field(
        2.0,
        title="Multipath correlation",
        description="Correlation time of the multipath error [s]: it decays by 1/e over this.",
    )
    range_nlos_duration_s: Annotated[float, Field(ge=0, le=MAX_DURATION_S)] = Field(
        2.0,
        title="NLOS burst",
        description="Mean duration of an NLOS burst [s]: a pair behind an obstacle reads long "
        "by one bias (range_outlier_bias_m) until the burst ends; range_outlier_probability is "
        "the fraction of the time a pair spends in bursts. 0: independent outliers per step.",
    )
    range_clock_offset_std_ppm: Annotated[float, Field(ge=0, le=MAX_CLOCK_OFFSET_PPM)] = Field(
        0.0,
        title="Clock offset",
        description="Std of each radio's crystal offset [ppm]; single-sided TWR then reads "
        "1/2 c range_reply_time_s (e_initiator - e_responder) off (Decawave APS011). "
        "DW1000/DW3000 crystals are trimmed to about 2 ppm; 0: double-sided TWR (negligible).",
    )
    range_reply_time_s: Annotated[float, Field(gt=0, le=MAX_REPLY_TIME_S)] = Field(
        3e-4,
        title="Reply time",
        description="The responder's reply delay in a single-sided exchange [s].",
    )
    range_exchange_s: Annotated[float, Field(gt=0, le=MAX_REPLY_TIME_S)] | None = Field(
        None,
        title="Exchange airtime",
        description="Channel time one ranging exchange takes [s] (a DS-TWR exchange of three "
        "frames: about 1-3 ms at 6.8 Mbps with guard times): a step carries "
        "floor(timing.step_s / this) exchanges, given to the pairs in turn (TDMA), so a large "
        "swarm ranges a pair every few steps. None: every pair every step.",
    )
    displacement_noise_std_m: NoiseStd = Field(
        0.0, title="Flow noise", description="Std of per-step displacement noise, per axis [m]."
    )
    displacement_drift_m_s: Annotated[float, Field(ge=0, le=MAX_SPEED_M_S)] = Field(
        0.0,
        title="Flow drift",
        description="Magnitude of a constant odometry drift per vehicle, random direction [m/s].",
    )
    target_sensing_range_m: Distance | None = Field(
        None,
        title="Target sensing range",
        description="A tracker sees the target only within this horizontal distance [m]: as "
        "the formation turns, who senses it changes (default: at any distance).",
    )
    target_dropout_probability: float = Field(
        0.0,
        ge=0,
        lt=1,
        title="Target dropout",
        description="Probability that a tracker misses the target at a step (randomly "
        "intermittent sensing).",
    )

    @field_validator("range_outlier_bias_m")
    @classmethod
    def _bias_interval(cls, bias: list[float]) -> list[float]:
        if not 0 <= bias[0] <= bias[1] <= MAX_COORDINATE_M:
            raise ValueError(f"must be [low, high] with 0 <= low <= high <= {MAX_COORDINATE_M:g} m")
        return bias


#: Events only a flight can play (they need real links, sensors or autopilots); the numeric
#: simulator refuses a scenario with any of them.
FLIGHT_ONLY_EVENTS = frozenset({"link_lost", "taken_over"})
#: Sensors whose loss only a flight can play (the numeric model has no flow odometry to fail).
FLIGHT_ONLY_SENSORS = frozenset({"flow"})


class EventConfig(Model):
    """Something that happens to a vehicle at a step (or a time)."""

    kind: Literal[
        "vehicle_lost", "vehicle_joins", "link_lost", "sensor_lost", "taken_over", "target_hidden"
    ] = Field(
        title="Kind",
        description="vehicle_lost: dies for good; vehicle_joins: absent until then "
        "(simulate only); link_lost: its MAVLink link drops (flying only); sensor_lost: a "
        "sensor stops (flow: flying only); taken_over: a pilot switches it to `mode` by RC, "
        "or another ground station disarms it (flying on the emulator only); target_hidden: "
        "the target is hidden from every tracker (or from `vehicle`'s) for `duration_s` (an "
        "occlusion).",
    )
    vehicle: int | None = Field(
        None, title="Vehicle", description="Vehicle id (target_hidden: default every vehicle)."
    )
    at_step: Annotated[int, Field(ge=0)] | None = Field(None, title="Step", description="k.")
    at_s: NonNegativeFloat | None = Field(None, title="Time", description="Time after k = 0 [s].")
    duration_s: Annotated[float, Field(gt=0, le=MAX_DURATION_S)] | None = Field(
        None,
        title="Duration",
        description="link_lost / sensor_lost / target_hidden: how long (default: for good).",
    )
    sensor: Literal["uwb", "flow", "tracker"] | None = Field(
        None, title="Sensor", description="sensor_lost: which sensor stops."
    )
    mode: Literal["hold", "land", "return", "posctl", "disarm"] = Field(
        "hold",
        title="Mode",
        description="taken_over: the mode the pilot switches to, or disarm: another ground "
        "station force-disarms it (in the air too).",
    )
    rearm_after_s: PositiveFloat | None = Field(
        None,
        title="Re-arm after",
        description="taken_over: the pilot arms it again this long after [s], as a pilot does "
        "after a forced disarm (PX4's arming checks apply).",
    )

    def step(self, step_s: float) -> int:
        """The step index at which the event takes effect."""
        if self.at_step is not None:
            return self.at_step
        if self.at_s is None:
            # Scenario validation reports this at the event's YAML path before anything asks.
            raise ValueError(f"event {self.kind} of vehicle {self.vehicle}: no at_step or at_s")
        steps = self.at_s / step_s - 1e-9
        return math.ceil(steps) if math.isfinite(steps) else sys.maxsize

    def duration_steps(self, step_s: float) -> int | None:
        """How many steps a ``duration_s`` window covers from :meth:`step` (None: for good)."""
        if self.duration_s is None:
            return None
        steps = self.duration_s / step_s - 1e-9
        return max(1, math.ceil(steps)) if math.isfinite(steps) else sys.maxsize


class BatchConfig(Model):
    """How ``--runs N`` varies the runs after the first (run 0 is the scenario as pinned)."""

    position_spread_m: Annotated[float, Field(ge=0, le=MAX_COORDINATE_M)] = Field(
        2.0, title="Position spread", description="Initial positions jitter, uniform in a disc."
    )
    randomize_phases: bool = Field(
        True, title="Random phases", description="Draw initial phases uniformly in [0, 2 pi)."
    )


class MetricsConfig(Model):
    """Tolerances that define 'converged' in the summary."""

    tracking_tolerance_m: Distance = Field(0.05, title="Tracking tol.", description="[m].")
    localization_tolerance_m: Distance = Field(1e-3, title="Localization tol.", description="[m].")
    phase_tolerance_rad: float = Field(
        0.01, gt=0, le=math.pi, title="Phase tol.", description="[rad]."
    )


SimulationMetricName = Literal[
    "final_tracking_error_m",
    "tail_tracking_error_rms_m",
    "tail_localization_error_median_m",
    "tail_localization_error_rms_m",
    "final_localization_error_m",
    "final_phase_spacing_error_rad",
    "tracking_converged_step",
    "localization_converged_step",
    "phase_converged_step",
    "max_consensus_speed_m_s",
    "max_speed_m_s",
    "min_separation_m",
    "final_live_vehicles",
    "gated_ranges",
    "target_lost_step",
    "max_tracking_error_after_convergence_m",
]
FlightMetricName = Literal[
    "vehicles_disarmed_at_end",
    "vehicles_disarmed_in_air",
    "vehicles_in_formation_at_end",
    "steps_on_stale_data",
]
#: Every metric an ``expect:`` bound may name (nested literals flatten into one).
MetricName = Literal[SimulationMetricName, FlightMetricName]
METRICS: tuple[SimulationMetricName, ...] = get_args(SimulationMetricName)
FLIGHT_METRICS: tuple[FlightMetricName, ...] = get_args(FlightMetricName)


class Expectation(Model):
    """Bounds a metric must respect for the scenario to pass."""

    max: float | None = Field(None, title="Maximum", description="Metric must be <= this.")
    min: float | None = Field(None, title="Minimum", description="Metric must be >= this.")

    @model_validator(mode="after")
    def _can_pass(self) -> Self:
        if self.min is not None and self.max is not None and self.min > self.max:
            raise ValueError(
                f"min {self.min:g} is above max {self.max:g}: no value can pass; give min <= max"
            )
        return self


class RangeCheckConfig(Model):
    """Which ranges are physically possible: the rest are dropped where they enter a vehicle's
    controller, before the estimator, and counted (``mission_runner.runner.plausibility``)."""

    max_range_m: Distance | None = Field(
        None,
        title="Radio reach",
        description="Longest range the radio measures [m]; None: sensors.range_max_m, else "
        "300 m (UWB line of sight).",
    )
    max_relative_speed_m_s: Annotated[float, Field(gt=0, le=2 * MAX_SPEED_M_S)] | None = Field(
        None,
        title="Relative speed bound",
        description="How fast a range can change [m/s]; None: twice the fastest vehicle's "
        "speed limit (the target is slower than the vehicles that enclose it).",
    )
    margin_m: Annotated[float, Field(ge=0, le=MAX_COORDINATE_M)] | None = Field(
        None,
        title="Noise margin",
        description="Change a range may show beyond the speed bound, from noise [m]; None: "
        "0.2 m plus six times the difference of two noisy ranges' std.",
    )


class DisplacementTrackingConfig(Model):
    """A PI correction that makes the vehicle realise the displacement the law commands."""

    gain_1_s: Annotated[float, Field(ge=0, le=MAX_GAIN)] = Field(
        0.0,
        title="Proportional gain",
        description="Velocity added per metre between the vehicle's odometry and where the law's "
        "commands would have taken it [1/s] (0: off).",
    )
    integral_gain_1_s2: Annotated[float, Field(ge=0, le=MAX_GAIN)] = Field(
        0.0,
        title="Integral gain",
        description="Velocity added per metre-second of that error [1/s^2]: removes a steady "
        "shortfall, e.g. a velocity loop losing to drag (0: off).",
    )
    max_correction_m_s: Speed = Field(
        2.0, title="Correction bound", description="Largest correction [m/s]."
    )


class SafetyConfig(Model):
    """Keeping vehicles apart: the paper has no collision avoidance, so the guard is an addition
    (off by default, to keep the paper's behaviour)."""

    min_separation_m: Distance | None = Field(
        None,
        title="Minimum separation",
        description="Vehicles keep at least this horizontal distance [m]: a guard between the "
        "law and the setpoint, from measured ranges and the estimates (never truth), in simulate "
        "and in flight. None: no guard.",
    )
    separation_gain_1_s: Gain = Field(
        4.0,
        title="Separation gain",
        description="How fast two vehicles may close on the minimum separation [1/s]: their "
        "distance above it shrinks by at most gain x step_s (capped at 1) of itself per step; "
        "up to 0.5 per step the guard stays safe even when the pair's step messages are lost.",
    )
    separation_margin_m: Annotated[float, Field(ge=0, le=MAX_COORDINATE_M)] | None = Field(
        None,
        title="Separation margin",
        description="Distance the guard keeps beyond min_separation_m [m], for range noise and "
        "estimate error. None: three times sensors.range_noise_std_m (0 without range noise).",
    )
    separation_braking_m_s2: Annotated[float, Field(gt=0, le=MAX_ACCELERATION_M_S2)] | None = Field(
        None,
        title="Braking",
        description="Deceleration each vehicle can count on [m/s^2]: two vehicles close no "
        "faster than they could still stop before the minimum separation. None: velocity "
        "changes at once (the numeric model); flying, about half the autopilot's MPC_ACC_HOR.",
    )
    separation_latency_s: Annotated[float, Field(ge=0, le=MAX_WAIT_S)] = Field(
        0.0,
        title="Command latency",
        description="How long commands in force keep closing a pair before a new one acts [s] "
        "(the velocity loop's response and the command delay; 0 in the numeric model).",
    )


class FlightConfig(Model):
    """How ``mission-runner run`` flies the scenario (ignored by ``simulate``)."""

    altitude_m: Altitude = Field(
        5.0, title="Altitude", description="Default height above home every vehicle holds [m]."
    )
    end_action: Literal["land", "hold", "return"] = Field(
        "land", title="At the end", description="What vehicles do when the mission ends."
    )
    on_lost: Literal["land", "hold", "return"] = Field(
        "land",
        title="On loss",
        description="What a vehicle does when its controller gives up on it (own odometry "
        "gone, link dead, mission aborted): its process commands it if the link still works, "
        "and the autopilot's offboard-loss failsafe is set to the same (PX4 COM_OBL_RC_ACT).",
    )
    autopilot_params: dict[
        Annotated[str, Field(min_length=1, max_length=16, pattern=r"^[A-Z0-9_]+$")],
        float | int,
    ] = Field(
        {},
        title="Autopilot parameters",
        description="PX4 parameters set over MAVLink on every vehicle, emulated or real, before "
        "take-off and read back (integers are INT32, other numbers REAL32), e.g. "
        "{MPC_ACC_HOR: 5.0}.",
    )
    clock: Literal["lockstep", "realtime"] = Field(
        "lockstep",
        title="Clock",
        description="Emulator time: lockstep (as fast as the controllers go, deterministic "
        "timing) or realtime (optionally sped up by speed).",
    )
    speed: float = Field(
        1.0,
        gt=0,
        le=MAX_CLOCK_SPEED,
        title="Speed",
        description="Real-time speed factor (the emulator runs up to 1000x).",
    )
    start_delay_s: Annotated[float, Field(ge=0, le=MAX_WAIT_S)] = Field(
        1.0, title="Start delay", description="Hover time between OFFBOARD and k = 0 [s]."
    )
    step_deadline_s: Wait = Field(
        0.04,
        title="Step deadline",
        description="How long after t_k a vehicle waits for the step's messages and ranges [s].",
    )
    lockstep_wait_s: Wait = Field(
        0.5,
        title="Lockstep wait",
        description="In lockstep, simulated time stands still while a vehicle waits for a step's "
        "messages; after this many wall seconds it goes on without the missing ones.",
    )
    silence_timeout_s: Wait = Field(
        1.0,
        title="Silence timeout",
        description="No fresh neighbour data for this long: stop following the law and hold [s].",
    )
    member_timeout_steps: Annotated[int, Field(ge=1)] = Field(
        8,
        title="Member timeout",
        description="A neighbour unheard for this many steps leaves the formation (n shrinks).",
    )
    max_vertical_speed_m_s: Speed = Field(
        1.0, title="Vertical speed", description="Bound of the altitude-hold velocity [m/s]."
    )
    velocity_lead_s: Annotated[float, Field(ge=0, le=10.0)] = Field(
        0.0,
        title="Velocity lead",
        description="Command u + lead * du/dt to offset the vehicle's velocity response time and "
        "the command delay [s] (0: the paper's pure velocity command).",
    )
    displacement_tracking: DisplacementTrackingConfig = Field(
        DisplacementTrackingConfig(),
        title="Displacement tracking",
        description="Close the loop on the own odometry so the vehicle moves T u(k) per step "
        "as the paper's model assumes; needed on airframes whose velocity loop lags or loses "
        "to drag (PX4 SIH), off by default.",
    )
    range_check: RangeCheckConfig = Field(
        RangeCheckConfig(),
        title="Range plausibility",
        description="Ranges that cannot be (negative, beyond the radio's reach, changing "
        "faster than the vehicles can move) are dropped before the estimator and counted.",
    )
    emulator: dict[str, Any] = Field(
        {},
        title="Emulator",
        description="Settings passed to the bundled emulator (sitl.config.EmulatorConfig: "
        "physics, wind, odometry, telemetry, ports, params, tlog_dir).",
    )

    @field_validator("autopilot_params")
    @classmethod
    def _fit_mavlink(cls, params: dict[str, float | int]) -> dict[str, float | int]:
        # PARAM_SET carries INT32 or REAL32: a larger number would reach the autopilot changed.
        for name, value in params.items():
            if isinstance(value, int) and not INT32_RANGE[0] <= value <= INT32_RANGE[1]:
                raise ValueError(
                    f"{name}: {value} does not fit an INT32 parameter "
                    f"({INT32_RANGE[0]}..{INT32_RANGE[1]})"
                )
            if isinstance(value, float) and abs(value) > REAL32_MAX:
                raise ValueError(
                    f"{name}: {value:g} does not fit a REAL32 parameter (|x| <= {REAL32_MAX:.7g})"
                )
        return params


class Scenario(Model):
    """A whole mission."""

    name: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")] = Field(
        title="Name", description="Short name, used for output folders."
    )
    description: str = Field("", title="Description", description="What the scenario shows.")
    seed: Annotated[int, Field(ge=0)] = Field(0, title="Seed", description="RNG seed.")
    timing: TimingConfig = Field(title="Timing", description="Step length and count.")
    algorithm: AlgorithmConfig = Field(title="Algorithm", description="Law parameters.")
    target: TargetConfig = Field(title="Target", description="The moving target.")
    vehicles: Annotated[list[VehicleConfig], Field(min_length=1, max_length=4096)] = Field(
        title="Vehicles", description="The swarm."
    )
    sensors: SensorConfig = Field(SensorConfig(), title="Sensors", description="Noise model.")
    events: list[EventConfig] = Field([], title="Events", description="Losses and joins.")
    batch: BatchConfig = Field(BatchConfig(), title="Batch", description="For --runs N.")
    metrics: MetricsConfig = Field(MetricsConfig(), title="Metrics", description="Tolerances.")
    safety: SafetyConfig = Field(
        SafetyConfig(), title="Safety", description="Separation guard (simulate and flight)."
    )
    flight: FlightConfig = Field(
        FlightConfig(), title="Flight", description="How mission-runner run flies it."
    )
    bus: BusSettings = Field(
        BusSettings(),
        title="Bus",
        description="Vehicle message bus: in-process by default, or kind: mqtt with host, port, "
        "credentials and TLS.",
    )
    expect: dict[MetricName, Expectation] = Field(
        {}, title="Expectations", description="Pass/fail bounds on summary metrics."
    )

    @field_validator("name")
    @classmethod
    def _plain_file_name(cls, name: str) -> str:
        # The name is a folder under out/: "." or ".." would write into out/ or beside it.
        if name in (".", ".."):
            raise ValueError(f"must be a plain file name, not {name!r} (it names output folders)")
        return name


# --- Loading --------------------------------------------------------------------------------------


def scenario_json_schema() -> dict[str, Any]:
    """The scenario's JSON Schema (draft 2020-12), from the model: what an editor's YAML
    language server checks and completes as one writes a scenario (titles and descriptions as
    hover text). Rules across fields (``beta < 1/step_s``, unique vehicle ids, events naming
    vehicles that exist) cannot be said in JSON Schema: loading the file checks those."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        **Scenario.model_json_schema(),
    }


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


#: MAVLink system ids are one byte (0 is broadcast): a flying vehicle's id is its system id.
MAX_MAVLINK_ID = 255


def flight_problems(scenario: Scenario) -> list[Problem]:
    """What a scenario valid for the numeric model cannot fly: vehicle ids beyond MAVLink's."""
    return [
        (
            f"vehicles[{index}].id",
            f"{vehicle.id} is not a MAVLink system id (1..{MAX_MAVLINK_ID}); a flying vehicle's "
            "id is its autopilot's system id",
        )
        for index, vehicle in enumerate(scenario.vehicles)
        if vehicle.id > MAX_MAVLINK_ID
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
    from .scenario import shape_matrices, target_positions  # noqa: PLC0415 - imports this module

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

    from .wiring import emulator_settings  # noqa: PLC0415 - wiring imports this module

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
    from .scenario import signal_values  # noqa: PLC0415 - scenario imports this module

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
    from .scenario import target_positions  # noqa: PLC0415 - scenario imports this module

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

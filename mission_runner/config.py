"""The scenario model: one typed YAML file describes a mission, for the simulator, the emulator and
the flying runner alike. It is validated once at load (:mod:`.checks` reads the file and adds the
rules that span fields); every problem is reported with its YAML path
(``vehicles[2].initial_phase_rad``) and the rule it breaks, before anything runs or is written.

Planar quantities are ``[north, east]`` pairs in metres (m/s for velocities): the paper's ``[x, y]``
is ``[north, east]`` here. Time-varying values (the target's path, the affine shape) are data:
constants, sinusoids, waypoints or safe expressions of ``t`` (see :mod:`.expressions`); never
Python code.
"""

from __future__ import annotations

import itertools
import logging
import math
import sys
from typing import TYPE_CHECKING, Annotated, Any, Literal, Self, get_args

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    field_validator,
    model_serializer,
    model_validator,
)

from .bus.settings import BusSettings
from .expressions import ExpressionError, compile_expression
from .limits import MAX_CLOCK_SPEED, MAX_NOISE_STD_M, MAX_WAIT_S

if TYPE_CHECKING:
    pass

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
#: A radio crystal's offset [ppm]: UWB radios are trimmed to a few; 1000 is a broken one.
MAX_CLOCK_OFFSET_PPM = 1000.0
#: A ranging exchange's reply delay or airtime [s]: milliseconds; a second is no UWB radio.
MAX_REPLY_TIME_S = 1.0
#: Frequencies of the oscillators [rad/s]: 100 rad/s is 16 turns a second, beyond any formation.
MAX_RATE_RAD_S = 100.0
#: Phases [rad]: every angle is within one turn; far larger numbers are typos and lose the
#: precision of sin and cos.
MAX_PHASE_RAD = 1000.0
#: Gains of the law and of the controllers [1/s, 1/s^2, dimensionless]: far beyond a stable one.
MAX_GAIN = 1000.0
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


class GraphConfig(Model):
    """The neighbourhood graph (``algorithm.graph``): one graph for the oscillator coupling, the
    consensus and the ranging schedule. Vehicle indices are positions in ``vehicles:`` from 0."""

    kind: Literal["complete", "ring", "k_nearest", "edges"] = Field(
        "complete",
        title="Kind",
        description="complete: every vehicle a neighbour of every other (the paper); ring: "
        "the two adjacent in the order of vehicles:, the last next to the first (a lost "
        "vehicle's two neighbours become neighbours); k_nearest: the k nearest at the start "
        "(vehicles' initial_position_m, made symmetric, fixed for the run); edges: the "
        "undirected edges given. The graph must be connected.",
    )
    k: Annotated[int, Field(ge=1, le=4096)] | None = Field(
        None, title="k", description="Neighbours of each vehicle for k_nearest (>= 1)."
    )
    edges: Annotated[list[list[int]], Field(max_length=100_000)] | None = Field(
        None,
        title="Edges",
        description="Undirected edges [i, j] between vehicle indices for kind edges.",
    )


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
    graph: GraphConfig = Field(
        GraphConfig(),
        title="Neighbourhood graph",
        description="Who couples, ranges and reaches consensus with whom (default: complete).",
    )
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

    @model_serializer(mode="wrap")
    def _without_default_graph(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """The complete graph (the default) is left out of dumps, so that a scenario without
        ``graph:`` records (summary.json, the recording) exactly as before the field existed."""
        data: dict[str, Any] = handler(self)
        if self.graph == GraphConfig():
            data.pop("graph", None)
        return data


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
    "graph_disconnected_step",
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

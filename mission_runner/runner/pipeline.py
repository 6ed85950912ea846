"""The pure part of a controller's step; :mod:`.controller` is the I/O around it.

What a step does, from what arrived (:func:`decide`): fly the law, or hold. And the chain that
makes the law's command the one the vehicle flies, in this order: the law's velocity, led
(:meth:`CommandShaper.lead`), plus the displacement-tracking correction
(:meth:`CommandShaper.tracking`), through the separation guard (:func:`separated`), clamped to
the vehicle's speed (:func:`clamp_horizontal`); the vertical velocity is the altitude hold's
(:func:`altitude_hold_m_s`). No clock, bus or vehicle link here: each piece is called alone in
tests. Velocities are north-east ``(2,)`` [m/s], positions north-east ``(2,)`` [m].
"""

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..enclosing import LOST, VehicleCommand
from ..enclosing.control import saturate
from ..enclosing.separation import separation_guard
from ..records import ControllerState


@dataclass(frozen=True)
class StepDecision:
    """What a step does: its state, and whether it flies the law (else it holds: zero
    horizontal velocity, the oscillator turned without data)."""

    state: ControllerState
    flies: bool


def decide(
    *,
    has_odometry: bool,
    stale_s: float,
    silence_timeout_s: float,
    in_control: bool,
    operator_hold: bool,
    target_status: int,
    target_on_lost: str,
) -> StepDecision:
    """What a step does, from what arrived for it.

    has_odometry: the own odometry at t_k came. stale_s: since anything fresh was last heard
    from a neighbour [s]; more than ``silence_timeout_s`` is stale. in_control: the vehicle is
    seen armed in OFFBOARD. operator_hold: the ground station's hold is on. target_status: the
    target track's (:data:`.enclosing.target.STATUS_NAMES` index). target_on_lost: ``hold`` or
    ``orbit`` (the law around the target's last estimate).

    On stale data or out of control: ``holding``, which the operator's hold does not mask
    (else ``held``); without odometry ``holding``; with the target lost ``target_lost``, held
    or orbiting; else ``following``.
    """
    holding = stale_s > silence_timeout_s or not in_control
    if operator_hold and not holding:
        return StepDecision(ControllerState.HELD, flies=False)
    if holding or not has_odometry:
        return StepDecision(ControllerState.HOLDING, flies=False)
    if target_status == LOST:
        return StepDecision(ControllerState.TARGET_LOST, flies=target_on_lost != "hold")
    return StepDecision(ControllerState.FOLLOWING, flies=True)


@dataclass
class CommandShaper:
    """The stateful links of the chain: lead and displacement tracking.

    step_s: the step T [s]. lead_s: the velocity lead [s] (0: off). gain_1_s,
    integral_gain_1_s2: the tracking PI's gains (both 0: off); max_correction_m_s: the most it
    adds [m/s].
    """

    step_s: float
    lead_s: float
    gain_1_s: float
    integral_gain_1_s2: float
    max_correction_m_s: float
    #: The law's last command (None: lead from nothing).
    previous_m_s: NDArray[np.float64] | None = None
    #: Where the law's commands so far would have taken the vehicle (None: start from where it
    #: is at the next step).
    reference_m: NDArray[np.float64] | None = None
    integral_m_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2))

    def hold(self) -> None:
        """The vehicle holds: when it resumes, track afresh from where it is, and lead from
        nothing (a command change over the whole hold is not a rate to lead)."""
        self.previous_m_s = None
        self.reference_m = None
        self.integral_m_s = np.zeros(2)

    def skip(self) -> None:
        """A step skipped: the reference restarts from where the vehicle is next."""
        self.reference_m = None

    def lead(self, velocity_m_s: ArrayLike) -> NDArray[np.float64]:
        """u + lead * du/dt: offsets the vehicle's velocity-loop lag and the command delay, so
        the displacement over the step is the one the law asked for."""
        velocity = np.asarray(velocity_m_s, dtype=float)
        previous, self.previous_m_s = self.previous_m_s, velocity
        if previous is None or self.lead_s == 0:
            return velocity
        return velocity + self.lead_s * (velocity - previous) / self.step_s

    def tracking(self, velocity_m_s: ArrayLike, here_m: ArrayLike) -> NDArray[np.float64]:
        """Displacement tracking: a PI correction towards where the law's commands would have
        taken a vehicle that realised them exactly (the paper's p(k+1) = p(k) + T u(k)), from
        the own odometry ``here_m``. A real multicopter's velocity loop lags and loses to drag
        (PX4 SIH: ~30 % of a 3 m/s command on a circle); the law's saturated consensus cannot
        make that up, the formation then trails the target. Off when both gains are 0 (the
        paper's pure command)."""
        if self.gain_1_s == 0 and self.integral_gain_1_s2 == 0:
            return np.zeros(2)
        here = np.asarray(here_m, dtype=float)
        if self.reference_m is None:
            self.reference_m = here.copy()
        error = self.reference_m - here
        limit = self.max_correction_m_s
        correction: NDArray[np.float64] = self.gain_1_s * error + self.integral_m_s
        if np.hypot(*correction) < limit:  # no wind-up while saturated
            self.integral_m_s = self.integral_m_s + (self.integral_gain_1_s2 * error * self.step_s)
        scale = min(1.0, limit / max(float(np.hypot(*correction)), 1e-12))
        self.reference_m = self.reference_m + self.step_s * np.asarray(velocity_m_s, dtype=float)
        return correction * scale


@dataclass(frozen=True)
class SeparationSettings:
    """The separation guard's settings (see :func:`.enclosing.separation.separation_guard`)."""

    min_separation_m: float
    gain_1_s: float
    step_s: float
    margin_m: float | None
    braking_m_s2: float | None
    latency_s: float
    range_noise_std_m: float


def separated(
    velocity_m_s: NDArray[np.float64],
    command: VehicleCommand,
    ranges_m: Mapping[int, float],
    *,
    own_in_force_m_s: tuple[float, float] | None,
    in_force_m_s: Mapping[int, tuple[float, float] | None],
    settings: SeparationSettings,
) -> NDArray[np.float64]:
    """The command through the separation guard: directions from the step's estimates
    (``command``, the law's), distances from the measured (horizontal) ranges by peer id, the
    pair's motion from the setpoints in force (the own, and the neighbours' by peer id, from
    their step messages; None or missing: not known). Never truth."""
    estimates_m, bearing_std = command.estimates_m, command.bearing_std_rad
    peers = [peer for peer in estimates_m if peer != 0]
    if not peers:
        return velocity_m_s

    def known(peer: int) -> tuple[float, float]:
        theirs = in_force_m_s.get(peer)
        return (math.nan, math.nan) if theirs is None else theirs

    return separation_guard(
        np.asarray(velocity_m_s, dtype=float),
        np.array([estimates_m[peer] for peer in peers], dtype=float),
        np.array([ranges_m.get(peer, math.nan) for peer in peers], dtype=float),
        np.array(own_in_force_m_s or (math.nan, math.nan), dtype=float),
        np.array([known(peer) for peer in peers], dtype=float),
        min_separation_m=settings.min_separation_m,
        gain_1_s=settings.gain_1_s,
        step_s=settings.step_s,
        margin_m=settings.margin_m,
        braking_m_s2=settings.braking_m_s2,
        latency_s=settings.latency_s,
        range_noise_std_m=settings.range_noise_std_m,
        bearing_std_rad=np.array([bearing_std.get(peer, math.nan) for peer in peers]),
    )


def clamp_horizontal(velocity_m_s: ArrayLike, limit_m_s: float) -> tuple[float, float]:
    """The velocity scaled down to at most ``limit_m_s`` [m/s], its direction kept."""
    clamped = saturate(np.asarray(velocity_m_s, dtype=float), limit_m_s)
    return (float(clamped[0]), float(clamped[1]))


def altitude_hold_m_s(
    down_m: float | None, *, altitude_m: float, gain_1_s: float, limit_m_s: float
) -> float:
    """The vertical (NED: down positive) velocity [m/s] that holds ``altitude_m`` (up, above
    home) from the own odometry's ``down_m`` (None: not known, 0)."""
    if down_m is None:
        return 0.0
    error = -altitude_m - down_m
    return float(np.clip(gain_1_s * error, -limit_m_s, limit_m_s))


@dataclass(frozen=True)
class StepCommand:
    """What a step commands (its horizontal velocity) and what the law used for it, as the
    step's record keeps it (a hold: none of it)."""

    velocity_m_s: tuple[float, float] = (0.0, 0.0)
    consensus_m_s: tuple[float, float] = (0.0, 0.0)
    neighbours_used: tuple[int, ...] = ()
    estimates_m: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    gated: tuple[int, ...] = ()
    ranges_m: dict[int, float] = field(default_factory=dict)

"""A separation guard between the enclosing law and the velocity setpoint (numpy only).

The paper's law has no collision avoidance: vehicles crossing the circle to their slots can pass
arbitrarily close. The guard changes a vehicle's command u_i as little as possible so that the
distance d_j to every neighbour j, with h_j = d_j - d_min, obeys a discrete-time barrier
condition over the step T the command is held for:

    h_j(k+1)  >=  (1 - gamma) h_j(k),        gamma = min(gain T, 1)

Written on the commands: with n_j the unit vector from j to this vehicle,
d_j(k+1) = |p_i - p_j + T (u_i - u_j)| >= d_j + T n_j . (u_i - u_j) (the norm is convex: motion
across n_j only opens the distance), so the condition holds if the pair's closing speed
w_j = -n_j . (u_i - u_j) is at most gamma h_j / T. Where the vehicles cannot stop at once
(``braking_m_s2``: each brakes at least that hard), the pair must also still be able to stop
within h_j: w_j <= 2 sqrt(braking h_j). Where commands take effect late (``latency_s``: a
velocity loop's response and the command's delay), h_j is first shrunk by what the commands
now in force close in that time.

Neither vehicle knows the other's next command, so each takes half of the allowed closing
speed, around a reference both compute alike: half the pair's commands in force along n_j (the
command each vehicle set at the last step and sends in its step message), c_j:

    n_j . u_i  >=  c_j - w_j / 2,     c_j = clip(n_j . (u_i' + u_j') / 2, -w_j / 2, w_j / 2)

If both run the guard, the pair closes no faster than w_j; a formation moving together needs
no change. The clip keeps u = 0 allowed while every h_j >= 0 (the conditions can always be met,
however many neighbours are close), and bounds what two references that disagree (a lost
message counts as a zero command) can cost: at most 2 w_j, which with gamma <= 1/2 still keeps
h_j >= 0.

Directions come from the vehicle's estimates of p_i - p_j (RLSE); one whose length disagrees
with the measured range (an estimator still converging) is not trusted, and the vehicle then
keeps its speed below w_j / 2 instead. A length that agrees says little about the bearing (an
early estimate, or with range noise a regression starved of motion, can point well off), so
where the estimator gives how far its bearing may be off (``bearing_std_rad``, from a bound of
its error) a direction is trusted only within a cone of ``CONE_SIGMAS`` of those stds, and the
condition must hold for every direction in it; a cone wider than ``MAX_CONE_RAD`` gives none.
The distance kept gets ``RANGE_SIGMAS`` sigma_r beyond d_min unless the caller sets the margin,
so that a range reading long does not eat into d_min.

Symmetric deadlocks (two vehicles head on, each held by
the other at the minimum separation) are broken by turning right: near the distance kept, the
part of the law's approach that a condition cuts is partly given back across n_j, to the
vehicle's right, which closes no distance; both turn right and pass each other.

The command kept is the projection of the (turned) command onto the intersection of the
conditions (Dykstra's alternating projections), scaled towards zero if a few sweeps left it
outside: zero is inside, and the set is convex. Scaling it down later (a speed limit) keeps it
inside for the same reason.

It sees only what a vehicle knows: its estimates, its measured ranges, its own last command and
its neighbours' step messages; never ground truth. Shapes: any leading batch dimensions ``...``,
m neighbours.
"""

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

#: Dykstra sweeps over the constraints; a few suffice for the handful of neighbours close at once.
SWEEPS = 12
#: An estimate whose length is off the measured range by more than this fraction is not trusted
#: for a direction (the estimator has not converged, or the neighbour moved unseen). At 0.2, an
#: early estimate 19 % short and 35 degrees off was trusted and a pair met at 0.89 m (one of
#: 1000 random starts of separation_guard.yaml); at 0.1 none of 2 x 1000 came below 0.94 m.
TRUST_FRACTION = 0.1
#: Of the command a condition cuts, this fraction is given back to the vehicle's right (across
#: the line to the neighbour) when the pair is stuck: enough to slide past a vehicle met head on
#: within a few steps.
TURN_FRACTION = 0.5
#: Stuck: within this fraction of the minimum separation of the distance kept, and the neighbour
#: not moving away. Farther out the law is left to sort the pair out: the turn is a deviation
#: the law's saturated consensus must work off, and turning at every close pass measurably kept
#: formations from converging (paper scenario, 1000 random starts).
STUCK_FRACTION = 0.25
#: The distance kept beyond d_min when no margin is given: this many range-noise stds (a range
#: reading long by more than 3 sigma happens about once in 700 readings, and the barrier's
#: gamma <= 1/2 leaves half of any such error to the next step).
RANGE_SIGMAS = 3.0
#: Half-angle of the cone of trusted directions, in the estimator's bearing stds. With exact
#: ranges the RLSE's bound is a hard one (one std is the largest error); with noise it is a
#: first-order figure: with 5 cm range noise (trusted estimates of pairs closer than 2.5 m, 100
#: random starts of separation_guard.yaml and of paper_tracking.yaml) the bearing error was
#: within 1.4 stds in 99 % of samples, 3.1 at most, and the margin of three range stds took the
#: rest (1000 starts of each: no pair below 1.03 m; bench/separation_bench.py). A wider cone
#: brakes more pairs, and a braked pair's estimates starve of motion: at 1.5 stds the median
#: run's tracking error over the last quarter was 1.9 m instead of 0.27 m (paper scenario).
CONE_SIGMAS = 1.0
#: A cone wider than this gives no direction (the vehicle brakes as for a blind one): the three
#: half-planes that bound a wider cone leave little of the command anyway.
MAX_CONE_RAD = np.pi / 3


def _norm(vector: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.sqrt(np.sum(vector * vector, axis=-1))


def _capped(velocity: NDArray[np.float64], cap: NDArray[np.float64]) -> NDArray[np.float64]:
    """``velocity`` ``(..., 2)`` scaled down to at most ``cap`` ``(...)`` [m/s] in norm."""
    norm = _norm(velocity)
    scale = np.where(norm > cap, cap / np.maximum(norm, 1e-12), 1.0)
    return velocity * scale[..., None]


def _known(velocity: NDArray[np.float64] | None, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """``velocity`` broadcast to ``shape`` ``(..., 2)``, unknown entries (NaN, None) as zero."""
    if velocity is None:
        return np.zeros(shape)
    velocity = np.broadcast_to(np.asarray(velocity, dtype=float), shape)
    return np.where(np.isfinite(velocity).all(axis=-1, keepdims=True), velocity, 0.0)


def allowed_closing_m_s(
    clearance_m: NDArray[np.float64],
    *,
    step_s: float,
    gain_1_s: float,
    braking_m_s2: float | None = None,
) -> NDArray[np.float64]:
    """The pair's allowed closing speed w [m/s] at ``clearance_m`` h = d - d_min (any shape):
    gamma h / T (negative, an opening speed, below d_min), and at most 2 sqrt(braking h)."""
    gamma = min(gain_1_s * step_s, 1.0)
    closing = gamma * clearance_m / step_s
    if braking_m_s2 is not None:
        closing = np.minimum(closing, 2.0 * np.sqrt(braking_m_s2 * np.maximum(clearance_m, 0.0)))
    return closing


def separation_guard(
    velocity_m_s: NDArray[np.float64],
    relative_m: NDArray[np.float64],
    distance_m: NDArray[np.float64],
    own_command_m_s: NDArray[np.float64] | None = None,
    neighbour_command_m_s: NDArray[np.float64] | None = None,
    *,
    min_separation_m: float,
    gain_1_s: float,
    step_s: float,
    margin_m: float | None = None,
    braking_m_s2: float | None = None,
    latency_s: float = 0.0,
    range_noise_std_m: float = 0.0,
    bearing_std_rad: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """The command closest to ``velocity_m_s`` that keeps the separation conditions.

    velocity_m_s: ``(..., 2)`` the law's north-east command [m/s].
    relative_m: ``(..., m, 2)`` estimated p_i - p_j for each neighbour [m] (NaN: none).
    distance_m: ``(..., m)`` measured range to each neighbour [m] (NaN: use |relative_m|).
    own_command_m_s: ``(..., 2)``, neighbour_command_m_s: ``(..., m, 2)`` the commands in force
    (set at the last step; the neighbours' from their step messages) [m/s] (NaN or None: not
    known, counted as zero).
    min_separation_m + margin_m: the distance kept [m] (the margin for range noise and estimate
    error; None: ``RANGE_SIGMAS`` range_noise_std_m). gain_1_s, step_s: gamma = min(gain T, 1).
    braking_m_s2, latency_s: see the module. range_noise_std_m: sigma_r of one range [m].
    bearing_std_rad: ``(..., m)`` how far each estimate's bearing may be off [rad]
    (:attr:`.step.StepOutputs.bearing_std_rad`; NaN: not known, no direction); None: the
    directions whose length agrees with the range are taken as exact.
    Returns ``(..., 2)``; unchanged where no condition binds.
    """
    command = np.asarray(velocity_m_s, dtype=float)
    pairs = _pairs(command, relative_m, distance_m, own_command_m_s, neighbour_command_m_s)
    if margin_m is None:
        margin_m = RANGE_SIGMAS * range_noise_std_m
    clearance = pairs.clearance_m(min_separation_m + margin_m, latency_s)
    closing = allowed_closing_m_s(
        clearance, step_s=step_s, gain_1_s=gain_1_s, braking_m_s2=braking_m_s2
    )
    bound, speed_cap, cone_rad = _conditions(pairs, closing, bearing_std_rad)
    normal = pairs.normal
    if cone_rad is not None:
        normal, bound = _cone_conditions(normal, bound, cone_rad)

    cut = np.maximum(bound - np.sum(normal * command[..., None, :], axis=-1), 0.0)
    if not (np.any(cut > 0) or np.any(_norm(command) > speed_cap)):
        return command
    if cone_rad is not None:  # the turn works on each neighbour's own line and worst cut
        m = cut.shape[-1] // 3
        normal, cut = normal[..., :m, :], np.max(np.reshape(cut, (*cut.shape[:-1], 3, m)), -2)
    wanted = _turned_right(
        command, normal, cut, clearance, pairs.theirs, min_separation_m=min_separation_m
    )
    if cone_rad is not None:  # the cone again, around the centre conditions' bounds
        normal, bound = _cone_conditions(normal, bound[..., :m], cone_rad)
    x = _project(wanted, normal, bound, speed_cap)
    return _inside(x, normal, bound, speed_cap)


class _Pairs(NamedTuple):
    """What a vehicle knows of each neighbour's line, all ``(..., m)`` but ``normal``.

    normal: ``(..., m, 2)`` n_j, the unit vector from j to this vehicle by the estimate (0 where
    the estimate gives none). usable: the estimate gives a direction. length: |estimate| [m].
    distance: the measured range, else ``length`` [m]. present: ``distance`` is known.
    own, theirs: n_j . u_i' and n_j . u_j', the commands in force along the line [m/s].
    """

    normal: NDArray[np.float64]
    usable: NDArray[np.bool_]
    length: NDArray[np.float64]
    distance: NDArray[np.float64]
    present: NDArray[np.bool_]
    own: NDArray[np.float64]
    theirs: NDArray[np.float64]

    def clearance_m(self, kept_m: float, latency_s: float) -> NDArray[np.float64]:
        """h_j: the distance beyond ``kept_m`` (inf where no distance is known), less what the
        commands in force still close in ``latency_s``, before the new ones act."""
        clearance = np.where(self.present, self.distance, np.inf) - kept_m
        if latency_s > 0:
            clearance = clearance - latency_s * np.maximum(self.theirs - self.own, 0.0)
        return clearance


def _pairs(
    command: NDArray[np.float64],
    relative_m: NDArray[np.float64],
    distance_m: NDArray[np.float64],
    own_command_m_s: NDArray[np.float64] | None,
    neighbour_command_m_s: NDArray[np.float64] | None,
) -> _Pairs:
    """Each neighbour's line from the estimates ``relative_m`` ``(..., m, 2)`` and ranges
    ``distance_m`` ``(..., m)``, and the commands in force along it (see
    :func:`separation_guard` for the arguments)."""
    length = _norm(relative_m)
    usable = np.isfinite(length) & (length > 1e-9)
    normal = np.where(usable[..., None], relative_m / np.where(usable, length, 1.0)[..., None], 0.0)
    distance = np.where(np.isfinite(distance_m), distance_m, length)
    present = np.isfinite(distance)
    own = np.sum(normal * _known(own_command_m_s, command.shape)[..., None, :], axis=-1)
    theirs = np.sum(normal * _known(neighbour_command_m_s, normal.shape), axis=-1)
    return _Pairs(normal, usable, length, distance, present, own, theirs)


def _conditions(
    pairs: _Pairs, closing: NDArray[np.float64], bearing_std_rad: NDArray[np.float64] | None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None]:
    """The conditions n_j . u >= b_j, from the pairs' allowed closing speeds w_j ``(..., m)``.

    Returns b_j ``(..., m)`` (-inf where the direction is not trusted), the speed cap
    ``(...)`` that the neighbours without a trusted direction set (inf: none), and the
    half-angle of each trusted direction's cone ``(..., m)`` [rad] (0 where not trusted; None
    without ``bearing_std_rad``: directions taken as exact).
    """
    half = 0.5 * np.where(pairs.present, closing, np.inf)
    along = pairs.own + pairs.theirs  # n . (u_i' + u_j')
    reference = np.clip(0.5 * along, -np.maximum(half, 0.0), np.maximum(half, 0.0))
    # Directions come from the estimates; one that disagrees with the measured range (an
    # estimator still converging) gives none, and the vehicle keeps below half the pair's
    # allowed closing speed whatever the direction.
    distance = pairs.distance
    trusted = (
        pairs.usable
        & pairs.present
        & (np.abs(pairs.length - distance) <= TRUST_FRACTION * distance)
    )
    cone = None
    if bearing_std_rad is not None:
        cone = CONE_SIGMAS * np.asarray(bearing_std_rad, dtype=float)
        trusted &= cone <= MAX_CONE_RAD  # NaN (unknown spread) is not
    bound = np.where(trusted, reference - half, -np.inf)
    blind = pairs.present & ~trusted
    speed_cap = np.min(np.where(blind, np.maximum(half, 0.0), np.inf), axis=-1)
    cone_rad = None if cone is None else np.where(trusted, cone, 0.0)
    return bound, speed_cap, cone_rad


def _turned_right(
    command: NDArray[np.float64],
    normal: NDArray[np.float64],
    cut: NDArray[np.float64],
    clearance: NDArray[np.float64],
    theirs: NDArray[np.float64],
    *,
    min_separation_m: float,
) -> NDArray[np.float64]:
    """``command`` ``(..., 2)`` with part of what the conditions ``cut`` ``(..., m)`` of its
    approach given back to the right of each line ``normal`` ``(..., m, 2)``, where the pair is
    stuck (near the distance kept, ``clearance`` ``(..., m)``, and the neighbour not moving
    away, ``theirs``). The vehicle heads to j along -n, whose right is (n_east, -n_north); j,
    doing the same, turns the other way, and they pass left side to left side."""
    stuck = np.clip(1.0 - clearance / (STUCK_FRACTION * min_separation_m), 0.0, 1.0)
    approach = np.minimum(cut, np.maximum(-np.sum(normal * command[..., None, :], axis=-1), 0.0))
    turn = TURN_FRACTION * approach * np.where(theirs >= 0.0, stuck, 0.0)
    right = np.stack([normal[..., 1], -normal[..., 0]], axis=-1)
    return command + np.sum(turn[..., None] * right, axis=-2)


def _cone_conditions(
    normal: NDArray[np.float64], bound: NDArray[np.float64], cone_rad: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The conditions n' . u >= b for every n' within ``cone_rad`` ``(..., m)`` of n ``(..., m,
    2)``, as three half-planes per neighbour ``(..., 3m, 2)``, ``(..., 3m)``: the cone's two edges
    with b, which suffice for b > 0 (every n' inside is a combination of the edges with weights
    summing to >= 1), and n itself with b cos(cone) for b <= 0: a command closing along a
    direction inside the cone, at angle phi from n, is then at most |b| cos(cone) / cos(phi) <=
    |b| fast. Inside the set the condition holds whichever direction of the cone is true."""
    cos, sin = np.cos(cone_rad)[..., None], np.sin(cone_rad)[..., None]
    across = np.stack([-normal[..., 1], normal[..., 0]], axis=-1)
    edges = [normal * cos + across * sin, normal * cos - across * sin]
    centre = np.where(bound <= 0.0, bound * cos[..., 0], bound)
    return np.concatenate([normal, *edges], axis=-2), np.concatenate([centre, bound, bound], -1)


def _project(
    x: NDArray[np.float64],
    normal: NDArray[np.float64],
    bound: NDArray[np.float64],
    speed_cap: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Dykstra's projection of ``x`` ``(..., 2)`` onto the half-planes {u : n_j . u >= b_j}
    ``(..., m, 2)``, ``(..., m)`` and the disc |u| <= cap ``(...)``: x moves by projections onto
    each set in turn; the corrections of each are carried so that the limit is the projection of
    ``x`` itself, not merely a point of the intersection."""
    m = normal.shape[-2]
    corrections = np.zeros((*x.shape[:-1], m + 1, 2))
    for _ in range(SWEEPS):
        for j in range(m + 1):
            y = x + corrections[..., j, :]
            if j < m:
                n_j = normal[..., j, :]
                shortfall = np.maximum(bound[..., j] - np.sum(n_j * y, axis=-1), 0.0)
                projected = y + shortfall[..., None] * n_j
            else:
                projected = _capped(y, speed_cap)
            corrections[..., j, :] = y - projected
            x = projected
    return x


def _inside(
    x: NDArray[np.float64],
    normal: NDArray[np.float64],
    bound: NDArray[np.float64],
    speed_cap: NDArray[np.float64],
) -> NDArray[np.float64]:
    """``x`` scaled towards zero until it meets every condition that zero meets (b_j <= 0): the
    few sweeps of :func:`_project` may stop short of the intersection when many bind at once.
    A condition zero does not meet (closer than the distance kept) is left to the projection."""
    along = np.sum(normal * x[..., None, :], axis=-1)
    outside = (along < bound) & (bound <= 0.0)
    scale = np.min(
        np.where(outside, bound / np.where(outside, along, -1.0), 1.0), axis=-1, initial=1.0
    )
    norm = _norm(x)
    scale = np.minimum(scale, np.where(norm > speed_cap, speed_cap / np.maximum(norm, 1e-12), 1.0))
    return x * np.clip(scale, 0.0, 1.0)[..., None]

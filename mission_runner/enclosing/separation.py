"""A separation guard between the enclosing law and the velocity setpoint (numpy only).

The paper's law has no collision avoidance: vehicles crossing the circle to their slots can pass
arbitrarily close. The guard changes a vehicle's command u_i as little as possible so that, for
every neighbour j at distance d_j with direction n_j (unit vector from j to this vehicle), the
control-barrier-function condition on h_j = d_j - d_min

    n_j . (u_i - u_j)  >=  -gain * h_j

holds: d_j closes no faster than gain * h_j, exponentially slowly towards d_min, and opens when
closer. Neither vehicle knows the other's next command, so they share the correction
reciprocally: each changes its own velocity along n_j by half of what the pair needs, from their
current velocities v_i, v_j (both measured, so both sides compute the same split):

    n_j . u_i  >=  n_j . (v_i + v_j) / 2  -  gain * h_j / 2

If both run the guard, the condition holds for the pair; a formation turning rigidly closes no
distance and is left alone. Where a velocity is unknown it counts as zero. The closest command
satisfying every condition is the projection of the law's command onto an intersection of
half-planes, found by Dykstra's alternating projections.

It sees only what a vehicle knows: the estimated relative positions (RLSE, for the directions),
the measured ranges (for the distances, falling back to the estimates' lengths) and the
neighbours' velocities from their odometry. Shapes: any leading batch dimensions ``...``, m
neighbours.
"""

import numpy as np
from numpy.typing import NDArray

#: Dykstra sweeps over the constraints; a few suffice for the handful of neighbours close at once.
SWEEPS = 12
#: An estimate whose length is off the measured range by more than this fraction is not trusted
#: for a direction (the estimator has not converged, or the neighbour moved unseen).
TRUST_FRACTION = 0.2


def _capped(velocity: NDArray[np.float64], cap: NDArray[np.float64]) -> NDArray[np.float64]:
    """``velocity`` ``(..., 2)`` scaled down to at most ``cap`` ``(...)`` [m/s] in norm."""
    norm = np.sqrt(np.sum(velocity * velocity, axis=-1))
    scale = np.where(norm > cap, cap / np.maximum(norm, 1e-12), 1.0)
    return velocity * scale[..., None]


def separation_guard(
    velocity_m_s: NDArray[np.float64],
    relative_m: NDArray[np.float64],
    distance_m: NDArray[np.float64],
    own_velocity_m_s: NDArray[np.float64] | None = None,
    neighbour_velocity_m_s: NDArray[np.float64] | None = None,
    *,
    min_separation_m: float,
    gain_1_s: float,
    horizon_s: float = 0.25,
) -> NDArray[np.float64]:
    """The command closest to ``velocity_m_s`` that keeps the separation condition.

    velocity_m_s: ``(..., 2)`` the law's north-east command [m/s].
    relative_m: ``(..., m, 2)`` estimated p_i - p_j for each neighbour [m] (NaN: none).
    distance_m: ``(..., m)`` measured range to each neighbour [m] (NaN: use |relative_m|).
    own_velocity_m_s: ``(..., 2)``, neighbour_velocity_m_s: ``(..., m, 2)`` the current
    velocities [m/s] (NaN or None: not known, counted as zero).
    horizon_s: only neighbours that could close to ``min_separation_m`` within this time at the
    pair's speeds (and any closer than twice it) constrain the command, so that a formation
    flying at its spacing is left to the law.
    Returns ``(..., 2)``; unchanged where no condition binds.
    """
    length = np.sqrt(np.sum(relative_m * relative_m, axis=-1))
    usable = np.isfinite(length) & (length > 1e-9)
    normal = np.where(usable[..., None], relative_m / np.where(usable, length, 1.0)[..., None], 0.0)
    distance = np.where(np.isfinite(distance_m), distance_m, length)
    along = np.zeros(length.shape)
    speed = np.zeros(length.shape)
    own = None if own_velocity_m_s is None else own_velocity_m_s[..., None, :]
    for velocity in (own, neighbour_velocity_m_s):
        if velocity is not None:
            known = np.isfinite(velocity).all(axis=-1)
            along = along + np.where(known, np.sum(normal * velocity, axis=-1), 0.0)
            speed = speed + np.where(known, np.sqrt(np.sum(velocity * velocity, axis=-1)), 0.0)
    command = np.asarray(velocity_m_s, dtype=float)
    speed = speed + np.sqrt(np.sum(command * command, axis=-1))[..., None]
    margin = gain_1_s * (distance - min_separation_m)
    near = distance - min_separation_m < np.maximum(min_separation_m, speed * horizon_s)
    # Directions come from the estimates; one that disagrees with the measured range (an
    # estimator still converging) gives none, and the vehicle brakes instead: its speed may not
    # exceed the closing speed the pair is allowed.
    trusted = usable & (np.abs(length - distance) <= TRUST_FRACTION * distance)
    bound = np.where(trusted & near, 0.5 * (along - margin), -np.inf)
    blind = near & ~trusted & np.isfinite(distance)
    speed_cap = np.min(np.where(blind, np.maximum(0.5 * margin, 0.0), np.inf), axis=-1)
    command = _capped(command, speed_cap)
    if not np.any(np.sum(normal * command[..., None, :], axis=-1) < bound):
        return command
    # Dykstra: x moves by projections onto each half-plane {u : n.u >= b}; the corrections of
    # each constraint are carried so that the limit is the projection of the command itself.
    x = command.copy()
    corrections = np.zeros(relative_m.shape)
    for _ in range(SWEEPS):
        for j in range(relative_m.shape[-2]):
            y = x + corrections[..., j, :]
            n_j = normal[..., j, :]
            shortfall = np.maximum(bound[..., j] - np.sum(n_j * y, axis=-1), 0.0)
            projected = y + shortfall[..., None] * n_j
            corrections[..., j, :] = y - projected
            x = projected
    return x

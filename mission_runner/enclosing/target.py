"""What the formation knows of the target's motion when it may be hidden (numpy only).

The law needs the target's velocity u_0(k) (the feed-forward every vehicle adds) and, for a
vehicle that ranges to the target, the target's cumulative displacement o_0(k) (the RLSE carries
the edge to the target forward with o_i - o_0). The paper assumes both known at every step
(Assumption 2). Here a vehicle keeps a *track* of the target:

- While somebody observes it (this vehicle's own tracker, or a neighbour's relay in its step
  message), the track takes the freshest observation: its velocity, and the step it was made at.
- While nobody does, the track predicts it with a constant-velocity model: the velocity of the
  freshest observation, integrated into o_0. A target that keeps its course is predicted exactly,
  so the edge estimates and the feed-forward stay right through an occlusion, and the range that
  comes back afterwards corrects whatever the prediction got wrong.
- After ``lost_after_s`` without an observation (or, for a target never observed, from the
  mission's start) the target is *lost*: the track stops predicting
  (u_0 = 0, o_0 frozen at the last estimate) and says so, so that no vehicle goes on following a
  target it no longer has an estimate of. An observation brings it back.

Every vehicle of a complete graph hears the same relays, so every vehicle's track holds the same
freshest observation and declares the target lost at the same step: the prediction is consistent
across the formation without any extra message.

o_0 must not jump when its source changes (a jump would shift the edge estimate with it): while a
vehicle observes the target itself at consecutive steps its own observed displacement is used,
with the offset that joins it to the track at the step it resumed; otherwise the track integrates
its velocity (forward Euler over the step, the model's p_0(k+1) = p_0(k) + T u_0(k)).

Arrays have any leading shape ``(...)``: one vehicle in flight, ``(B,)`` runs in the simulator.
"""

from dataclasses import dataclass
from typing import Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Target status codes (:attr:`TargetEstimate.status`): observed at this step (by this vehicle or
#: a neighbour), predicted from an earlier observation, lost (never seen, or not for too long).
OBSERVED, PREDICTED, LOST = 0, 1, 2
STATUS_NAMES = ("observed", "predicted", "lost")


@dataclass(frozen=True)
class TargetTrack:
    """One track per leading index, between steps.

    step: the last step the track was updated at (-1: never). velocity_m_s: ``(..., 2)`` the
    freshest observation's velocity, north-east [m/s] (NaN: never observed). observed_step:
    ``(...)`` the step it was made at (-inf: never). odometry_m: ``(..., 2)`` o_0 at ``step`` [m].
    offset_m: ``(..., 2)`` o_0 minus this vehicle's own observed displacement while it observes
    the target at consecutive steps (NaN otherwise). lost: ``(...)`` bool, lost at ``step``.
    """

    step: int
    velocity_m_s: NDArray[np.float64]
    observed_step: NDArray[np.float64]
    odometry_m: NDArray[np.float64]
    offset_m: NDArray[np.float64]
    lost: NDArray[np.bool_]

    @classmethod
    def initial(cls, shape: tuple[int, ...] = ()) -> Self:
        """Nothing observed yet; o_0 starts at 0. ``shape``: the leading shape ``(...)``."""
        return cls(
            step=-1,
            velocity_m_s=np.full((*shape, 2), np.nan),
            observed_step=np.full(shape, -np.inf),
            odometry_m=np.zeros((*shape, 2)),
            offset_m=np.full((*shape, 2), np.nan),
            lost=np.ones(shape, dtype=bool),
        )


@dataclass(frozen=True)
class TargetEstimate:
    """What the law gets at step k.

    status: ``(...)`` int, :data:`OBSERVED`, :data:`PREDICTED` or :data:`LOST`.
    velocity_m_s: ``(..., 2)`` u_0(k) [m/s]; 0 where lost (the formation orbits the last estimate)
    or never observed.
    odometry_m: ``(..., 2)`` o_0(k) [m]. age_s: ``(...)`` time since the freshest observation
    [s] (inf: never observed).
    """

    status: NDArray[np.int8]
    velocity_m_s: NDArray[np.float64]
    odometry_m: NDArray[np.float64]
    age_s: NDArray[np.float64]


def track_target(
    track: TargetTrack,
    step: int,
    *,
    velocity_m_s: ArrayLike,
    observed_step: ArrayLike,
    own_odometry_m: ArrayLike,
    step_s: float,
    lost_after_s: float,
) -> tuple[TargetTrack, TargetEstimate]:
    """Advance ``track`` to ``step`` with the freshest observation heard for it.

    velocity_m_s: ``(..., 2)`` the freshest observation's velocity [m/s] (NaN: none heard).
    observed_step: ``(...)`` the step it was made at (NaN: none; at most ``step``); one older
    than the track's is ignored. own_odometry_m: ``(..., 2)`` this vehicle's own observed
    cumulative target displacement at ``step`` [m], NaN where it did not observe the target
    itself. step_s: T [s]. lost_after_s: the longest prediction [s].
    Returns the new track and the :class:`TargetEstimate` of ``step``.
    """
    velocity = np.asarray(velocity_m_s, dtype=float)
    seen_at = np.asarray(observed_step, dtype=float)
    own = np.asarray(own_odometry_m, dtype=float)
    fresh = np.isfinite(seen_at) & (seen_at > track.observed_step) & np.isfinite(velocity).all(-1)
    new_velocity = np.where(fresh[..., None], velocity, track.velocity_m_s)
    new_seen_at = np.where(fresh, seen_at, track.observed_step)
    age_s = (step - new_seen_at) * step_s
    # A target never observed is waited for from the mission's start (k = 0) as long as one
    # that was: a first relay that is a step late must not lose it.
    unseen_s = np.where(np.isfinite(new_seen_at), age_s, step * step_s)
    lost = unseen_s > lost_after_s
    status = np.where(age_s == 0, OBSERVED, np.where(lost, LOST, PREDICTED)).astype(np.int8)

    # o_0 over the interval since the last update: the velocity the track held then, none once lost.
    elapsed_s = (step - track.step) * step_s if track.step >= 0 else 0.0
    held = track.velocity_m_s
    moving = np.where(track.lost[..., None] | np.isnan(held), 0.0, held)
    predicted = track.odometry_m + elapsed_s * moving
    observing = np.isfinite(own).all(-1)
    continuing = observing & np.isfinite(track.offset_m).all(-1) & (step - track.step == 1)
    odometry = np.where(continuing[..., None], own + track.offset_m, predicted)
    offset = np.where(observing[..., None], odometry - own, np.nan)

    new_track = TargetTrack(
        step=step,
        velocity_m_s=new_velocity,
        observed_step=new_seen_at,
        odometry_m=odometry,
        offset_m=offset,
        lost=lost,
    )
    estimate = TargetEstimate(
        status=status,
        velocity_m_s=np.where(lost[..., None] | np.isnan(new_velocity), 0.0, new_velocity),
        odometry_m=odometry,
        age_s=age_s,
    )
    return new_track, estimate

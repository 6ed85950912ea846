"""A tiny kinematic loop for algorithm tests: true positions, exact ranges and odometry."""

from dataclasses import dataclass, field

import numpy as np

from mission_runner.enclosing import EnclosingParams

PAPER = EnclosingParams(
    step_s=0.125,
    beta=7.0,
    saturation_m_s=0.4,
    forgetting_factor=0.7,
    coupling_gain=1.0,
    coupling_gain_last=-1.0,
    radius_m=4.0,
    initial_gain=1.0,
    estimator="rlse",
    filter=None,
    shared_ranges=False,
    bound_range_noise_std_m=None,
)


@dataclass
class World:
    """N vehicles at ``positions`` ``(N, 2)`` and a target moving at ``target_velocity``."""

    positions: np.ndarray
    target_velocity: np.ndarray = field(default_factory=lambda: np.array([0.8, 0.0]))
    senses: np.ndarray | None = None
    step_s: float = 0.125
    k: int = 0

    def __post_init__(self):
        self.origin = self.positions.copy()
        if self.senses is None:
            self.senses = np.arange(len(self.positions)) == 0

    def target(self, k=None):
        return self.target_velocity * self.step_s * (self.k if k is None else k)

    def everyone(self):
        return np.vstack([self.target(), self.positions])

    def ranges(self):
        """``(N, N+1)``; NaN on the diagonal and to the target for non-sensing vehicles."""
        gaps = self.positions[:, None, :] - self.everyone()[None, :, :]
        ranges = np.linalg.norm(gaps, axis=-1)
        ranges[np.arange(len(ranges)), np.arange(len(ranges)) + 1] = np.nan
        ranges[~self.senses, 0] = np.nan
        return ranges

    def odometry(self):
        """``(N+1, 2)``: slot 0 the target's displacement since k = 0, then each vehicle's."""
        return np.vstack([self.target() - self.target(0), self.positions - self.origin])

    def truth(self):
        """``(N, N+1, 2)`` true p_i - p_j."""
        return self.positions[:, None, :] - self.everyone()[None, :, :]

    def advance(self, velocity):
        self.positions = self.positions + self.step_s * velocity
        self.k += 1


def initial_positions():
    return np.array([[-3.0, -2.0], [2.0, -4.0], [3.0, 3.0], [-2.0, 4.0]])

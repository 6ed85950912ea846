"""Each vehicle's own odometry, the source of LOCAL_POSITION_NED.

A flow-based estimator knows only displacement since it started: its origin is where the
vehicle was switched on, not a shared frame, and its error grows (drift) besides the white noise
of every sample. A controller that uses LOCAL_POSITION_NED can therefore only rely on
displacements, never on comparing two vehicles' absolute local positions.

Shapes: ``origin_ned_m`` and ``drift_ned_m`` are (n, 3) in the world NED frame (metres). The
frame of the odometry is aligned with north/east/down (PX4's EKF local frame is NED).
"""

from __future__ import annotations

import math
import random

import numpy as np
import numpy.typing as npt


class Odometry:
    """Flow odometry of ``n`` vehicles: drift evolves in :meth:`step`, noise per sample."""

    def __init__(
        self,
        origin_ned_m: npt.ArrayLike,
        *,
        position_noise_std_m: float = 0.0,
        velocity_noise_std_m_s: float = 0.0,
        drift_bias_std_m_s: float = 0.0,
        drift_random_walk_m_s_per_sqrt_s: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.origin_ned_m = np.array(origin_ned_m, dtype=float)
        n = self.origin_ned_m.shape[0]
        self.n = n
        self.position_noise_std_m = float(position_noise_std_m)
        self.velocity_noise_std_m_s = float(velocity_noise_std_m_s)
        self.drift_random_walk = float(drift_random_walk_m_s_per_sqrt_s)
        self._rng = np.random.default_rng([seed, 0x0D0])
        self.drift_ned_m = np.zeros((n, 3))
        self.drift_velocity_ned_m_s = np.zeros((n, 3))
        if drift_bias_std_m_s > 0:
            self.drift_velocity_ned_m_s[:, :2] = self._rng.normal(
                0.0, drift_bias_std_m_s, size=(n, 2)
            )
        self._drifting = drift_bias_std_m_s > 0 or self.drift_random_walk > 0
        # One generator per vehicle so a vehicle's noise does not depend on how many messages
        # the others send.
        self._noise = [random.Random(seed * 100003 + i) for i in range(n)]

    def step(self, dt: float) -> None:
        if not self._drifting:
            return
        if self.drift_random_walk > 0:
            self.drift_velocity_ned_m_s[:, :2] += self._rng.normal(
                0.0, self.drift_random_walk * math.sqrt(dt), size=(self.n, 2)
            )
        self.drift_ned_m += self.drift_velocity_ned_m_s * dt

    def sample(
        self,
        index: int,
        true_position_ned_m: list[float],
        true_velocity_ned_m_s: list[float],
        drift_ned_m: list[float],
    ) -> tuple[float, float, float, float, float, float]:
        """One LOCAL_POSITION_NED sample (x, y, z, vx, vy, vz) of vehicle ``index``.

        ``drift_ned_m`` is the vehicle's row of :attr:`drift_ned_m` (as a list, from the
        emulator's per-step snapshot); the origin is subtracted here.
        """
        origin = self.origin_ned_m[index]
        gauss = self._noise[index].gauss
        sp = self.position_noise_std_m
        sv = self.velocity_noise_std_m_s
        x = true_position_ned_m[0] - origin[0] + drift_ned_m[0]
        y = true_position_ned_m[1] - origin[1] + drift_ned_m[1]
        z = true_position_ned_m[2] - origin[2] + drift_ned_m[2]
        vx, vy, vz = true_velocity_ned_m_s
        if sp > 0:
            x += gauss(0.0, sp)
            y += gauss(0.0, sp)
            z += gauss(0.0, sp)
        if sv > 0:
            vx += gauss(0.0, sv)
            vy += gauss(0.0, sv)
            vz += gauss(0.0, sv)
        return float(x), float(y), float(z), float(vx), float(vy), float(vz)

    def to_world(self, index: int, local_ned_m: tuple[float, float, float]) -> list[float]:
        """World position the vehicle flies to when told to go to ``local_ned_m`` in its own
        odometry frame: the controller closes the loop on its estimate, so drift shifts it."""
        origin = self.origin_ned_m[index]
        drift = self.drift_ned_m[index]
        return [float(local_ned_m[k] + origin[k] - drift[k]) for k in range(3)]

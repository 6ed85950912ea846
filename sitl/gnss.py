"""Error of the position each vehicle reports as its own (GPS through PX4's EKF).

Real PX4 SITL (SIH) reports positions that wander around the truth by tens of centimetres, slowly:
its simulated GPS has a random-walk-like error that the EKF smooths. Two vehicles' reported
positions therefore disagree by a slowly varying amount, which is what hurts anything built on
differences of GPS positions (synthesised ranges, relative positions). The model here is, per
vehicle and per axis (north, east, down), a first-order Gauss-Markov bias plus white noise:

    b(t + dt) = phi * b(t) + bias_std * sqrt(1 - phi^2) * w,   phi = exp(-dt / tau)
    error(t)  = b(t) + noise_std * v

with w, v independent standard normal draws. The discretisation is exact for any dt, and the bias
starts from its stationary distribution, so its statistics do not depend on the physics rate or on
how long the emulator has run. Shapes: ``bias_ned_m`` and ``error_ned_m`` are (n, 3), metres, world
NED. :meth:`GnssError.step` is synchronous and vectorised over vehicles; the emulator calls it once
per physics step.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt


class GnssError:
    """Position error of ``n`` vehicles; ``error_ned_m`` is what to add to the truth."""

    def __init__(
        self,
        n: int,
        *,
        bias_std_m: float = 0.0,
        bias_time_constant_s: float = 30.0,
        noise_std_m: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> None:
        if not bias_time_constant_s > 0:
            raise ValueError(f"bias_time_constant_s must be > 0, got {bias_time_constant_s!r}")
        if bias_std_m < 0 or noise_std_m < 0:
            raise ValueError("standard deviations must be >= 0")
        self.n = n
        self.bias_std_m = float(bias_std_m)
        self.bias_time_constant_s = float(bias_time_constant_s)
        self.noise_std_m = float(noise_std_m)
        self._rng = rng if rng is not None else np.random.default_rng(0)
        self.bias_ned_m: npt.NDArray[np.float64] = np.zeros((n, 3))
        if self.bias_std_m > 0:
            self.bias_ned_m[:] = self._rng.normal(0.0, self.bias_std_m, size=(n, 3))
        self.error_ned_m: npt.NDArray[np.float64] = self.bias_ned_m.copy()
        self._cached_dt = math.nan
        self._phi = 1.0
        self._innovation_std_m = 0.0

    @property
    def active(self) -> bool:
        return self.bias_std_m > 0 or self.noise_std_m > 0

    def step(self, dt: float) -> None:
        """Advance the bias by ``dt`` seconds and draw this step's white noise."""
        if not self.active:
            return
        if dt != self._cached_dt:
            self._cached_dt = dt
            self._phi = math.exp(-dt / self.bias_time_constant_s)
            self._innovation_std_m = self.bias_std_m * math.sqrt(1.0 - self._phi * self._phi)
        rng = self._rng
        size = (self.n, 3)
        if self.bias_std_m > 0:
            self.bias_ned_m *= self._phi
            self.bias_ned_m += rng.normal(0.0, self._innovation_std_m, size=size)
        if self.noise_std_m > 0:
            noise = rng.normal(0.0, self.noise_std_m, size=size)
            np.add(self.bias_ned_m, noise, out=self.error_ned_m)
        else:
            self.error_ned_m[:] = self.bias_ned_m

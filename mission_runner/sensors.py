"""The sensor models: true positions in, what a UWB radio, a target tracker and an odometry
source would report out (numpy only).

One model for every place that synthesises measurements: the numeric simulator
(:mod:`.sim.simulator`, batched), the emulated world (:mod:`.world`) and the range aid for real
autopilots (:mod:`.runner.ranges`) all call these functions with the scenario's ``sensors:``
settings, so a noise, dropout or range limit means the same everywhere.

Ranges between vehicles come from :class:`UwbRanging`, which ranges as UWB radios do: a two-way
exchange gives one number, which with ``one_exchange_per_pair`` both ends read at the same
instant; with ``one_exchange_per_direction`` each end has its own timestamp noise, dropout and
clock error, while what belongs to the pair (the antenna-delay bias, the multipath, an NLOS
burst) is common to both directions. Those pair errors last from step to step, so the model
keeps them; a channel of limited airtime ranges the pairs in turn (:func:`range_schedule`).
The target's range comes from a tracker, not a radio: :func:`range_readings`, independent draws.

``rng`` is a numpy ``Generator`` or anything with its ``normal(scale=, size=)`` and
``uniform(size=)`` (the simulator's batch streams).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from .config import SensorConfig


class Rng(Protocol):
    """What the models draw from: a numpy ``Generator``, or the simulator's batch streams (called
    with keywords only)."""

    def normal(self, *, scale: float, size: Any) -> Any: ...

    def uniform(self, *, low: float = ..., high: float = ..., size: Any) -> Any: ...


def measure_ranges(
    from_m: ArrayLike,
    sensors: SensorConfig,
    rng: Rng,
    *,
    to_m: ArrayLike | None = None,
    measured: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """Ranges from every point of ``from_m`` to every point of ``to_m``, through
    :func:`range_readings`.

    from_m: ``(..., n, d)`` true positions [m] (NaN rows: not measured this time).
    to_m: ``(..., m, d)``; default ``from_m`` (then a point is never ranged to itself).
    measured: ``(..., n, m)`` bool, the pairs that are ranged at all (default: every pair).
    Returns ``(..., n, m)`` ranges [m], NaN where nothing is measured.
    """
    points = np.asarray(from_m, dtype=float)
    others = points if to_m is None else np.asarray(to_m, dtype=float)
    gaps = points[..., :, None, :] - others[..., None, :, :]
    distances = np.sqrt(np.sum(gaps * gaps, axis=-1))
    if others is points:
        not_self = ~np.eye(distances.shape[-1], dtype=bool)
        measured = not_self if measured is None else measured & not_self
    return range_readings(distances, sensors, rng, measured=measured)


def range_readings(
    true_m: NDArray[np.float64],
    sensors: SensorConfig,
    rng: Rng,
    *,
    measured: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """What a UWB radio reads for true distances ``true_m`` (any shape, NaN: no line): Gaussian
    noise (``range_noise_std_m``, reported as its absolute value), random dropouts
    (``range_dropout_probability``), NLOS outliers (``range_outlier_probability``: longer by a
    bias uniform in ``range_outlier_bias_m``) and a maximum range (``range_max_m``); NaN where
    nothing is read, or where ``measured`` (same shape, bool) is False. Noise, dropout and
    outliers are drawn for every entry, read or not, so that one pair's fate does not shift
    another's draws.
    """
    kept = np.isfinite(true_m)
    if measured is not None:
        kept &= measured
    readings = true_m
    if sensors.range_noise_std_m > 0:
        readings = readings + rng.normal(scale=sensors.range_noise_std_m, size=true_m.shape)
    if sensors.range_dropout_probability > 0:
        kept &= rng.uniform(size=true_m.shape) >= sensors.range_dropout_probability
    if sensors.range_outlier_probability > 0:
        outlier = rng.uniform(size=true_m.shape) < sensors.range_outlier_probability
        low, high = sensors.range_outlier_bias_m
        bias = rng.uniform(low=low, high=high, size=true_m.shape)
        readings = readings + np.where(outlier, bias, 0.0)
    if sensors.range_max_m is not None:
        kept &= readings <= sensors.range_max_m
    return np.where(kept, np.abs(readings), np.nan)


def target_seen(
    distance_m: NDArray[np.float64],
    sensors: SensorConfig,
    rng: Rng,
    *,
    looking: NDArray[np.bool_],
) -> NDArray[np.bool_]:
    """Which trackers see the target: those ``looking`` (``(..., n)`` bool: a tracker that is
    there, works and is not occluded) whose horizontal distance ``distance_m`` ``(..., n)`` [m]
    is within ``target_sensing_range_m``, less random misses (``target_dropout_probability``,
    drawn for every entry, only when set, so that scenarios without it draw as before)."""
    seen = looking & np.isfinite(distance_m)
    if sensors.target_sensing_range_m is not None:
        seen &= distance_m <= sensors.target_sensing_range_m
    if sensors.target_dropout_probability > 0:
        seen &= rng.uniform(size=distance_m.shape) >= sensors.target_dropout_probability
    return seen


def odometry_drift(sensors: SensorConfig, rng: Rng, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """A constant drift velocity [m/s] per vehicle, ``shape + (2,)``: ``displacement_drift_m_s``
    in a random direction (zeros without drift)."""
    if sensors.displacement_drift_m_s <= 0:
        return np.zeros((*shape, 2))
    angle = rng.uniform(low=0, high=2 * np.pi, size=shape)
    return sensors.displacement_drift_m_s * np.stack([np.cos(angle), np.sin(angle)], -1)


def odometry_error_step(
    sensors: SensorConfig, rng: Rng, error_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The odometry error after one more step: a random walk of ``displacement_noise_std_m`` per
    step. error_m: ``(..., 2)`` [m], returned unchanged without noise."""
    if sensors.displacement_noise_std_m <= 0:
        return error_m
    return error_m + rng.normal(scale=sensors.displacement_noise_std_m, size=error_m.shape)


#: The speed of light [m/s]: a clock error in a two-way exchange reaches the range through it.
SPEED_OF_LIGHT_M_S = 299_792_458.0
RANGE_SCHEMES = ("one_exchange_per_pair", "one_exchange_per_direction")


def exchanges_per_step(sensors: SensorConfig, step_s: float) -> int | None:
    """How many ranging exchanges the channel carries in one step (None: no airtime limit)."""
    if sensors.range_exchange_s is None:
        return None
    # The tolerance keeps 0.1 / 0.001 at 100, not 99.
    return math.floor(step_s / sensors.range_exchange_s + 1e-9)


def range_slots(
    n: int, sensors: SensorConfig, graph: NDArray[np.bool_] | None = None
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The exchanges a full round of ranging takes, in the order the channel serves them:
    ``(initiators, responders)``, the pairs i < j with ``one_exchange_per_pair``, both
    directions of each pair in turn with ``one_exchange_per_direction``. ``graph`` ``(n, n)``
    bool: only its edges are ranged (the neighbourhood graph); None: every pair."""
    if graph is None:
        rows, cols = np.triu_indices(n, 1)
    else:
        rows, cols = np.nonzero(np.triu(graph, 1))  # the same row-major order
    if sensors.range_scheme == "one_exchange_per_pair":
        return rows, cols
    return np.stack([rows, cols], -1).ravel(), np.stack([cols, rows], -1).ravel()


def range_schedule(
    n: int, sensors: SensorConfig, step_s: float, k: int, graph: NDArray[np.bool_] | None = None
) -> NDArray[np.bool_]:
    """Which ranges (row i reads column j) the channel carries at step ``k``, ``(n, n)`` bool:
    every pair without ``range_exchange_s``; else a TDMA round: the step's
    :func:`exchanges_per_step` exchanges go to the next :func:`range_slots` after those of step
    k - 1, so that with many vehicles a pair is ranged every few steps. The schedule is fixed
    by the scenario's vehicles (a lost vehicle's slots stay unused, as a static TDMA frame's)
    and ``graph`` (only its edges, see :func:`range_slots`)."""
    everyone = ~np.eye(n, dtype=bool) if graph is None else graph
    capacity = exchanges_per_step(sensors, step_s)
    if capacity is None:
        return everyone
    initiators, responders = range_slots(n, sensors, graph)
    if capacity >= len(initiators):
        return everyone
    served = (k * capacity + np.arange(capacity)) % len(initiators)
    carried = np.zeros((n, n), dtype=bool)
    carried[initiators[served], responders[served]] = True
    if sensors.range_scheme == "one_exchange_per_pair":
        carried |= carried.T
    return carried


def ranging_plan(
    n: int, sensors: SensorConfig, step_s: float, graph: NDArray[np.bool_] | None = None
) -> str:
    """One line saying which ranges a step of ``n`` vehicles has under ``sensors``' scheme and
    airtime (:func:`range_schedule`), over the edges of ``graph`` (None: every pair)."""
    scheme = sensors.range_scheme.replace("_", " ")
    slots = len(range_slots(n, sensors, graph)[0])
    capacity = exchanges_per_step(sensors, step_s)
    if capacity is None or capacity >= slots:
        pairs = "every pair" if graph is None else "every graph edge"
        return f"ranging: {scheme}, {slots} exchanges a round, {pairs} every step"
    every = math.ceil(slots / capacity)
    return (
        f"ranging: {scheme}, {slots} exchanges a round, {capacity} a step "
        f"(sensors.range_exchange_s {sensors.range_exchange_s:g} s): each pair every "
        f"{slots / capacity:.3g} steps on average, at most {every} ({every * step_s:.3g} s)"
    )


def _pairwise(values: NDArray[Any]) -> NDArray[Any]:
    """``values`` ``(..., n, n)`` made symmetric from its upper triangle (diagonal zero): one
    draw per pair, whoever reads it."""
    upper = np.triu(values, 1)
    return upper + np.swapaxes(upper, -1, -2)


class UwbRanging:
    """The UWB radios of ``n`` vehicles (for every entry of a ``batch`` of runs): the ranges
    each reads at each step, with the errors that last kept from step to step.

    A range is the true distance plus: the exchange's timestamp noise
    (``range_noise_std_m``); the pair's bias (``range_bias_std_m``, constant); its multipath
    (``range_multipath_std_m``, a Gauss-Markov process of correlation time
    ``range_multipath_correlation_s``); an NLOS burst's bias (``range_outlier_probability`` of
    the time, bursts of mean ``range_nlos_duration_s``, each reading long by one bias drawn
    from ``range_outlier_bias_m``); single-sided TWR's clock error
    (``range_clock_offset_std_ppm``). Dropouts (``range_dropout_probability``) lose an exchange,
    ``range_max_m`` bounds the reading, ``range_exchange_s`` the exchanges per step.

    Everything is drawn for every pair whether it is ranged or not, and only what is switched
    on, so that one pair's fate does not move another's draws and a noise-free model draws
    nothing. Call :meth:`read` with increasing steps; a step skipped still ages the errors.
    """

    def __init__(
        self,
        sensors: SensorConfig,
        n: int,
        step_s: float,
        batch: tuple[int, ...] = (),
        graph: NDArray[np.bool_] | None = None,
    ) -> None:
        self.sensors = sensors
        self.n = n
        self.graph = graph  # the pairs the schedule serves (:func:`range_slots`); None: all
        self.step_s = step_s
        self.shape = (*batch, n, n)
        # Read-only zeros until a configured error draws its own (never written in place): a
        # noise-free model of 1000 vehicles holds no 8 MB planes.
        zero, no = np.broadcast_to(0.0, self.shape), np.broadcast_to(False, self.shape)
        self.bias_m, self.multipath_m, self.clock_m = zero, zero, zero
        self.nlos, self.nlos_bias_m = no, zero
        self._step: int | None = None

    @property
    def per_pair(self) -> bool:
        return self.sensors.range_scheme == "one_exchange_per_pair"

    def read(
        self,
        true_m: NDArray[np.float64],
        rng: Rng,
        *,
        k: int,
        measured: NDArray[np.bool_] | None = None,
    ) -> NDArray[np.float64]:
        """Step ``k``'s ranges for true distances ``true_m`` ``(*batch, n, n)`` [m] (NaN: no
        line), NaN where nothing is read: on the diagonal, where ``measured`` (same shape,
        bool) is False (with ``one_exchange_per_pair`` at either end: the exchange serves
        both or neither), off the step's :func:`range_schedule`, dropped or out of range."""
        if self._step is None:
            self._start(rng)
        elif k < self._step:
            raise ValueError(f"UWB ranging went back from step {self._step} to {k}")
        else:
            for _ in range(k - self._step):
                self._age(rng)
        self._step = k
        sensors = self.sensors
        kept = np.isfinite(true_m) & range_schedule(self.n, sensors, self.step_s, k, self.graph)
        if measured is not None:
            kept &= measured & np.swapaxes(measured, -1, -2) if self.per_pair else measured
        readings = true_m
        # Error terms that are all zero (not configured) are skipped: adding 0 changes nothing
        # (the readings are distances, so not -0), and each is a pass over n^2 ranges.
        for error_m in (self.bias_m, self.multipath_m, self.clock_m):
            if error_m.any():
                readings = readings + error_m
        if self.nlos.any():
            readings = readings + np.where(self.nlos, self.nlos_bias_m, 0.0)
        if sensors.range_noise_std_m > 0:
            readings = readings + self._exchanged(
                rng.normal(scale=sensors.range_noise_std_m, size=self.shape)
            )
        if sensors.range_dropout_probability > 0:
            lost = rng.uniform(size=self.shape) < sensors.range_dropout_probability
            kept &= ~self._exchanged(lost)
        if sensors.range_max_m is not None:
            kept &= readings <= sensors.range_max_m
        readings = np.abs(readings)  # a new array: true_m is the caller's
        np.copyto(readings, np.nan, where=~kept)  # in place: n^2 ranges
        return readings

    @property
    def draws(self) -> bool:
        """Whether the model draws anything (noise, dropouts, pair errors): then every pair is
        drawn at every step, as :meth:`read` does."""
        sensors = self.sensors
        return any(
            value > 0
            for value in (
                sensors.range_noise_std_m,
                sensors.range_dropout_probability,
                sensors.range_bias_std_m,
                sensors.range_multipath_std_m,
                sensors.range_outlier_probability,
                sensors.range_clock_offset_std_ppm,
            )
        )

    def read_edges(
        self,
        true_m: NDArray[np.float64],
        rng: Rng,
        k: int,
        edges: tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]],
        measured: NDArray[np.bool_],
    ) -> NDArray[np.float64]:
        """:meth:`read` of the pairs ``edges`` = ``(rows, cols, reverse)`` ``(E,)`` only (i reads
        j; ``reverse``: the index of the edge j -> i, -1 if none), for true distances
        ``true_m`` and ``measured`` ``(*batch, E)``; returns ``(*batch, E)``, the readings
        :meth:`read` gives there. O(E) for a model that draws nothing; one that draws reads
        every pair (the same draws as :meth:`read`) and picks the edges."""
        rows, cols, reverse = edges
        if self.draws:
            dense = np.full(self.shape, np.nan)
            dense[..., rows, cols] = true_m
            asked = np.zeros(self.shape, dtype=bool)
            asked[..., rows, cols] = measured
            return self.read(dense, rng, k=k, measured=asked)[..., rows, cols]
        if self._step is not None and k < self._step:
            raise ValueError(f"UWB ranging went back from step {self._step} to {k}")
        self._step = k
        schedule = range_schedule(self.n, self.sensors, self.step_s, k, self.graph)
        kept = np.isfinite(true_m) & schedule[rows, cols] & measured
        if self.per_pair:  # the exchange serves both ends or neither
            kept &= np.where(reverse >= 0, measured[..., reverse], False)
        if self.sensors.range_max_m is not None:
            kept &= true_m <= self.sensors.range_max_m
        return np.where(kept, np.abs(true_m), np.nan)

    def _exchanged(self, values: NDArray[Any]) -> NDArray[Any]:
        """What each exchange draws: one per pair, or one per direction."""
        return _pairwise(values) if self.per_pair else values

    def _start(self, rng: Rng) -> None:
        """The pair errors at the first step, drawn from their stationary distributions."""
        sensors, shape = self.sensors, self.shape
        if sensors.range_bias_std_m > 0:
            self.bias_m = _pairwise(rng.normal(scale=sensors.range_bias_std_m, size=shape))
        if sensors.range_multipath_std_m > 0:
            self.multipath_m = _pairwise(
                rng.normal(scale=sensors.range_multipath_std_m, size=shape)
            )
        if sensors.range_outlier_probability > 0:
            self.nlos = _pairwise(rng.uniform(size=shape)) < sensors.range_outlier_probability
            self.nlos &= ~np.eye(self.n, dtype=bool)
            self.nlos_bias_m = self._nlos_biases(rng)
        if sensors.range_clock_offset_std_ppm > 0:
            offset = rng.normal(scale=sensors.range_clock_offset_std_ppm * 1e-6, size=shape[:-1])
            # Single-sided TWR reads 1/2 c t_reply (e_initiator - e_responder) off (APS011);
            # in one exchange per pair the lower index initiates.
            error = 0.5 * SPEED_OF_LIGHT_M_S * sensors.range_reply_time_s
            error_m = error * (offset[..., :, None] - offset[..., None, :])
            self.clock_m = _pairwise(error_m) if self.per_pair else error_m

    def _age(self, rng: Rng) -> None:
        """The pair errors one step later: the multipath decays towards a fresh draw, NLOS
        bursts start and end (a Markov chain in the stationary fraction of the time)."""
        sensors, shape = self.sensors, self.shape
        if sensors.range_multipath_std_m > 0:
            kept = math.exp(-self.step_s / sensors.range_multipath_correlation_s)
            fresh = rng.normal(
                scale=sensors.range_multipath_std_m * math.sqrt(1.0 - kept * kept), size=shape
            )
            self.multipath_m = kept * self.multipath_m + _pairwise(fresh)
        probability = sensors.range_outlier_probability
        if probability > 0:
            chance = _pairwise(rng.uniform(size=shape))
            fresh_bias = self._nlos_biases(rng)
            not_self = ~np.eye(self.n, dtype=bool)
            if sensors.range_nlos_duration_s == 0:  # independent outliers, each its own bias
                self.nlos = (chance < probability) & not_self
                self.nlos_bias_m = fresh_bias
                return
            leave = min(1.0, self.step_s / sensors.range_nlos_duration_s)
            enter = min(1.0, leave * probability / (1.0 - probability))
            starting = ~self.nlos & (chance < enter) & not_self
            ending = self.nlos & (chance < leave)
            self.nlos = (self.nlos & ~ending) | starting
            self.nlos_bias_m = np.where(starting, fresh_bias, self.nlos_bias_m)

    def _nlos_biases(self, rng: Rng) -> NDArray[np.float64]:
        low, high = self.sensors.range_outlier_bias_m
        return _pairwise(np.asarray(rng.uniform(low=low, high=high, size=self.shape)))

"""Coupled-oscillator pattern generator, the paper's eq. ``osc``.

theta_i(k+1) = theta_i(k) + T omega_i
               + T sum_j a_ij sum_{l=1..n} (K_l / l) sin(l (theta_i - theta_j))

With K_l > 0 for l < n and K_n < 0 small, the splay state (phases 2 pi / n apart) is a stable
equilibrium (Lemma 1). ``n`` is the number of live vehicles, so the harmonic gains change when a
vehicle is lost or joins and the rest re-balance.

The double sum is evaluated as one matrix product,
``sum_j a_ij sin(l (theta_i - theta_j))
= sin(l theta_i) (A cos(l theta))_i - cos(l theta_i) (A sin(l theta))_i``,
which runs in BLAS instead of a Python triple loop and works unchanged for one vehicle (one row)
and for a whole swarm or a batch of swarms (leading axes).
"""

import numpy as np
from numpy.typing import ArrayLike, NDArray


def harmonic_gains(
    n_live: ArrayLike, n_harmonics: int, gain: float, gain_last: float
) -> NDArray[np.float64]:
    """Gains K_1..K_L for ``n_live`` vehicles: ``gain`` for l < n, ``gain_last`` for l = n, 0 above.

    n_live: int array ``(...)``; returns ``(..., n_harmonics)``. A swarm of one has no coupling.
    """
    n_live = np.asarray(n_live)[..., None]
    order = np.arange(1, n_harmonics + 1)
    gains = np.where(order < n_live, gain, 0.0)
    return np.where((order == n_live) & (n_live > 1), gain_last, gains)


def coupling_rate(
    phase_rows: NDArray[np.float64],
    phase_slots: NDArray[np.float64],
    weights: NDArray[np.float64],
    gains: NDArray[np.float64],
) -> NDArray[np.float64]:
    """The coupling term sum_j a_ij sum_l (K_l / l) sin(l (theta_i - theta_j)), in rad/s per unit T.

    phase_rows: ``(..., R)`` phases of the computing vehicles [rad].
    phase_slots: ``(..., S)`` phases of every slot [rad]; entries with zero weight may be NaN.
    weights: ``(..., R, S)`` a_ij, zero where j is not a neighbour of row i this step.
    gains: ``(..., R, L)`` K_l for l = 1..L (see :func:`harmonic_gains`).
    Returns ``(..., R)``.
    """
    n_harmonics = gains.shape[-1]
    order = np.arange(1, n_harmonics + 1)
    slots = np.where(weights.any(axis=-2), phase_slots, 0.0)[..., :, None] * order  # (..., S, L)
    basis = np.concatenate([np.cos(slots), np.sin(slots)], axis=-1)  # (..., S, 2L)
    mixed = weights @ basis  # (..., R, 2L)
    rows = phase_rows[..., :, None] * order  # (..., R, L)
    terms = np.sin(rows) * mixed[..., :n_harmonics] - np.cos(rows) * mixed[..., n_harmonics:]
    return np.sum((gains / order) * terms, axis=-1)


def advance_phase(
    phase_rows: NDArray[np.float64],
    omega_rad_s: NDArray[np.float64],
    coupling: NDArray[np.float64],
    step_s: float,
) -> NDArray[np.float64]:
    """theta(k+1) from theta(k), the natural frequency and the coupling. Shapes ``(..., R)``."""
    return phase_rows + step_s * (omega_rad_s + coupling)


def splay_spacing_error(phases: ArrayLike, live: ArrayLike) -> NDArray[np.float64]:
    """Largest deviation of neighbouring phase gaps from 2 pi / n among live vehicles [rad].

    phases: ``(..., N)`` [rad]; live: ``(..., N)`` bool. Returns ``(...)``; 0 in the splay state,
    NaN when fewer than two vehicles are live.
    """
    phases = np.asarray(phases, dtype=float)
    live = np.asarray(live, dtype=bool)
    wrapped = np.where(live, np.mod(phases, 2 * np.pi), np.inf)
    ordered = np.sort(wrapped, axis=-1)
    n_live = live.sum(axis=-1)
    first = ordered[..., :1]
    # Close the circle: the gap after the last live phase wraps round to the first one.
    last_index = np.maximum(n_live - 1, 0)[..., None]
    last = np.take_along_axis(ordered, last_index, axis=-1)
    with np.errstate(invalid="ignore"):  # inf - inf between absent vehicles, masked below
        gaps = np.diff(ordered, axis=-1)
        gaps = np.concatenate([gaps, first + 2 * np.pi - last], axis=-1)
    index = np.arange(gaps.shape[-1])
    counted = (index < n_live[..., None] - 1) | (index == gaps.shape[-1] - 1)
    ideal = 2 * np.pi / np.maximum(n_live, 1)[..., None]
    error = np.where(counted, np.abs(gaps - ideal), 0.0)
    error = np.where(np.isfinite(error), error, 0.0).max(axis=-1)
    return np.where(n_live >= 2, error, np.nan)

"""Coupled-oscillator pattern generator, the paper's eq. ``osc``.

theta_i(k+1) = theta_i(k) + T omega_i
               + T sum_j a_ij sum_{l=1..n} (K_l / l) sin(l (theta_i - theta_j))

With K_l > 0 for l < n and K_n < 0 small, the splay state (phases 2 pi / n apart) is a stable
equilibrium (Lemma 1). ``n`` is the number of live vehicles, so the harmonic gains change when a
vehicle is lost or joins and the rest re-balance.

The double sum is evaluated through
``sum_j a_ij sin(l (theta_i - theta_j))
= sin(l theta_i) (A cos(l theta))_i - cos(l theta_i) (A sin(l theta))_i``,
with A's rows the neighbours heard (a matrix product for a few vehicles; for many, sums over
every heard vehicle, see :data:`PRODUCT_MAX_SLOTS`), instead of a Python triple loop; it works
unchanged for one vehicle (one row) and for a whole swarm or a batch of swarms (leading axes).
"""

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .control import row_normalised


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
    phase_slots: NDArray[np.float64],
    row_slots: NDArray[np.intp],
    heard: NDArray[np.bool_],
    gains: NDArray[np.float64],
    *,
    neighbours: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """The coupling term sum_j a_ij sum_l (K_l / l) sin(l (theta_i - theta_j)), in rad/s per unit T,
    with every heard vehicle but itself a neighbour of each row: a_ij = 1 / |N_i| over
    N_i = heard minus i (and, with ``neighbours`` ``(..., R, S)`` bool, within the row's graph
    neighbours).

    phase_slots: ``(..., S)`` phases of every slot [rad], the rows' own included; NaN where not
    heard. row_slots: ``(R,)`` the rows' slots. heard: ``(..., S)`` bool, the slots heard this
    step (finite phases). gains: ``(..., L)`` K_l for l = 1..L, the same for every row (see
    :func:`harmonic_gains`). Returns ``(..., R)``.
    """
    # Unheard phases (NaN) have zero weight; 0 keeps them from poisoning the sums.
    phase_slots = np.where(np.isfinite(phase_slots), phase_slots, 0.0)
    if phase_slots.shape[-1] <= PRODUCT_MAX_SLOTS:
        return _product_coupling(phase_slots, row_slots, heard, gains, neighbours=neighbours)
    if neighbours is not None:
        return _edge_coupling(phase_slots, row_slots, heard[..., None, :] & neighbours, gains)
    return _summed_coupling(phase_slots, row_slots, heard, gains)


#: Up to this many slots the neighbour sums are one matrix product with the weights, O(R S L),
#: of np.cos and np.sin of every l theta; above, sums over every heard slot, O(S L) for any
#: number of rows, of the harmonics as phasors e^{i l theta} by doubling (:func:`phasors`).
#: Both are the same sums up to rounding; the product keeps the bundled scenarios (a handful of
#: vehicles) bit-identical to the results published with them, and costs little at that size,
#: while for the simulator's 256-vehicle complete graph it and the sines were most of the step.
PRODUCT_MAX_SLOTS = 64


def harmonics(
    phase_rad: NDArray[np.float64], n_harmonics: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(cos(l theta), sin(l theta)) for l = 1..n_harmonics, each ``(..., n_harmonics)`` for phases
    ``(...)`` [rad], by angle addition from harmonics computed directly at l = 1, 2, 4, ...:
    harmonics d+1..2d are harmonics 1..d turned by d theta. A few times faster than np.cos and
    np.sin of every l theta, and closer to the exact values for large l theta: the error grows
    with the number of doublings, not with the rounding of l theta."""
    shape = (*phase_rad.shape, n_harmonics)
    cos, sin = np.empty(shape), np.empty(shape)
    cos[..., 0], sin[..., 0] = np.cos(phase_rad), np.sin(phase_rad)
    done = 1
    while done < n_harmonics:
        width = min(done, n_harmonics - done)
        turn = done * phase_rad[..., None]
        cos_turn, sin_turn = np.cos(turn), np.sin(turn)
        cos_done, sin_done = cos[..., :width], sin[..., :width]
        np.subtract(cos_done * cos_turn, sin_done * sin_turn, out=cos[..., done : done + width])
        np.add(sin_done * cos_turn, cos_done * sin_turn, out=sin[..., done : done + width])
        done += width
    return cos, sin


def _product_coupling(
    phase_slots: NDArray[np.float64],
    row_slots: NDArray[np.intp],
    heard: NDArray[np.bool_],
    gains: NDArray[np.float64],
    *,
    neighbours: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """:func:`coupling_rate` as ``sin(l theta_i) (A cos(l theta))_i - cos(l theta_i) (A sin(l
    theta))_i`` with one matrix product ``A @ [cos, sin]``; phases finite."""
    n_harmonics = gains.shape[-1]
    order = np.arange(1, n_harmonics + 1)
    slots = phase_slots[..., :, None] * order  # (..., S, L)
    cos_slots, sin_slots = np.cos(slots), np.sin(slots)
    not_self = np.arange(heard.shape[-1]) != row_slots[:, None]  # (R, S)
    mask = not_self & heard[..., None, :]
    if neighbours is not None:
        mask = mask & neighbours
    weights = row_normalised(mask)
    mixed = weights @ np.concatenate([cos_slots, sin_slots], axis=-1)  # (..., R, 2L)
    # The rows' sines and cosines are their slots' (the same floats).
    cos_rows, sin_rows = cos_slots[..., row_slots, :], sin_slots[..., row_slots, :]  # (..., R, L)
    terms = sin_rows * mixed[..., :n_harmonics] - cos_rows * mixed[..., n_harmonics:]
    return np.sum((gains[..., None, :] / order) * terms, axis=-1)


def _summed_coupling(
    phase_slots: NDArray[np.float64],
    row_slots: NDArray[np.intp],
    heard: NDArray[np.bool_],
    gains: NDArray[np.float64],
) -> NDArray[np.float64]:
    """:func:`coupling_rate` in O(S L): with the same gains for every row,
    ``sum_{j heard} sum_l (K_l / l) sin(l (theta_i - theta_j))
    = sum_l (K_l / l) Im(e^{i l theta_i} conj(Z_l))`` with Z_l the sum of e^{i l theta_j} over
    the heard slots; a heard row's own term is sin(0) = 0, so the sum over its neighbours is the
    sum over every heard slot. Phases finite."""
    n_harmonics = gains.shape[-1]
    # Real products over the phasors' (cos, sin) pairs, which numpy keeps interleaved: complex
    # ones start BLAS threads that cost twice the CPU for no gain in time.
    pairs = phasors(phase_slots, n_harmonics).view(np.float64)  # (..., L, 2S): cos, sin
    spread = np.zeros((*heard.shape[:-1], 2 * heard.shape[-1], 2))  # (..., 2S, 2)
    spread[..., 0::2, 0] = heard
    spread[..., 1::2, 1] = heard
    sums = pairs @ spread  # (..., L, 2): C_l, S_l (Z_l = C_l + i S_l)
    scaled = gains / np.arange(1, n_harmonics + 1)  # (..., L)
    # sin(l theta_i) C_l - cos(l theta_i) S_l, l = 1..L: the weights of cos and of sin.
    weights = np.stack([-sums[..., 1], sums[..., 0]], axis=-2) * scaled[..., None, :]
    mixed = weights @ pairs  # (..., 2, 2S)
    rates = mixed[..., 0, 0::2] + mixed[..., 1, 1::2]  # (..., S)
    n_neighbours = np.sum(heard, axis=-1, keepdims=True) - heard[..., row_slots]  # (..., R)
    return rates[..., row_slots] / np.maximum(n_neighbours, 1)


def phasors(phase_rad: NDArray[np.float64], n_harmonics: int) -> NDArray[np.complex128]:
    """e^{i l theta} for l = 1..n_harmonics, ``(..., n_harmonics, S)`` complex for phases
    ``(..., S)`` [rad] (harmonic l - 1 on the second axis from the end): :func:`harmonics` as
    complex numbers, one complex product a harmonic (harmonics d+1..2d are harmonics 1..d
    times e^{i d theta}) instead of four real products and two sums, each with its temporary;
    a harmonic's slots are contiguous, so each doubling multiplies whole rows. Three times
    faster than :func:`harmonics` for a 256-vehicle swarm."""
    slots = phase_rad.shape[-1]
    result = np.empty((*phase_rad.shape[:-1], n_harmonics, slots), dtype=np.complex128)
    result[..., 0, :] = np.exp(1j * phase_rad)
    done = 1
    while done < n_harmonics:
        width = min(done, n_harmonics - done)
        turn = np.exp(1j * (done * phase_rad))[..., None, :]
        np.multiply(result[..., :width, :], turn, out=result[..., done : done + width, :])
        done += width
    return result


def _edge_coupling(
    phase_slots: NDArray[np.float64],
    row_slots: NDArray[np.intp],
    heard: NDArray[np.bool_],
    gains: NDArray[np.float64],
) -> NDArray[np.float64]:
    """:func:`coupling_rate` over a sparse graph, E the pairs (row, heard neighbour) of
    ``heard`` ``(..., R, S)``: each pair's sum over the harmonics (:func:`pair_coupling`), then
    the sums by row. A dense product would be O(R S L), with L ~ S harmonics. Phases finite."""
    pairs = (np.arange(heard.shape[-1]) != row_slots[:, None]) & heard
    *lead, rows, slots = np.nonzero(pairs)
    difference = phase_slots[(*lead, row_slots[rows])] - phase_slots[(*lead, slots)]
    batch_shape = pairs.shape[:-2]
    batch = np.ravel_multi_index(tuple(lead), batch_shape) if lead else np.zeros_like(rows)
    per_pair = pair_coupling(difference, gains.reshape(-1, gains.shape[-1]), batch)
    row_shape = pairs.shape[:-1]
    flat = np.ravel_multi_index((*lead, rows), row_shape)
    total = np.bincount(flat, weights=per_pair, minlength=int(np.prod(row_shape)))
    count = np.sum(pairs, axis=-1)
    return total.reshape(row_shape) / np.maximum(count, 1)


def pair_coupling(
    difference_rad: NDArray[np.float64],
    gains: NDArray[np.float64],
    which: NDArray[np.intp],
) -> NDArray[np.float64]:
    """f(x) = sum_l (K_l / l) sin(l x) for each pair's phase difference x = theta_i - theta_j
    ``(P,)`` [rad], with the gains ``gains[which[p]]`` (``(G, L)`` rows of K_1..K_L, ``which``
    ``(P,)``). Up to :data:`DIRECT_MAX_HARMONICS` harmonics the sum itself, O(P L); above, a
    table of f on a grid (:func:`_coupling_table`), O(P) a pair once the table is built."""
    result = np.empty(difference_rad.shape)
    if difference_rad.size == 0:
        return result
    # Wrapped to one turn: l times the difference keeps its precision for large l. Within a
    # half turn it is kept as it is (adding pi would round off its low bits, times f' ~ L).
    wrapped = difference_rad - (2 * np.pi) * np.rint(difference_rad / (2 * np.pi))
    if gains.shape[0] > 1 and np.all(gains == gains[0]):  # a batch's runs share their gains
        gains, which = gains[:1], np.zeros_like(which)
    used = np.unique(which)
    for group in used:
        members = which == group if used.size > 1 else slice(None)
        result[members] = _pair_sum(wrapped[members], gains[group])
    return result


#: Up to this many harmonics :func:`pair_coupling` sums them; above, it reads a table.
DIRECT_MAX_HARMONICS = 64


def _pair_sum(
    difference_rad: NDArray[np.float64], gains: NDArray[np.float64]
) -> NDArray[np.float64]:
    """f(x) for the phase differences ``(P,)`` in [-pi, pi) with one row of gains ``(L,)``."""
    n_harmonics = gains.shape[-1]
    if n_harmonics <= DIRECT_MAX_HARMONICS:
        scaled = gains / np.arange(1, n_harmonics + 1)
        _, sines = harmonics(difference_rad, n_harmonics)
        return sines @ scaled
    table = _coupling_table(gains.tobytes(), n_harmonics)
    points = table.shape[0]
    step = 2 * np.pi / points
    nearest = np.rint(difference_rad / step)
    # x - g h with h in two parts, the first of 32 bits so that g times it is exact: the offset
    # then carries the rounding of x alone, not x's times M (f' is up to ~L).
    step_high = float(np.float32(step))
    offset = difference_rad - nearest * step_high
    offset -= nearest * (step - step_high)
    offset /= step  # in [-1/2, 1/2] grid steps
    coefficients = table[nearest.astype(np.intp) % points]  # (P, J + 1)
    total = coefficients[:, -1].copy()
    for order in range(table.shape[1] - 2, -1, -1):  # Horner in the offset
        total *= offset
        total += coefficients[:, order]
    return total


#: The table's grid has this many points per harmonic (a power of two times L at least), so
#: that l times the distance to the nearest point is at most pi / GRID_PER_HARMONIC; its
#: Taylor series there, to :data:`TAYLOR_TERMS` terms, is then exact to rounding
#: ((pi / 8)^17 / 17! < 1e-20 of the sum of |K_l / l|).
GRID_PER_HARMONIC = 8
TAYLOR_TERMS = 17


@functools.lru_cache(maxsize=4)
def _coupling_table(gains_bytes: bytes, n_harmonics: int) -> NDArray[np.float64]:
    """f and its derivatives on a uniform grid of M points over one turn, ``(M, J)``: row g
    holds f^(j)(x_g) h^j / j! for j < J, x_g = g h, h = 2 pi / M, so that f(x_g + u h) is the
    polynomial in u of the row. f is a trigonometric polynomial: every derivative on the grid
    is one inverse FFT of its coefficients. Kept per set of gains (they change only when a
    vehicle is lost or joins)."""
    gains = np.frombuffer(gains_bytes, dtype=np.float64)
    points = 1 << max(6, int(np.ceil(np.log2(GRID_PER_HARMONIC * n_harmonics))))
    order = np.arange(1, n_harmonics + 1)
    step = 2 * np.pi / points
    coefficients = np.zeros((TAYLOR_TERMS, points), dtype=complex)
    term = (gains / order).astype(complex)  # K_l / l (i l h)^j / j!, j = 0, 1, ...
    for j in range(TAYLOR_TERMS):
        coefficients[j, 1 : n_harmonics + 1] = term
        term = term * (1j * order * step) / (j + 1)
    # sum_l c_l e^{i l x_g}; the imaginary part is the sine series.
    values = np.fft.ifft(coefficients, axis=-1) * points
    return np.ascontiguousarray(values.imag.T)


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

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from mission_runner.enclosing.control import row_normalised
from mission_runner.enclosing.oscillator import (
    PRODUCT_MAX_SLOTS,
    _product_coupling,
    _summed_coupling,
    advance_phase,
    coupling_rate,
    harmonic_gains,
    harmonics,
    pair_coupling,
    phasors,
    splay_spacing_error,
)


def brute_force_coupling(theta, weights, gains):
    """The paper's double sum, written as loops."""
    out = []
    for i in range(len(theta)):
        total = 0.0
        for j in range(len(theta)):
            for order, gain in enumerate(gains, start=1):
                total += gain * weights[i, j] / order * math.sin(order * (theta[i] - theta[j]))
        out.append(total)
    return np.array(out)


def test_harmonic_gains_follow_the_live_count():
    gains = harmonic_gains(np.array([4, 3, 1]), 5, 1.0, -1.0)
    np.testing.assert_array_equal(gains[0], [1, 1, 1, -1, 0])
    np.testing.assert_array_equal(gains[1], [1, 1, -1, 0, 0])
    np.testing.assert_array_equal(gains[2], [0, 0, 0, 0, 0])


@given(
    theta=arrays(np.float64, st.integers(2, 7), elements=st.floats(-10, 10)),
    seed=st.integers(0, 2**16),
)
def test_sums_over_the_heard_equal_the_double_sum(theta, seed):
    rng = np.random.default_rng(seed)
    n = theta.size
    heard = rng.uniform(size=n) < 0.8
    rows = np.arange(n)
    weights = row_normalised(heard[None, :] & (rows[:, None] != rows))
    gains = harmonic_gains(n, n, 1.3, -0.7)
    slots = np.where(heard, theta, np.nan)
    slots[rows] = theta  # a row always knows its own phase
    fast = coupling_rate(slots, rows, heard, gains)
    np.testing.assert_allclose(fast, brute_force_coupling(theta, weights, gains), atol=1e-9)


@pytest.mark.parametrize("n_slots", [5, PRODUCT_MAX_SLOTS + 7])
def test_one_row_sees_the_same_coupling_as_in_the_swarm(n_slots):
    rng = np.random.default_rng(n_slots)
    theta = rng.uniform(-10, 10, n_slots)
    heard = rng.uniform(size=n_slots) < 0.8
    gains = harmonic_gains(n_slots, n_slots, 1.0, -1.0)
    swarm = coupling_rate(theta, np.arange(n_slots), heard, gains)
    for row in range(n_slots):
        alone = coupling_rate(theta, np.array([row]), heard, gains)
        np.testing.assert_allclose(alone, swarm[row : row + 1], rtol=0, atol=1e-13)


def test_large_swarms_sum_over_the_heard_as_the_matrix_product_does():
    rng = np.random.default_rng(3)
    batch, n_slots = 2, PRODUCT_MAX_SLOTS + 9
    phases = rng.uniform(-50, 50, (batch, n_slots))
    rows = rng.permutation(n_slots)[:20]
    heard = rng.uniform(size=(batch, n_slots)) < 0.7
    gains = harmonic_gains(heard.sum(axis=-1), n_slots - 1, 1.3, -0.7)  # (batch, L)
    product = _product_coupling(phases, rows, heard, gains)
    summed = _summed_coupling(phases, rows, heard, gains)
    assert summed.shape == (batch, rows.size)
    # np.cos(l theta) in the product is itself off by |l theta| eps, up to 4e-13 here
    np.testing.assert_allclose(summed, product, rtol=0, atol=1e-10)


@pytest.mark.parametrize("n_harmonics", [1, 2, 7, 256, 300])
def test_harmonics_by_angle_addition_equal_the_direct_ones(n_harmonics):
    phase = np.random.default_rng(n_harmonics).uniform(-50, 50, (3, 40))
    cos, sin = harmonics(phase, n_harmonics)
    angle = phase[..., None] * np.arange(1, n_harmonics + 1)
    # np.cos(l theta) itself is off by up to |l theta| eps (the rounding of l theta)
    np.testing.assert_allclose(cos, np.cos(angle), rtol=0, atol=1e-11)
    np.testing.assert_allclose(sin, np.sin(angle), rtol=0, atol=1e-11)
    assert cos.shape == sin.shape == (3, 40, n_harmonics)


def pairwise_coupling(theta, heard, gains):
    """The coupling of every slot as the mean over its heard neighbours of the sum over the
    harmonics, pair by pair (each difference wrapped to a half turn, so l times it keeps its
    precision)."""
    difference = theta[:, None] - theta[None, :]
    difference -= 2 * np.pi * np.rint(difference / (2 * np.pi))
    order = np.arange(1, gains.size + 1)
    per_pair = np.sin(difference[..., None] * order) @ (gains / order)  # (S, S)
    mask = heard[None, :] & ~np.eye(theta.size, dtype=bool)
    return np.sum(np.where(mask, per_pair, 0.0), axis=-1) / np.maximum(mask.sum(axis=-1), 1)


@pytest.mark.parametrize("n_slots", [9, PRODUCT_MAX_SLOTS, PRODUCT_MAX_SLOTS + 1, 200])
@pytest.mark.parametrize("seed", range(3))
def test_coupling_equals_the_pairwise_sum_below_and_above_the_product_threshold(n_slots, seed):
    rng = np.random.default_rng([n_slots, seed])
    theta = rng.uniform(0, 2 * np.pi, n_slots)
    heard = rng.uniform(size=n_slots) < 0.8
    gains = harmonic_gains(heard.sum(), n_slots - 1, 1.3, -0.7)
    rows = np.arange(n_slots)
    expected = pairwise_coupling(theta, heard, gains)
    np.testing.assert_allclose(
        coupling_rate(theta, rows, heard, gains), expected, rtol=0, atol=1e-12
    )


@pytest.mark.parametrize("n_harmonics", [1, 2, 7, 256, 300])
def test_phasors_equal_the_harmonics(n_harmonics):
    phase = np.random.default_rng(n_harmonics).uniform(-50, 50, (3, 40))
    powers = np.swapaxes(phasors(phase, n_harmonics), -1, -2)
    cos, sin = harmonics(phase, n_harmonics)
    assert powers.shape == (3, 40, n_harmonics)
    # both are within a few eps of the exact values; np.cos(l theta) is not (see above)
    np.testing.assert_allclose(powers.real, cos, rtol=0, atol=1e-13)
    np.testing.assert_allclose(powers.imag, sin, rtol=0, atol=1e-13)


def test_unheard_neighbours_with_nan_phase_do_not_poison_the_sum():
    theta = np.array([0.1, 0.5, np.nan])
    heard = np.array([False, True, False])
    rate = coupling_rate(theta, np.array([0]), heard, harmonic_gains(3, 3, 1.0, -1.0))
    assert np.isfinite(rate).all()
    assert rate[0] != 0.0  # slot 1 is heard


def run_oscillators(theta, steps=400, step_s=0.125, omega=math.pi / 2):
    n = theta.size
    rows, heard = np.arange(n), np.ones(n, dtype=bool)
    gains = harmonic_gains(n, n, 1.0, -1.0)
    for _ in range(steps):
        theta = advance_phase(theta, omega, coupling_rate(theta, rows, heard, gains), step_s)
    return theta


# n = 2 is left out on purpose: with the paper's K_n = -1 (not "sufficiently small") the first-order
# terms of K_1 and K_2 cancel, so two nearly synchronised phases drift apart only at third order.
@pytest.mark.parametrize("n", [3, 4, 5, 6, 8])
@pytest.mark.parametrize("seed", range(8))
def test_splay_state_is_reached_from_seeded_random_phases(n, seed):
    theta = np.random.default_rng([n, seed]).uniform(0, 2 * np.pi, n)
    final = run_oscillators(theta, steps=1200)
    assert splay_spacing_error(final, np.ones(n, dtype=bool)) < 1e-6


def test_splay_state_rotates_at_the_natural_frequency():
    n = 4
    splay = np.arange(n) * 2 * np.pi / n
    after = run_oscillators(splay, steps=10)
    np.testing.assert_allclose(after - splay, 10 * 0.125 * math.pi / 2, atol=1e-12)


def test_spacing_error_measures_the_worst_gap():
    live = np.ones(4, dtype=bool)
    assert splay_spacing_error(np.array([0, 1, 2, 3]) * np.pi / 2, live) < 1e-12
    skewed = np.array([0.0, np.pi / 2 + 0.1, np.pi, 3 * np.pi / 2])
    assert splay_spacing_error(skewed, live) == pytest.approx(0.1)
    three_of_four = np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3, 1.0])
    assert splay_spacing_error(three_of_four, np.array([1, 1, 1, 0], bool)) < 1e-12
    assert np.isnan(splay_spacing_error(np.array([0.0, 1.0]), np.array([True, False])))


@pytest.mark.parametrize("n_harmonics", [5, 65, 1000])
def test_the_pair_coupling_table_equals_the_harmonic_sum(n_harmonics):
    # Two sets of gains (live counts) at once; differences near 0 (where f' ~ L), near a half
    # turn and beyond one turn. The reference sums every harmonic in extended precision.
    gains = harmonic_gains(np.array([n_harmonics, n_harmonics - 1]), n_harmonics, 1.3, -0.7)
    rng = np.random.default_rng(n_harmonics)
    difference = np.concatenate(
        [rng.uniform(-np.pi, np.pi, 400), rng.uniform(-1e-3, 1e-3, 50), [0.0, np.pi, 7.0, -20.0]]
    )
    which = rng.integers(0, 2, difference.size)
    fast = pair_coupling(difference, gains, which)
    order = np.arange(1, n_harmonics + 1).astype(np.longdouble)
    angle = difference.astype(np.longdouble)[:, None] * order
    exact = np.sum(np.sin(angle) * (gains[which].astype(np.longdouble) / order), axis=-1)
    np.testing.assert_allclose(fast, exact.astype(float), rtol=0, atol=5e-15)

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from mission_runner.enclosing.control import row_normalised
from mission_runner.enclosing.oscillator import (
    advance_phase,
    coupling_rate,
    harmonic_gains,
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
def test_matrix_form_equals_the_double_sum(theta, seed):
    rng = np.random.default_rng(seed)
    n = theta.size
    mask = (rng.uniform(size=(n, n)) < 0.8) & ~np.eye(n, dtype=bool)
    weights = row_normalised(mask)
    gains = harmonic_gains(n, n, 1.3, -0.7)
    fast = coupling_rate(theta, theta, weights, np.broadcast_to(gains, (n, n)))
    np.testing.assert_allclose(fast, brute_force_coupling(theta, weights, gains), atol=1e-9)


def test_unheard_neighbours_with_nan_phase_do_not_poison_the_sum():
    theta = np.array([0.1, 0.5, np.nan])
    weights = row_normalised(np.array([[False, True, False]]))
    rate = coupling_rate(theta[:1], theta, weights, harmonic_gains(3, 3, 1.0, -1.0)[None])
    assert np.isfinite(rate).all()


def run_oscillators(theta, steps=400, step_s=0.125, omega=math.pi / 2):
    n = theta.size
    weights = row_normalised(~np.eye(n, dtype=bool))
    gains = np.broadcast_to(harmonic_gains(n, n, 1.0, -1.0), (n, n))
    for _ in range(steps):
        theta = advance_phase(theta, omega, coupling_rate(theta, theta, weights, gains), step_s)
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

"""The per-edge filter estimator: exact without noise, near the noise floor with it, and deaf to
a range that is off by an NLOS bias."""

import dataclasses

import numpy as np
import pytest

from mission_runner.enclosing import SwarmEnclosing
from mission_runner.enclosing.ekf import FilterEdges, FilterSettings, filter_update
from mission_runner.enclosing.errors import EnclosingError
from mission_runner.enclosing.rlse import EdgeEstimates, rlse_update

from .swarm_loop import PAPER, World, initial_positions
from .test_rlse import circular_relative_path
from .test_step import OMEGA, PHASES, make_vehicles, swarm_step, vehicle_steps


def run_edge(
    path,
    settings,
    *,
    range_noise_m=0.0,
    displacement_noise_m=0.0,
    seed=0,
    biased=None,
    measured=None,
    odometry_jump=None,
):
    """One edge (R = S = 1) along ``path`` ``(K, 2)``: ranges with Gaussian noise (plus
    ``biased`` ``{k: bias_m}``), relative odometry with a random-walk error (plus
    ``odometry_jump`` ``(k, (2,))`` from step k on). Returns the
    estimate error per step ``(K,)``, the gated mask ``(K,)`` and the final state."""
    rng = np.random.default_rng(seed)
    edges = FilterEdges.initial((1, 1))
    odometry_error = np.zeros(2)
    errors, gated = [], []
    for k, relative in enumerate(path):
        distance = np.linalg.norm(relative) + range_noise_m * rng.normal()
        distance += (biased or {}).get(k, 0.0)
        if measured is not None and not measured[k]:
            distance = np.nan
        odometry = relative - path[0] + odometry_error
        if odometry_jump is not None and k >= odometry_jump[0]:
            odometry = odometry + odometry_jump[1]
        moved = odometry[:, None, None]
        edges, rejected = filter_update(
            edges, np.array([[distance]]), *moved, step=k, settings=settings
        )
        estimate = np.ravel(np.stack(edges.current(*moved), axis=-1))
        errors.append(np.linalg.norm(estimate - relative))
        gated.append(bool(rejected[0, 0]))
        odometry_error = odometry_error + np.sqrt(2) * displacement_noise_m * rng.normal(size=2)
    return np.array(errors), np.array(gated), edges


def rlse_errors(path, forgetting_factor, *, range_noise_m, displacement_noise_m, seed=0):
    """The paper's RLSE on the same measurements as :func:`run_edge` draws."""
    rng = np.random.default_rng(seed)
    estimates = EdgeEstimates.initial((1, 1))
    odometry_error = np.zeros(2)
    errors = []
    for relative in path:
        distance = np.linalg.norm(relative) + range_noise_m * rng.normal()
        moved = (relative - path[0] + odometry_error)[:, None, None]
        estimates = rlse_update(estimates, np.array([[distance]]), *moved, forgetting_factor)
        errors.append(np.linalg.norm(np.ravel(np.stack(estimates.current(*moved), -1)) - relative))
        odometry_error = odometry_error + np.sqrt(2) * displacement_noise_m * rng.normal(size=2)
    return np.array(errors)


#: The gate, hand-over and regression these tests were measured with (a scenario's come from
#: its ``algorithm.estimator_settings``: mission_runner.wiring.filter_settings).
MEASURED_WITH = {
    "gate_chi2": 10.83,
    "gate_patience": 10,
    "initial_forgetting_factor": 0.7,
    "handover_updates": 10,
    "handover_std_m": 1.0,
    "range_common_std_m": 0.0,
    "gate_long_only": False,
}
NOISE_FREE = FilterSettings(range_noise_std_m=0.0, displacement_noise_std_m=0.0, **MEASURED_WITH)
NOISY = FilterSettings(range_noise_std_m=0.1, displacement_noise_std_m=0.005, **MEASURED_WITH)
#: Sensors good to 0.1 mm: the filter takes over once the regression is that good.
NEARLY_EXACT = FilterSettings(
    range_noise_std_m=1e-4, displacement_noise_std_m=3e-5, **MEASURED_WITH
)


def test_with_exact_sensors_the_edge_stays_on_its_exact_regression():
    errors, gated, edges = run_edge(circular_relative_path(150), NOISE_FREE)
    assert errors[0] > 1.0
    assert not edges.engaged.any()
    # Measured: below 1e-6 m from step 50 on.
    assert errors[55:].max() < 1e-6
    assert not gated.any()


def test_nearly_exact_filter_takes_over_near_the_truth_and_converges_below_a_micrometre():
    errors, gated, edges = run_edge(circular_relative_path(150), NEARLY_EXACT)
    assert errors[0] > 1.0
    assert edges.engaged.all()
    # Measured: below 1e-6 m from step 46 on (67 when the hand-over did not wait for the
    # regression to reach the sensors' noise).
    assert errors[50:].max() < 1e-6
    assert not gated.any()


def test_before_the_hand_over_the_estimate_is_the_papers_rlse():
    path = circular_relative_path(8)
    settings = dataclasses.replace(NOISE_FREE, handover_updates=50)
    errors, _, edges = run_edge(path, settings)
    assert not edges.engaged.any()
    np.testing.assert_array_equal(
        errors, rlse_errors(path, 0.7, range_noise_m=0.0, displacement_noise_m=0.0)
    )


def test_with_noise_the_filter_is_several_times_better_than_the_papers_rlse():
    path = circular_relative_path(600)
    noise = {"range_noise_m": 0.1, "displacement_noise_m": 0.005}
    filtered, gated, _ = run_edge(path, NOISY, **noise, seed=3)
    paper = rlse_errors(path, 0.7, **noise, seed=3)
    tail = slice(150, None)
    filter_rms = np.sqrt(np.mean(filtered[tail] ** 2))
    assert filter_rms < 0.06
    assert filter_rms < np.sqrt(np.mean(paper[tail] ** 2)) / 4
    assert gated.sum() <= 3  # a 10.83 chi-square gate rejects ~0.1 % of good ranges


def test_an_injected_outlier_is_gated_and_leaves_the_estimate_alone():
    path = circular_relative_path(300)
    noise = {"range_noise_m": 0.05, "displacement_noise_m": 0.002, "seed": 11}
    settings = dataclasses.replace(NOISY, range_noise_std_m=0.05, displacement_noise_std_m=0.002)
    clean, clean_gated, _ = run_edge(path, settings, **noise)
    hit, hit_gated, _ = run_edge(path, settings, **noise, biased={200: 3.0})
    assert hit_gated[200] and not clean_gated[200]
    assert (hit_gated != clean_gated).sum() == 1
    # The range is skipped as if missing: the next update spans two steps, nearly the same.
    assert np.abs(hit[200:] - clean[200:]).max() < 0.02


def test_gating_long_ranges_only_takes_a_short_one_and_still_gates_a_long_one():
    """NLOS reads long: with ``gate_long_only`` a range 0.5 m too short is taken (it says the
    estimate is too long), one 0.5 m too long is still gated."""
    path = circular_relative_path(300)
    noise = {"range_noise_m": 0.05, "displacement_noise_m": 0.002, "seed": 11}
    settings = dataclasses.replace(
        NOISY, range_noise_std_m=0.05, displacement_noise_std_m=0.002, gate_long_only=True
    )
    _, short_gated, _ = run_edge(path, settings, **noise, biased={200: -0.5})
    _, long_gated, _ = run_edge(path, settings, **noise, biased={200: 0.5})
    assert long_gated[200] and not short_gated[200]
    both_sides = dataclasses.replace(settings, gate_long_only=False)
    assert run_edge(path, both_sides, **noise, biased={200: -0.5})[1][200]


def test_without_a_gate_the_same_outlier_pulls_the_estimate():
    path = circular_relative_path(300)
    noise = {"range_noise_m": 0.05, "displacement_noise_m": 0.002, "seed": 11}
    settings = dataclasses.replace(
        NOISY, range_noise_std_m=0.05, displacement_noise_std_m=0.002, gate_chi2=None
    )
    clean, _, _ = run_edge(path, settings, **noise)
    hit, gated, _ = run_edge(path, settings, **noise, biased={200: 3.0})
    assert not gated.any()
    assert hit[200] - clean[200] > 0.1


def test_an_edge_that_gates_every_range_restarts_from_its_regression():
    # An odometry glitch moves the filter's prediction 2 m for good: every range disagrees with
    # it, which is the filter being wrong, not the ranges.
    path = circular_relative_path(200)
    errors, gated, edges = run_edge(path, NEARLY_EXACT, odometry_jump=(100, np.array([2.0, 0.0])))
    assert gated[100:110].all()
    assert edges.engaged.all()
    assert gated.sum() < 30
    assert errors[-20:].max() < 1e-5  # measured 3.6e-6 m: 90 steps after the restart


def test_missing_ranges_stretch_the_prediction():
    path = circular_relative_path(200)
    measured = np.random.default_rng(5).uniform(size=len(path)) > 0.4
    measured[0] = True
    errors, _, _ = run_edge(path, NOISE_FREE, measured=measured)
    assert np.isfinite(errors).all()
    assert errors[150:].max() < 1e-6


def test_runs_are_deterministic_for_a_seed():
    path = circular_relative_path(100)
    first = run_edge(path, NOISY, range_noise_m=0.1, displacement_noise_m=0.005, seed=4)[0]
    second = run_edge(path, NOISY, range_noise_m=0.1, displacement_noise_m=0.005, seed=4)[0]
    np.testing.assert_array_equal(first, second)


EKF = dataclasses.replace(PAPER, estimator="ekf", filter=NOISE_FREE)


def test_vehicle_face_and_swarm_face_agree_with_the_filter():
    world = World(initial_positions())
    swarm = SwarmEnclosing(EKF, PHASES, np.full(4, OMEGA))
    vehicles = make_vehicles(params=EKF)
    for _ in range(200):
        together = swarm_step(swarm, world)
        alone = vehicle_steps(vehicles, world)
        velocities = np.array([command.velocity_m_s for command in alone])
        np.testing.assert_allclose(velocities, together.velocity_m_s, rtol=0, atol=1e-9)
        error = np.linalg.norm(together.estimate_m - world.truth(), axis=-1)
        world.advance(together.velocity_m_s)
    assert np.nanmax(error) < 1e-6


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"gate_chi2": 0.0}, "gate_chi2"),
        ({"initial_forgetting_factor": 1.5}, "initial_forgetting_factor"),
        ({"handover_updates": 0}, "handover_updates"),
    ],
)
def test_invalid_filter_settings_are_rejected(change, message):
    with pytest.raises(EnclosingError, match=message):
        dataclasses.replace(NOISY, **change)


def test_the_filter_estimator_needs_its_settings():
    with pytest.raises(EnclosingError, match="needs filter"):
        dataclasses.replace(PAPER, estimator="ekf")

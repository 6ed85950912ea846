import numpy as np

from mission_runner.enclosing.rlse import EdgeEstimates, rlse_update


def circular_relative_path(steps, radius=3.0, offset=(5.0, -2.0)):
    """p_ij(k) of two vehicles circling each other: persistently exciting."""
    angle = np.arange(steps) * 0.2
    return np.asarray(offset) + radius * np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def run_edge(path, measured):
    """One edge (R = S = 1) whose own odometry is p_ij itself (the other vehicle stays put)."""
    estimates = EdgeEstimates.initial((1, 1))
    history = []
    for k, relative in enumerate(path):
        distance = np.linalg.norm(relative) if measured[k] else np.nan
        moved = (relative - path[0])[:, None, None]
        estimates = rlse_update(estimates, np.array([[distance]]), *moved, 0.7)
        history.append(np.ravel(estimates.current(*moved)) - relative)
    return np.linalg.norm(np.array(history), axis=-1)


def test_noise_free_estimate_converges_to_the_true_relative_position():
    path = circular_relative_path(150)
    error = run_edge(path, np.ones(len(path), dtype=bool))
    assert error[0] > 1.0
    assert error[100:].max() < 1e-9


def test_missing_ranges_stretch_the_update_instead_of_corrupting_it():
    path = circular_relative_path(200)
    measured = np.random.default_rng(5).uniform(size=len(path)) > 0.4
    measured[0] = True
    error = run_edge(path, measured)
    assert np.isfinite(error).all()
    assert error[150:].max() < 1e-9


def test_edges_without_odometry_keep_their_anchor():
    estimates = EdgeEstimates.initial((1, 2))
    zero = np.zeros((1, 2))
    first = rlse_update(estimates, np.array([[3.0, 4.0]]), zero, zero, 0.7)
    assert first.anchored.all()
    north, east = np.array([[1.0, np.nan]]), np.array([[0.0, np.nan]])
    second = rlse_update(first, np.array([[3.5, 4.2]]), north, east, 0.7)
    np.testing.assert_array_equal(second.anchor_range_m[0, 1], 4.0)
    np.testing.assert_array_equal(second.estimate_m[0, 1], first.estimate_m[0, 1])
    now = np.stack(second.current(north, east), axis=-1)
    assert np.isnan(now[0, 1]).all()
    assert np.isfinite(now[0, 0]).all()


def test_first_measurement_anchors_with_the_papers_initial_values():
    zero = np.zeros((2, 3))
    estimates = rlse_update(EdgeEstimates.initial((2, 3)), np.full((2, 3), 2.0), zero, zero, 0.7)
    np.testing.assert_array_equal(estimates.estimate_m, 0.0)
    np.testing.assert_array_equal(estimates.gain, np.broadcast_to(np.eye(2), (2, 3, 2, 2)))

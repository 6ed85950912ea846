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


def test_the_error_bound_holds_the_estimates_error_and_shrinks_as_it_converges():
    # Exact ranges: the bound starts at the range (phat = 0, direction unknown) and, the error
    # moving linearly, bounds it exactly after every update; the estimate is not changed by it.
    rng = np.random.default_rng(5)
    truth = np.array([3.0, -2.0])
    kept = plain = EdgeEstimates.initial((1, 1))
    bounds, ranges = [], []
    for _ in range(15):
        truth = truth + rng.normal(scale=0.3, size=2)
        moved = (truth[0] - np.zeros((1, 1)), truth[1] - np.zeros((1, 1)))  # o_j still
        distance = np.array([[np.hypot(*truth)]])
        kept = rlse_update(kept, distance, *moved, 0.7, range_noise_std_m=0.0)
        plain = rlse_update(plain, distance, *moved, 0.7)
        error = np.hypot(*(np.array(kept.current(*moved))[:, 0, 0] - truth))
        bound = float(kept.bearing_std_rad[0, 0]) * float(kept.anchor_range_m[0, 0])
        assert error <= bound * (1 + 1e-9) + 1e-12
        assert np.array_equal(kept.estimate_north_m, plain.estimate_north_m)
        bounds.append(bound)
        ranges.append(float(distance[0, 0]))
    assert bounds[0] == ranges[0]  # the first range: phat = 0 is that far off
    assert bounds[-1] < 0.1 * bounds[0]
    assert plain.bearing_std_rad[0, 0] != plain.bearing_std_rad[0, 0]  # none kept: NaN


def test_a_range_over_too_short_a_displacement_is_skipped_and_the_next_spans_the_longer_one():
    zero = np.zeros((1, 1))
    first = rlse_update(EdgeEstimates.initial((1, 1)), np.array([[5.0]]), zero, zero, 0.7)
    near = (zero + 0.05, zero)  # 5 cm since the anchor: below the 0.15 m asked for
    skipped = rlse_update(first, np.array([[5.04]]), *near, 0.7, min_displacement_m=0.15)
    assert skipped.anchor_range_m[0, 0] == 5.0 and skipped.anchor_north_m[0, 0] == 0.0
    assert skipped.gain_nn[0, 0] == first.gain_nn[0, 0]
    far = (zero + 0.2, zero)
    spanned = rlse_update(skipped, np.array([[5.15]]), *far, 0.7, min_displacement_m=0.15)
    assert np.array_equal(
        spanned.estimate_m, rlse_update(first, np.array([[5.15]]), *far, 0.7).estimate_m
    )

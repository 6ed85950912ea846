"""Scoring a mission of vehicle processes from the range aid's truth."""

import numpy as np

from mission_runner.records import TruthSample
from mission_runner.runner.scoring import fill_truth_gaps


def _samples(known):
    """Two vehicles flying north at 1 m a step, vehicle 2 two metres east; ``known[k]``: which
    of them has a position at step k."""
    return [
        TruthSample(
            k,
            0.125 * k,
            np.zeros(2),
            np.array(
                [[k, 0.0] if alive[0] else [np.nan, np.nan], [k, 2.0] if alive[1] else [np.nan] * 2]
            ),
            np.array(alive),
        )
        for k, alive in enumerate(known)
    ]


def test_steps_the_range_aid_skipped_are_interpolated_between_the_positions_around_them():
    both, none, second = (True, True), (False, False), (False, True)
    filled = fill_truth_gaps(_samples([both, none, none, both, second, both]))

    assert all(s.alive.all() for s in filled)
    for k, sample in enumerate(filled):
        np.testing.assert_allclose(sample.positions_m, [[k, 0.0], [k, 2.0]])


def test_a_vehicle_lost_for_good_or_gone_too_long_stays_unknown():
    both, second = (True, True), (False, True)
    lost = fill_truth_gaps(_samples([both, second, second, second]))
    assert [s.alive.tolist() for s in lost] == [[True, True]] + [[False, True]] * 3
    long_gap = fill_truth_gaps(_samples([both, *[second] * 9, both]), max_gap_steps=8)
    assert not any(s.alive[0] for s in long_gap[1:-1])
    assert all(np.isnan(s.positions_m[0]).all() for s in long_gap[1:-1])

import numpy as np

from mission_runner.config import Expectation
from mission_runner.metrics import check_expectations, converged_step, distribution


def test_converged_step_is_the_first_step_after_the_last_violation():
    error = np.array([[5, 1, 0.01, 0.2, 0.01, 0.001], [0.01] * 6, [1] * 6, [1, 1, 1, 1, 1, 0.0]])
    np.testing.assert_array_equal(converged_step(error, 0.05), [4, 0, -1, 5])


def test_nan_counts_as_not_converged():
    assert converged_step(np.array([[0.0, np.nan, 0.0]]), 0.1)[0] == 2


def test_expectations_report_each_violation():
    expect = {
        "final_tracking_error_m": Expectation(max=0.05),
        "min_separation_m": Expectation(min=1.0),
        "tracking_converged_step": Expectation(max=100),
    }
    failures = check_expectations(
        expect,
        {"final_tracking_error_m": 0.2, "min_separation_m": 2.0, "tracking_converged_step": -1},
    )
    assert len(failures) == 2
    assert "final_tracking_error_m = 0.2 > max 0.05" in failures[0]
    assert "never" in failures[1]


def test_distribution_of_errors_and_of_convergence_steps():
    stats = distribution(np.arange(101.0), "final_tracking_error_m")
    assert stats == {"median": 50.0, "p95": 95.0, "worst": 100.0}
    steps = distribution(np.array([10, 20, -1]), "tracking_converged_step")
    assert steps["never_converged"] == 1 and steps["worst"] is None

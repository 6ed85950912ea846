"""The paper's claims, checked on the numeric simulator (the same step a vehicle flies)."""

from pathlib import Path

import numpy as np
import pytest

from mission_runner.checks import load_scenario, validate_scenario
from mission_runner.enclosing import LOST
from mission_runner.metrics import check_expectations, run_metrics
from mission_runner.sim.simulator import flight_only_events, simulate

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def scenario_data(name="paper_tracking"):
    return load_scenario(CONFIGS / f"{name}.yaml").model_dump(mode="json")


def with_changes(data, **sections):
    for key, value in sections.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) else value
    return validate_scenario(data)


@pytest.fixture(scope="module")
def tracking_batch():
    scenario = load_scenario(CONFIGS / "paper_tracking.yaml")
    return simulate(scenario, runs=24)


def test_tracking_error_converges_below_5_cm_from_varied_initial_conditions(tracking_batch):
    final = tracking_batch.tracking_error_m[:, -1]
    assert np.median(final) < 1e-6
    assert (final < 0.05).all()


def test_relative_localization_error_reaches_1e_9(tracking_batch):
    assert (tracking_batch.localization_error_m[:, -50:] < 1e-9).all()


def test_splay_spacing_is_reached(tracking_batch):
    assert (tracking_batch.phase_spacing_error_rad[:, -1] < 1e-6).all()


def test_saturated_term_stays_within_ubar(tracking_batch):
    assert tracking_batch.consensus_speed_m_s.max() <= 0.4 * (1 + 1e-12)


def test_batch_run_zero_is_the_pinned_single_run(tracking_batch):
    single = simulate(tracking_batch.scenario)
    np.testing.assert_array_equal(single.positions_m[0], tracking_batch.positions_m[0])


def test_runs_are_reproducible_with_noise():
    # Plumbing (the seed reaches every draw): 60 steps show it as well as 600.
    scenario = with_changes(
        scenario_data(),
        sensors={"range_noise_std_m": 0.05, "displacement_noise_std_m": 0.002},
        timing={"steps": 60},
    )
    first, second = simulate(scenario, runs=3), simulate(scenario, runs=3)
    np.testing.assert_array_equal(first.positions_m, second.positions_m)
    other_seed = simulate(with_changes(scenario.model_dump(mode="json"), seed=99), runs=3)
    assert not np.array_equal(first.positions_m, other_seed.positions_m)


def test_narrow_passage_rebalances_after_the_loss_of_vehicle_4():
    result = simulate(load_scenario(CONFIGS / "paper_narrow_passage.yaml"))
    live = result.live[0]
    assert live[249].all() and live[250].sum() == 3
    spacing = result.phase_spacing_error_rad[0]
    assert spacing[245] < 1e-6  # four vehicles 90 degrees apart before the loss
    assert spacing[252] > 0.5  # three vehicles with a 180-degree hole right after it
    assert spacing[-1] < 1e-6  # ... re-balanced to 120 degrees
    assert result.tracking_error_m[0, -1] < 0.05


def test_a_vehicle_joining_late_is_taken_into_the_pattern():
    data = scenario_data()
    data["events"] = [{"kind": "vehicle_joins", "vehicle": 4, "at_step": 200}]
    # It waits where the swarm will be when it joins (the target is 20 m north by then).
    data["vehicles"][3]["initial_position_m"] = [22.0, 3.0]
    result = simulate(validate_scenario(data))
    live = result.live[0]
    assert live[199].sum() == 3 and live[200].all()
    assert result.phase_spacing_error_rad[0, 190] < 1e-6  # three at 120 degrees
    assert result.phase_spacing_error_rad[0, -1] < 1e-6  # four at 90 degrees
    assert result.tracking_error_m[0, -1] < 0.05


# One subset in the fast lane (two sensing, neither alone), the rest with the slow tests: each
# is a full 600-step run, and vehicle 1 alone is also tracking_batch's.
@pytest.mark.parametrize(
    "sensing",
    [
        pytest.param([1], marks=pytest.mark.slow),
        pytest.param([2], marks=pytest.mark.slow),
        pytest.param([3], marks=pytest.mark.slow),
        [1, 3],
        pytest.param([1, 2, 3, 4], marks=pytest.mark.slow),
    ],
)
def test_any_subset_of_sensing_vehicles_drives_the_centroid_to_the_target(sensing):
    data = scenario_data()
    for vehicle in data["vehicles"]:
        vehicle["senses_target"] = vehicle["id"] in sensing
    result = simulate(validate_scenario(data))
    assert result.tracking_error_m[0, -1] < 0.05


def test_flight_only_events_are_refused_with_a_pointer_to_run():
    from mission_runner.errors import SimulationError

    with pytest.raises(SimulationError, match="mission-runner run"):
        simulate(load_scenario(CONFIGS / "link_lost_flight.yaml"))


def test_losing_the_only_sensing_vehicle_is_predicted_then_lost():
    # Nobody senses the target from step 10: every vehicle predicts it for target_lost_after_s,
    # then the formation declares it lost (it used to be an error of the simulator).
    data = scenario_data()
    data["timing"]["steps"] = 40  # lost at 26, and lost it stays
    data["events"] = [{"kind": "vehicle_lost", "vehicle": 1, "at_step": 10}]
    data["algorithm"]["target_lost_after_s"] = 2.0
    result = simulate(validate_scenario(data))
    step_s = data["timing"]["step_s"]
    lost_at = 10 - 1 + round(2.0 / step_s) + 1  # last seen at 9; lost once 2 s have passed
    assert run_metrics(result)["target_lost_step"][0] == lost_at
    lost = result.target_status[0] == LOST
    assert lost[lost_at:].all() and not lost[:lost_at].any()


def test_sheared_and_translated_shapes_are_followed():
    data = scenario_data()
    data["algorithm"]["shape"] = {"shear_a": 0.3, "translate_north_m": 1.5}
    result = simulate(validate_scenario(data))
    # A translation moves the centroid off the target by exactly the translation.
    centroid = result.positions_m[0, -1].mean(axis=0)
    np.testing.assert_allclose(centroid - result.target_m[-1], [1.5, 0.0], atol=1e-3)


def simulable():
    """Bundled scenarios the numeric model can run (link, sensor and takeover events need a
    flight)."""
    names = []
    for path in sorted(CONFIGS.glob("*.yaml")):
        scenario = load_scenario(path)
        if not flight_only_events(scenario):
            names.append(path.stem)
    return names


# Every shipped scenario in full (about 0.5 s each): what CI checks; the fast lane has the claims.
@pytest.mark.slow
@pytest.mark.parametrize("name", simulable())
def test_every_scenario_meets_its_expectations(name):
    scenario = load_scenario(CONFIGS / f"{name}.yaml")
    metrics = {key: value[0] for key, value in run_metrics(simulate(scenario)).items()}
    assert scenario.expect, f"{name} has no expect: block"
    assert check_expectations(scenario.expect, metrics) == []

"""The UWB ranging model (:class:`mission_runner.sensors.UwbRanging`): one exchange read by both
ends, pair errors that last, NLOS in bursts, airtime; seeded and deterministic."""

import numpy as np
import pytest

from mission_runner.config import SensorConfig
from mission_runner.sensors import (
    SPEED_OF_LIGHT_M_S,
    UwbRanging,
    exchanges_per_step,
    range_schedule,
    ranging_plan,
)
from mission_runner.world import step_measurements

STEP_S = 0.1
#: Every error of the model on, at the figures docs/algorithm.md cites.
EVERYTHING = {
    "range_noise_std_m": 0.1,
    "range_bias_std_m": 0.05,
    "range_multipath_std_m": 0.05,
    "range_outlier_probability": 0.05,
    "range_dropout_probability": 0.02,
    "range_clock_offset_std_ppm": 2.0,
}
EVERYTHING_CLOCK = {"range_clock_offset_std_ppm": 2.0}


def distances(n, batch=(), seed=3):
    points = np.random.default_rng(seed).uniform(-5, 5, size=(*batch, n, 3))
    gaps = points[..., :, None, :] - points[..., None, :, :]
    return np.sqrt(np.sum(gaps * gaps, axis=-1))


def readings(sensors, true_m, steps, seed=0, batch=()):
    """``steps`` steps of ranges ``(steps, *batch, n, n)`` of a model seeded ``seed``."""
    n = true_m.shape[-1]
    model = UwbRanging(sensors, n, STEP_S, batch=batch)
    rng = np.random.default_rng(seed)
    return np.array([model.read(true_m, rng, k=k) for k in range(steps)])


def test_one_exchange_per_pair_gives_both_ends_the_same_number_at_every_step():
    true_m = distances(5)
    ranges = readings(SensorConfig(**EVERYTHING), true_m, 200)
    assert np.array_equal(ranges, np.swapaxes(ranges, -1, -2), equal_nan=True)
    off_diagonal = ~np.eye(5, dtype=bool)
    assert np.isfinite(ranges[:, off_diagonal]).mean() > 0.95  # read, not all dropped
    assert np.isnan(ranges[:, ~off_diagonal]).all()


def test_one_exchange_per_direction_has_its_own_noise_but_shares_the_pair_errors():
    true_m = distances(4)
    sensors = SensorConfig(
        **{**EVERYTHING, "range_clock_offset_std_ppm": 0.0},
        range_scheme="one_exchange_per_direction",
    )
    ranges = readings(sensors, true_m, 400)
    both = np.isfinite(ranges) & np.isfinite(np.swapaxes(ranges, -1, -2))
    difference = (ranges - np.swapaxes(ranges, -1, -2))[both]
    # Independent timestamp noise at each end: the difference has sqrt(2) x 0.1 m; the pair's
    # bias, multipath and NLOS cancel in it.
    assert 0.13 < np.std(difference) < 0.16
    errors = (ranges - true_m)[both]
    assert np.std(errors) > np.std(difference) / np.sqrt(2)  # the common part is there too
    clocked = sensors.model_copy(update={"range_noise_std_m": 0.0, **EVERYTHING_CLOCK})
    without_noise = readings(clocked, true_m, 50)
    clock = without_noise - np.swapaxes(without_noise, -1, -2)
    # Single-sided TWR's clock error flips sign with the initiator: 1/2 c t_reply (e_i - e_j).
    assert np.nanmax(np.abs(clock)) > 0.01


def test_a_pair_bias_is_constant_and_shared_by_both_ends():
    true_m = distances(6)
    ranges = readings(SensorConfig(range_bias_std_m=0.05), true_m, 50)
    error = ranges - true_m
    off_diagonal = ~np.eye(6, dtype=bool)
    assert np.all(error[:, off_diagonal] == error[0, off_diagonal])
    assert np.array_equal(error[0], error[0].T, equal_nan=True)
    many = readings(SensorConfig(range_bias_std_m=0.05), distances(60), 1)[0] - distances(60)
    assert 0.045 < np.nanstd(many[np.triu_indices(60, 1)]) < 0.055


def test_multipath_varies_slowly_with_its_correlation_time():
    sensors = SensorConfig(range_multipath_std_m=0.05, range_multipath_correlation_s=2.0)
    true_m = distances(30)
    error = (
        readings(sensors, true_m, 300)[:, *np.triu_indices(30, 1)] - true_m[np.triu_indices(30, 1)]
    )
    assert 0.045 < np.std(error) < 0.055
    lag_1 = np.mean(error[1:] * error[:-1]) / np.mean(error * error)
    assert lag_1 == pytest.approx(np.exp(-STEP_S / 2.0), abs=0.01)


def nlos_runs(in_nlos):
    """Lengths of the runs of True along the first axis, over every pair."""
    flat = in_nlos.reshape(in_nlos.shape[0], -1).T
    lengths = []
    for series in flat:
        edges = np.diff(np.concatenate([[0], series.astype(int), [0]]))
        lengths.extend(np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1))
    return np.array(lengths)


@pytest.mark.parametrize(("duration_s", "mean_steps"), [(2.0, 20.0), (0.0, 1 / 0.95)])
def test_nlos_comes_in_bursts_that_last_and_keep_one_bias(duration_s, mean_steps):
    sensors = SensorConfig(
        range_outlier_probability=0.05,
        range_outlier_bias_m=[0.3, 3.0],
        range_nlos_duration_s=duration_s,
    )
    true_m = distances(20)
    pairs = np.triu_indices(20, 1)
    error = readings(sensors, true_m, 2000)[:, *pairs] - true_m[pairs]
    in_nlos = error > 1e-9
    assert in_nlos.mean() == pytest.approx(0.05, rel=0.15)
    assert nlos_runs(in_nlos).mean() == pytest.approx(mean_steps, rel=0.15)
    if duration_s:  # within a burst, one bias
        lasting = in_nlos[1:] & in_nlos[:-1]
        assert np.array_equal(error[1:][lasting], error[:-1][lasting])


def test_single_sided_twr_reads_its_clock_offsets_through_the_reply_time():
    sensors = SensorConfig(range_clock_offset_std_ppm=2.0, range_reply_time_s=3e-4)
    true_m = distances(10, batch=(200,))
    error = readings(sensors, true_m, 1, batch=(200,))[0] - true_m
    # 1/2 c t_reply (e_i - e_j): std sqrt(2) x 2 ppm x 45 km = 0.127 m
    expected = 0.5 * SPEED_OF_LIGHT_M_S * 3e-4 * np.sqrt(2) * 2e-6
    assert np.std(error[:, *np.triu_indices(10, 1)]) == pytest.approx(expected, rel=0.1)


def test_the_model_is_seeded_deterministic_and_a_batch_entry_is_its_own():
    sensors = SensorConfig(**EVERYTHING)
    true_m = distances(4)
    first, again = readings(sensors, true_m, 30, seed=5), readings(sensors, true_m, 30, seed=5)
    assert np.array_equal(first, again, equal_nan=True)
    assert not np.array_equal(first, readings(sensors, true_m, 30, seed=6), equal_nan=True)


def test_a_noise_free_model_draws_nothing_and_reads_the_truth():
    class NoDraws:
        def normal(self, **_):
            raise AssertionError("drew")

        uniform = normal

    true_m = distances(4)
    model = UwbRanging(SensorConfig(), 4, STEP_S)
    for k in range(3):
        read = model.read(true_m, NoDraws(), k=k)
        assert np.array_equal(read, np.where(np.eye(4, dtype=bool), np.nan, true_m), equal_nan=True)


def test_a_skipped_step_still_ages_the_errors_and_steps_never_go_back():
    sensors = SensorConfig(range_multipath_std_m=0.05)
    true_m = distances(3)
    stepped = readings(sensors, true_m, 5)[4]
    model = UwbRanging(sensors, 3, STEP_S)
    rng = np.random.default_rng(0)
    model.read(true_m, rng, k=0)
    assert np.array_equal(model.read(true_m, rng, k=4), stepped, equal_nan=True)
    with pytest.raises(ValueError, match="went back"):
        model.read(true_m, rng, k=3)


def test_a_pair_not_measured_at_one_end_is_not_ranged_in_one_exchange_per_pair():
    measured = ~np.eye(3, dtype=bool)
    measured[0, 1] = False
    model = UwbRanging(SensorConfig(), 3, STEP_S)
    read = model.read(distances(3), np.random.default_rng(0), k=0, measured=measured)
    assert np.isnan(read[0, 1]) and np.isnan(read[1, 0]) and np.isfinite(read[0, 2])


@pytest.mark.parametrize(
    ("scheme", "slots"), [("one_exchange_per_pair", 28), ("one_exchange_per_direction", 56)]
)
def test_airtime_ranges_the_pairs_in_turn(scheme, slots):
    """8 vehicles, 10 ms exchanges, 0.1 s steps: 10 exchanges a step for 28 pairs (56
    directions), so each pair is ranged every 3 (6) steps, exactly once a round."""
    sensors = SensorConfig(range_scheme=scheme, range_exchange_s=0.01)
    assert exchanges_per_step(sensors, STEP_S) == 10
    carried = np.array([range_schedule(8, sensors, STEP_S, k) for k in range(slots)])
    per_step = carried.sum(axis=(1, 2))
    assert np.all(per_step == (20 if scheme == "one_exchange_per_pair" else 10))
    assert np.all(carried.sum(axis=0)[~np.eye(8, dtype=bool)] == 10)
    unlimited = SensorConfig(range_scheme=scheme)
    assert range_schedule(8, unlimited, STEP_S, 3).sum() == 56


def test_airtime_bounds_what_the_model_reads():
    sensors = SensorConfig(range_exchange_s=0.01)
    model = UwbRanging(sensors, 8, STEP_S)
    read = model.read(distances(8), np.random.default_rng(0), k=0)
    assert np.isfinite(read).sum() == 20


def test_the_emulated_world_publishes_one_number_for_both_ends_of_a_pair():
    from mission_runner.bus import RangeSet, Topics

    sensors = SensorConfig(**EVERYTHING)
    positions = np.random.default_rng(1).uniform(-5, 5, size=(4, 3))
    uwb = UwbRanging(sensors, 4, STEP_S)
    rng = np.random.default_rng(2)
    for k in range(20):
        measured = step_measurements(
            k,
            k * STEP_S,
            ids=[1, 2, 3, 4],
            topics=Topics("unit"),
            positions_m=positions,
            ranging=np.ones(4, dtype=bool),
            tracking=np.zeros(4, dtype=bool),
            target_m=[0.0, 0.0],
            target_velocity_m_s=[0.0, 0.0],
            sensors=sensors,
            rng=rng,
            uwb=uwb,
        )
        ranges = {
            (m.vehicle_id, peer): range_m
            for _, m in measured
            if isinstance(m, RangeSet)
            for peer, range_m in m.ranges_m
        }
        assert ranges
        assert all(ranges.get((j, i)) == value for (i, j), value in ranges.items())


def test_a_step_must_carry_at_least_one_exchange():
    from mission_runner.checks import validate_scenario
    from mission_runner.errors import ConfigError
    from tests.test_config import base

    data = base()
    data["sensors"] = {"range_exchange_s": data["timing"]["step_s"] * 2}
    with pytest.raises(ConfigError) as caught:
        validate_scenario(data, source="test.yaml")
    assert [where for where, _ in caught.value.problems] == ["sensors.range_exchange_s"]


def test_the_ranging_plan_says_how_often_a_pair_is_ranged():
    airtime = SensorConfig(range_exchange_s=0.01)
    assert ranging_plan(8, airtime, STEP_S).endswith(
        "28 exchanges a round, 10 a step (sensors.range_exchange_s 0.01 s): each pair every "
        "2.8 steps on average, at most 3 (0.3 s)"
    )
    assert ranging_plan(4, SensorConfig(), STEP_S).endswith("every pair every step")

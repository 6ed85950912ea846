"""GPS/EKF position error: the Gauss-Markov model's statistics, what the vehicles report with it
(GLOBAL_POSITION_INT and GPS_RAW_INT agree), and pairwise range errors like real SIH's."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest
from pydantic import ValidationError
from pymavlink.dialects.v20 import common as mavlink

from sitl import Clock, Emulator, EmulatorConfig, Truth
from sitl.config import ClockConfig, GpsErrorConfig, PhysicsConfig, PlacementConfig
from sitl.geo import MapProjection
from sitl.gnss import GnssError
from sitl.telemetry import MSG_GLOBAL_POSITION_INT, MSG_GPS_RAW_INT
from tests.sitl.helpers import Bench, RawClient, free_port_config

REQUEST_MESSAGE = 512


def pairwise_range_errors(
    true_ned_m: npt.NDArray[np.float64], reported_ned_m: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """Range between every pair from reported positions minus the true range, (n (n-1) / 2,)."""
    i, j = np.triu_indices(true_ned_m.shape[0], 1)
    true_range = np.linalg.norm(true_ned_m[i] - true_ned_m[j], axis=1)
    return np.linalg.norm(reported_ned_m[i] - reported_ned_m[j], axis=1) - true_range


def model_pairwise_p95_m(bias_std_m: float, noise_std_m: float) -> float:
    """95th percentile of a pair's range error: the difference of two independent errors,
    projected on the baseline, is normal with variance 2 (bias^2 + noise^2)."""
    return 1.6449 * math.sqrt(2.0 * (bias_std_m**2 + noise_std_m**2))


# ------------------------------------------------------------------ the model alone
def test_gauss_markov_bias_and_noise_have_the_configured_statistics() -> None:
    bias_std, tau, noise_std, dt = 0.25, 20.0, 0.05, 0.1
    model = GnssError(
        400,
        bias_std_m=bias_std,
        bias_time_constant_s=tau,
        noise_std_m=noise_std,
        rng=np.random.default_rng(3),
    )
    biases, errors = [], []
    for step in range(3000):  # 300 s, 15 correlation times
        model.step(dt)
        if step % 10 == 9:
            biases.append(model.bias_ned_m.copy())
            errors.append(model.error_ned_m.copy())
    bias = np.array(biases)  # (300, 400, 3), one sample per second
    white = np.array(errors) - bias
    assert bias.std() == pytest.approx(bias_std, rel=0.05)
    assert abs(bias.mean()) < 0.02
    assert white.std() == pytest.approx(noise_std, rel=0.02)
    lag = round(tau)  # samples are 1 s apart
    correlation = (bias[lag:] * bias[:-lag]).mean() / (bias * bias).mean()
    assert correlation == pytest.approx(math.exp(-1.0), abs=0.04)
    # The white part is white.
    assert abs((white[1:] * white[:-1]).mean()) / white.var() < 0.02

    positions = np.array([[40.0 * k, 0.0, 0.0] for k in range(400)])
    ranges = np.concatenate(
        [pairwise_range_errors(positions, positions + e) for e in np.array(errors)[::10]]
    )
    p95 = model_pairwise_p95_m(bias_std, noise_std)
    assert np.percentile(ranges, 5) == pytest.approx(-p95, rel=0.05)
    assert np.percentile(ranges, 95) == pytest.approx(p95, rel=0.05)


def test_the_bias_starts_stationary_and_the_step_size_does_not_matter() -> None:
    def model(seed: int) -> GnssError:
        return GnssError(
            20000, bias_std_m=0.3, bias_time_constant_s=10.0, rng=np.random.default_rng(seed)
        )

    coarse, fine = model(1), model(2)
    start_coarse, start_fine = coarse.bias_ned_m.copy(), fine.bias_ned_m.copy()
    coarse.step(5.0)
    for _ in range(1000):
        fine.step(0.005)
    for stepped, start in ((coarse, start_coarse), (fine, start_fine)):
        assert stepped.bias_ned_m.std() == pytest.approx(0.3, rel=0.02)
        correlation = (stepped.bias_ned_m * start).mean() / (start * start).mean()
        assert correlation == pytest.approx(math.exp(-0.5), abs=0.02)


def test_no_error_by_default_and_seeded_otherwise() -> None:
    off = GnssError(3)
    off.step(0.02)
    assert not off.active and not off.error_ned_m.any()
    runs = []
    for _ in range(2):
        model = GnssError(3, bias_std_m=0.2, noise_std_m=0.1, rng=np.random.default_rng([5, 1]))
        for _ in range(10):
            model.step(0.02)
        runs.append(model.error_ned_m.copy())
    assert np.array_equal(runs[0], runs[1])
    with pytest.raises(ValidationError):
        GpsErrorConfig(bias_time_constant_s=0.0)
    assert not EmulatorConfig().gps_error.active


# ------------------------------------------------------------------ what a vehicle reports
def _decode_ned(
    projection: MapProjection, lat_e7: int, lon_e7: int, alt_mm: int, ground_amsl_m: float
) -> npt.NDArray[np.float64]:
    north, east = projection.to_local(lat_e7 * 1e-7, lon_e7 * 1e-7)
    return np.array([north, east, ground_amsl_m - alt_mm * 1e-3])


def test_reported_positions_carry_the_error_and_the_truth_does_not() -> None:
    gnss = GnssError(2, bias_std_m=1.0, noise_std_m=0.2, rng=np.random.default_rng(9))
    bench = Bench(2, gnss=gnss)
    bench.run(1.0)
    for i, ap in enumerate(bench.autopilots):
        gpos = ap.telemetry.global_position_int(bench.t)
        raw = ap.telemetry.gps_raw_int(bench.t)
        assert (gpos.lat, gpos.lon, gpos.alt) == (raw.lat, raw.lon, raw.alt)
        reported = _decode_ned(bench.projection, gpos.lat, gpos.lon, gpos.alt, 488.0)
        truth = bench.physics.position_ned_m[i]
        assert reported - truth == pytest.approx(gnss.error_ned_m[i], abs=0.012)
        assert gpos.relative_alt == round(-gnss.error_ned_m[i, 2] * 1000)
        # Control and home use the truth: the vehicle does not drift on the ground.
        assert list(truth) == [0.0, 5.0 * i, 0.0]
        assert ap.true_global_position() != ap.global_position()


@pytest.mark.slow  # 200 s of 8 vehicles for error statistics
@pytest.mark.asyncio
async def test_emulated_vehicles_pairwise_range_errors_match_the_configured_model() -> None:
    """SIH-like numbers: 8 vehicles 20 m apart on the ground for 200 s, reported positions
    sampled every 0.5 s from the GLOBAL_POSITION_INT each vehicle sends."""
    n, bias_std, noise_std = 8, 0.25, 0.05
    cfg = EmulatorConfig(
        vehicles=n,
        seed=11,
        ports=free_port_config(n, gcs=False),
        clock=ClockConfig(mode="lockstep"),
        physics=PhysicsConfig(rate_hz=20.0),
        placement=PlacementConfig(grid_spacing_m=20.0, grid_columns=3),
        gps_error=GpsErrorConfig(
            bias_std_m=bias_std, bias_time_constant_s=5.0, noise_std_m=noise_std
        ),
    )
    samples: list[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]] = []
    mismatches: list[str] = []

    async with Emulator(cfg) as emulator:
        projection, ground = emulator.projection, cfg.home.altitude_amsl_m

        def sample(time_s: float, truth: Truth) -> None:
            if round(time_s / emulator.dt_s) % 10:
                return
            reported = np.empty((n, 3))
            for i in range(n):
                build = emulator.autopilot(i).telemetry.build
                gpos, raw = build(MSG_GLOBAL_POSITION_INT, time_s), build(MSG_GPS_RAW_INT, time_s)
                assert gpos is not None and raw is not None
                if (gpos.lat, gpos.lon, gpos.alt) != (raw.lat, raw.lon, raw.alt):
                    mismatches.append(f"vehicle {i} at {time_s:.2f} s")
                reported[i] = _decode_ned(projection, gpos.lat, gpos.lon, gpos.alt, ground)
            error = reported - truth.position_ned_m
            if not np.allclose(error, truth.gps_error_ned_m, atol=0.012):
                mismatches.append(f"error != truth.gps_error_ned_m at {time_s:.2f} s")
            samples.append((truth.position_ned_m.copy(), reported))

        emulator.add_step_listener(sample)
        await emulator.run_for(200.0, timeout_s=60.0)
        start = emulator.truth.position_ned_m.copy()
    assert mismatches == []
    assert len(samples) == 400
    # The truth never moved: vehicles on the ground fly on their true positions.
    assert all(np.array_equal(true, start) for true, _ in samples)
    ranges = np.concatenate([pairwise_range_errors(t, r) for t, r in samples])
    p95 = model_pairwise_p95_m(bias_std, noise_std)
    # Tolerances: about 3.5 standard deviations of these percentiles over seeds.
    assert np.percentile(ranges, 5) == pytest.approx(-p95, rel=0.25)
    assert np.percentile(ranges, 95) == pytest.approx(p95, rel=0.25)
    assert ranges.std() == pytest.approx(p95 / 1.6449, rel=0.12)


@pytest.mark.asyncio
async def test_global_position_and_gps_raw_agree_on_the_wire() -> None:
    cfg = EmulatorConfig(
        vehicles=1,
        ports=free_port_config(1, gcs=False),
        clock=ClockConfig(mode="lockstep"),
        gps_error=GpsErrorConfig(bias_std_m=2.0, noise_std_m=0.5),
    )
    clock = Clock("lockstep")
    clock.register("test")
    async with (
        Emulator(cfg, clock=clock) as emulator,
        RawClient(cfg.ports.api_remote_port(0)) as client,
    ):
        with client.matching(lambda m: m.get_type() == "HEARTBEAT") as heartbeat:
            clock.acted("test", 2.0)
            await clock.sleep_until(2.0)
            await heartbeat
        replies = {}

        # Streamed copies from earlier steps may still arrive: take the ones of this step.
        def gpos_now(m: mavlink.MAVLink_message) -> bool:
            return m.get_type() == "GLOBAL_POSITION_INT" and m.time_boot_ms == 2000

        def raw_now(m: mavlink.MAVLink_message) -> bool:
            return m.get_type() == "GPS_RAW_INT" and m.time_usec == 2_000_000

        for msg_id, kind, now in (
            (MSG_GLOBAL_POSITION_INT, "GLOBAL_POSITION_INT", gpos_now),
            (MSG_GPS_RAW_INT, "GPS_RAW_INT", raw_now),
        ):
            with client.matching(now) as reply:
                assert await client.command(1, REQUEST_MESSAGE, msg_id) == 0
                replies[kind] = await reply
        error = emulator.truth.gps_error_ned_m[0].copy()
        true = emulator.truth.global_position(0)
    gpos, raw = replies["GLOBAL_POSITION_INT"], replies["GPS_RAW_INT"]
    assert (gpos.lat, gpos.lon, gpos.alt) == (raw.lat, raw.lon, raw.alt)
    reported = _decode_ned(emulator.projection, gpos.lat, gpos.lon, gpos.alt, 488.0)
    assert reported == pytest.approx(error, abs=0.012)  # the vehicle stands at the origin
    assert np.linalg.norm(error) > 0.1
    assert true == pytest.approx((cfg.home.latitude_deg, cfg.home.longitude_deg, 488.0))

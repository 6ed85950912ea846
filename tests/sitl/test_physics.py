"""Kinematic multicopter model: tracking, limits, ground, wind, vectorisation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl import physics as ph


def flying(n: int = 1, altitude_m: float = 10.0) -> ph.MulticopterPhysics:
    start = np.zeros((n, 3))
    start[:, 1] = np.arange(n) * 10.0
    start[:, 2] = -altitude_m
    model = ph.MulticopterPhysics(start)
    model.control_mode[:] = ph.VELOCITY
    return model


def run(model: ph.MulticopterPhysics, seconds: float, dt: float = 0.02) -> None:
    for _ in range(round(seconds / dt)):
        model.step(dt)


def test_velocity_setpoint_is_reached_and_distance_matches() -> None:
    model = flying()
    model.velocity_setpoint_ned_m_s[0] = (2.0, -1.0, 0.0)
    run(model, 10.0)
    np.testing.assert_allclose(model.velocity_ned_m_s[0], (2.0, -1.0, 0.0), atol=1e-6)
    # 10 s at 2 m/s minus the ramp-up (accel-limited, ~0.7 s at 3 m/s^2 plus lag).
    assert 18.5 < model.position_ned_m[0, 0] < 20.0
    assert model.position_ned_m[0, 2] == pytest.approx(-10.0)


def test_speed_limits_apply_horizontally_and_vertically() -> None:
    model = flying()
    model.velocity_setpoint_ned_m_s[0] = (30.0, 30.0, -20.0)
    run(model, 10.0)
    v = model.velocity_ned_m_s[0]
    assert math.hypot(v[0], v[1]) == pytest.approx(12.0, abs=1e-6)
    assert v[2] == pytest.approx(-3.0, abs=1e-6)
    model.velocity_setpoint_ned_m_s[0] = (0.0, 0.0, 20.0)
    run(model, 5.0)
    assert model.velocity_ned_m_s[0, 2] == pytest.approx(1.5, abs=1e-6)


def test_acceleration_is_limited() -> None:
    model = flying()
    model.velocity_setpoint_ned_m_s[0] = (10.0, 0.0, 0.0)
    previous = 0.0
    for _ in range(50):
        model.step(0.02)
        v = model.velocity_ned_m_s[0, 0]
        assert (v - previous) / 0.02 <= 3.0 + 1e-9
        previous = v


def test_position_mode_arrives_without_large_overshoot() -> None:
    model = flying()
    model.control_mode[0] = ph.POSITION
    model.position_setpoint_ned_m[0] = (30.0, 40.0, -20.0)
    max_north = -math.inf
    for _ in range(3000):
        model.step(0.02)
        max_north = max(max_north, model.position_ned_m[0, 0])
    np.testing.assert_allclose(model.position_ned_m[0], (30.0, 40.0, -20.0), atol=0.05)
    assert max_north < 30.0 + 0.5
    # Cruise speed bounds the horizontal speed in position mode.
    model.position_setpoint_ned_m[0] = (500.0, 40.0, -20.0)
    run(model, 20.0)
    assert math.hypot(*model.velocity_ned_m_s[0, :2]) == pytest.approx(5.0, abs=0.01)


def test_ground_stops_descent_and_skids_do_not_slide() -> None:
    model = flying(altitude_m=1.0)
    model.velocity_setpoint_ned_m_s[0] = (3.0, 0.0, 1.0)
    run(model, 5.0)
    assert model.position_ned_m[0, 2] == 0.0
    assert np.all(model.velocity_ned_m_s[0] == 0.0)
    x = model.position_ned_m[0, 0]
    run(model, 2.0)
    assert model.position_ned_m[0, 0] == x
    assert model.on_ground()[0]


def test_climb_command_frees_a_grounded_vehicle() -> None:
    model = flying(altitude_m=0.0)
    model.velocity_setpoint_ned_m_s[0] = (0.0, 0.0, -1.0)
    run(model, 3.0)
    assert model.position_ned_m[0, 2] < -2.0


def test_motors_off_falls_and_stops_on_ground() -> None:
    model = flying(altitude_m=20.0)
    model.control_mode[0] = ph.MOTORS_OFF
    run(model, 1.0)
    assert model.position_ned_m[0, 2] == pytest.approx(-20.0 + 0.5 * ph.GRAVITY_M_S2, abs=0.2)
    run(model, 5.0)
    assert model.position_ned_m[0, 2] == 0.0
    assert model.roll_rad[0] == 0.0 and model.pitch_rad[0] == 0.0


def test_yaw_turns_at_the_rate_limit_towards_the_setpoint() -> None:
    model = flying()
    model.yaw_setpoint_rad[0] = math.radians(90.0)
    model.step(1.0)
    assert math.degrees(model.yaw_rad[0]) == pytest.approx(45.0)
    run(model, 3.0)
    assert math.degrees(model.yaw_rad[0]) == pytest.approx(90.0, abs=0.5)
    before = math.degrees(model.yaw_rad[0])
    model.yaw_setpoint_rad[0] = math.nan
    model.yaw_rate_setpoint_rad_s[0] = math.radians(-10.0)
    run(model, 1.0)
    assert math.degrees(model.yaw_rad[0]) == pytest.approx(before - 10.0, abs=1e-6)


def test_tilt_follows_acceleration_in_body_frame() -> None:
    model = flying()
    model.yaw_rad[0] = math.pi / 2  # facing east
    model.velocity_setpoint_ned_m_s[0] = (0.0, 10.0, 0.0)  # accelerate forward
    model.step(0.02)
    assert model.pitch_rad[0] < -0.2  # nose down
    assert abs(model.roll_rad[0]) < 1e-9


def test_vehicles_are_independent() -> None:
    model = flying(3)
    model.velocity_setpoint_ned_m_s[:] = [(1, 0, 0), (0, 2, 0), (0, 0, -1)]
    run(model, 5.0)
    np.testing.assert_allclose(
        model.velocity_ned_m_s, [(1, 0, 0), (0, 2, 0), (0, 0, -1)], atol=1e-6
    )


def test_gusts_push_and_are_reproducible_with_a_seed() -> None:
    def trajectory(seed: int) -> np.ndarray:
        wind = ph.Wind(2, (3.0, 0.0, 0.0), 1.5, 2.0, rng=np.random.default_rng(seed))
        model = ph.MulticopterPhysics(np.array([[0, 0, -10.0], [0, 10, -10.0]]), wind=wind)
        model.control_mode[:] = ph.POSITION
        model.position_setpoint_ned_m[:] = model.position_ned_m
        out = []
        for _ in range(500):
            model.step(0.02)
            out.append(model.position_ned_m.copy())
        return np.array(out)

    a, b, c = trajectory(1), trajectory(1), trajectory(2)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    displacement = np.abs(a[:, :, :2] - a[0, :, :2])
    assert displacement.max() > 0.01  # the gusts moved the vehicles...
    assert displacement.max() < 5.0  # ...but the controller held them near


def test_bad_dt_is_refused() -> None:
    with pytest.raises(ValueError, match="dt"):
        flying().step(0.0)


@pytest.mark.parametrize("tilt_s", [0.0, 0.2])
def test_the_lags_move_alike_at_any_physics_rate(tilt_s: float) -> None:
    """A small velocity step (no limit binds) seen at the same instants with a 2.5 ms and a
    25 ms step: the velocity and tilt lags are discretised exactly, so only the position's
    integration differs (O(dt)); the forward-Euler lag was 12 % off after one 25 ms step."""
    runs = []
    for dt in (0.0025, 0.025):
        model = flying()
        model.time_constant_s = 0.1
        model.tilt_time_constant_s = tilt_s
        model.velocity_setpoint_ned_m_s[0] = (0.2, 0.0, 0.0)
        seen = []
        for _ in range(8):
            run(model, 0.025, dt)
            seen.append(model.velocity_ned_m_s[0, 0])
        runs.append(np.array(seen))
    fine, coarse = runs
    tolerance = 1e-9 if tilt_s == 0.0 else 0.02 * 0.2  # the tilt lag feeds the velocity's
    np.testing.assert_allclose(coarse, fine, atol=tolerance)
    assert fine[-1] > 0.1

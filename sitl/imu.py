"""What the inertial sensors, the magnetometer and the barometer of a kinematic vehicle read.

The physics (:mod:`sitl.physics`) gives each vehicle a NED acceleration, ZYX Euler angles and
their rates; an IMU strapped to the body measures the specific force (acceleration minus
gravity) and the body angular rates in the body frame FRD, a magnetometer the earth's field in
that frame, a barometer the static pressure at its altitude. These pure functions turn one into
the other for HIGHRES_IMU and SCALED_IMU (:mod:`sitl.telemetry`). There is no sensor noise: the
readings are as exact as the rest of the emulated state.

Frames: NED is the local north-east-down frame, FRD the body frame (forward, right, down); a
vehicle at rest reads a specific force of (0, 0, -g) in FRD.
"""

from __future__ import annotations

import math

GRAVITY_M_S2 = 9.80665
#: Equatorial field strength of an axial dipole that matches the earth's field to ~20 %, gauss.
_DIPOLE_FIELD_GAUSS = 0.31
#: International Standard Atmosphere at sea level.
_SEA_LEVEL_PRESSURE_HPA = 1013.25
_TEMPERATURE_LAPSE_K_M = 0.0065
_SEA_LEVEL_TEMPERATURE_K = 288.15
_BAROMETRIC_EXPONENT = 5.25588  # g M / (R L)

Vector3 = tuple[float, float, float]


def ned_to_frd(vector_ned: Vector3, roll_rad: float, pitch_rad: float, yaw_rad: float) -> Vector3:
    """``vector_ned`` in the body frame of a vehicle with ZYX Euler angles (roll, pitch, yaw)."""
    n, e, d = vector_ned
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    sp, cp = math.sin(pitch_rad), math.cos(pitch_rad)
    sy, cy = math.sin(yaw_rad), math.cos(yaw_rad)
    # Transpose of the body-to-NED rotation R_z(yaw) R_y(pitch) R_x(roll).
    forward = cp * cy * n + cp * sy * e - sp * d
    right = (sr * sp * cy - cr * sy) * n + (sr * sp * sy + cr * cy) * e + sr * cp * d
    down = (cr * sp * cy + sr * sy) * n + (cr * sp * sy - sr * cy) * e + cr * cp * d
    return forward, right, down


def specific_force_frd(
    acceleration_ned_m_s2: Vector3, roll_rad: float, pitch_rad: float, yaw_rad: float
) -> Vector3:
    """What an accelerometer reads, m/s^2 FRD: the acceleration minus gravity, in the body."""
    an, ae, ad = acceleration_ned_m_s2
    return ned_to_frd((an, ae, ad - GRAVITY_M_S2), roll_rad, pitch_rad, yaw_rad)


def body_rates_frd(
    roll_rad: float,
    pitch_rad: float,
    roll_rate_rad_s: float,
    pitch_rate_rad_s: float,
    yaw_rate_rad_s: float,
) -> Vector3:
    """What a gyroscope reads, rad/s FRD (p, q, r), from the ZYX Euler angle rates."""
    sr, cr = math.sin(roll_rad), math.cos(roll_rad)
    sp, cp = math.sin(pitch_rad), math.cos(pitch_rad)
    p = roll_rate_rad_s - yaw_rate_rad_s * sp
    q = pitch_rate_rad_s * cr + yaw_rate_rad_s * sr * cp
    r = -pitch_rate_rad_s * sr + yaw_rate_rad_s * cr * cp
    return p, q, r


def earth_field_ned_gauss(latitude_deg: float) -> Vector3:
    """The earth's magnetic field at ``latitude_deg`` as an axial dipole, gauss NED (no
    declination). At PX4 SITL's default home (47.4 deg N) it is (0.21, 0, 0.46); PX4 SIH's
    world magnetic model reads about (0.21, 0.01, 0.44) there."""
    lat = math.radians(latitude_deg)
    return (
        _DIPOLE_FIELD_GAUSS * math.cos(lat),
        0.0,
        2.0 * _DIPOLE_FIELD_GAUSS * math.sin(lat),
    )


def static_pressure_hpa(altitude_amsl_m: float) -> float:
    """International Standard Atmosphere pressure at ``altitude_amsl_m`` (troposphere), hPa."""
    ratio = 1.0 - _TEMPERATURE_LAPSE_K_M * altitude_amsl_m / _SEA_LEVEL_TEMPERATURE_K
    pressure_hpa: float = _SEA_LEVEL_PRESSURE_HPA * max(ratio, 0.0) ** _BAROMETRIC_EXPONENT
    return pressure_hpa

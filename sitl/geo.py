"""Local NED metres <-> WGS84 degrees, with PX4's azimuthal equidistant projection.

PX4 converts between its local frame and latitude/longitude with this projection
(``lib/geo`` ``MapProjection``); using the same one keeps the emulator's GLOBAL_POSITION_INT,
HOME_POSITION and mission coordinates consistent with what a PX4 client expects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

EARTH_RADIUS_M = 6371000.0


@dataclass(frozen=True, slots=True)
class MapProjection:
    """Projection around a reference point (degrees)."""

    ref_latitude_deg: float
    ref_longitude_deg: float

    def to_global(self, north_m: float, east_m: float) -> tuple[float, float]:
        """(north, east) metres -> (latitude, longitude) degrees."""
        lat0 = math.radians(self.ref_latitude_deg)
        lon0 = math.radians(self.ref_longitude_deg)
        x_rad = north_m / EARTH_RADIUS_M
        y_rad = east_m / EARTH_RADIUS_M
        c = math.hypot(x_rad, y_rad)
        if c < 1e-15:
            return self.ref_latitude_deg, self.ref_longitude_deg
        sin_c, cos_c = math.sin(c), math.cos(c)
        sin_lat0, cos_lat0 = math.sin(lat0), math.cos(lat0)
        lat = math.asin(cos_c * sin_lat0 + x_rad * sin_c * cos_lat0 / c)
        lon = lon0 + math.atan2(y_rad * sin_c, c * cos_lat0 * cos_c - x_rad * sin_lat0 * sin_c)
        return math.degrees(lat), math.degrees(lon)

    def to_local(self, latitude_deg: float, longitude_deg: float) -> tuple[float, float]:
        """(latitude, longitude) degrees -> (north, east) metres."""
        lat0 = math.radians(self.ref_latitude_deg)
        lon0 = math.radians(self.ref_longitude_deg)
        lat = math.radians(latitude_deg)
        d_lon = math.radians(longitude_deg) - lon0
        sin_lat, cos_lat = math.sin(lat), math.cos(lat)
        sin_lat0, cos_lat0 = math.sin(lat0), math.cos(lat0)
        cos_d_lon = math.cos(d_lon)
        arg = min(max(sin_lat0 * sin_lat + cos_lat0 * cos_lat * cos_d_lon, -1.0), 1.0)
        c = math.acos(arg)
        k = 1.0 if abs(c) < 1e-12 else c / math.sin(c)
        north = k * (cos_lat0 * sin_lat - sin_lat0 * cos_lat * cos_d_lon) * EARTH_RADIUS_M
        east = k * cos_lat * math.sin(d_lon) * EARTH_RADIUS_M
        return north, east

"""Settings of the vehicle emulator, as pydantic models.

:class:`EmulatorConfig` is self-contained so that a scenario file can embed it as one section;
validation errors are pydantic ``ValidationError`` s whose ``loc`` is the path inside this model
(the scenario loader prefixes its own section name). Every field has a title and a description;
units are in the field names.

Speed and acceleration limits, take-off/return altitudes and failsafe settings are PX4
parameters (``params``), with PX4's names and ranges, because clients read and write them with the
parameter protocol at run time.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator

from sitl.params import validate_overrides
from sitl.signing import key_from_passphrase

MAX_VEHICLES = 250
"""System ids are index + 1 and PX4's MAV_SYS_ID stops at 250 for vehicles."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class PortsConfig(_Model):
    """UDP port layout. For up to 10 vehicles the defaults are PX4 SITL's (instance i: API link
    binds 14580+i and sends to 14540+i, GCS link binds 18570+i and sends to 14550).

    Beyond 10 vehicles PX4 sends every API link to 14549; here (unless ``px4_compat_ports``)
    every vehicle keeps its own client port, counting up from 14540 and skipping the GCS port:
    vehicle 10 uses 14551, vehicle 49 uses 14590. The vehicles' own API ports then move past
    the client ports if 14580+i would collide with them.
    """

    bind_host: str = Field(
        "0.0.0.0",
        title="Bind address",
        description="Local address the vehicles' UDP endpoints bind to.",
    )
    remote_host: str = Field(
        "127.0.0.1",
        title="Client address",
        description="Address telemetry goes to until a client has sent a valid MAVLink packet; "
        "after that the vehicle answers the first client it heard from, like PX4.",
    )
    api_local_base: int | None = Field(
        None,
        ge=1,
        le=65535,
        title="API link local port base",
        description="Vehicle i binds api_local_base + i for its API/offboard link. None: "
        "api_remote_base + 40 (PX4: 14580), or the first port after the client ports if "
        "that would overlap them (more than 39 vehicles).",
    )
    api_remote_base: int = Field(
        14540,
        ge=1,
        le=65535,
        title="API link client port base",
        description="Vehicle i sends API telemetry to api_remote_base + i (skipping "
        "gcs_remote_port); a MAVSDK client listens there with udpin://0.0.0.0:<port> "
        "(PX4: 14540).",
    )
    px4_compat_ports: bool = Field(
        False,
        title="PX4 client port sharing",
        description="If true, vehicles with index > 9 all send to api_remote_base + 9 like PX4 "
        "SITL does (clients must then tell vehicles apart by system id). If false every "
        "vehicle gets its own client port, which works for any number of vehicles.",
    )
    gcs_enabled: bool = Field(
        True,
        title="GCS link enabled",
        description="Open the second link for QGroundControl/MAVProxy on every vehicle.",
    )
    gcs_local_base: int = Field(
        18570,
        ge=1,
        le=65535,
        title="GCS link local port base",
        description="Vehicle i binds gcs_local_base + i for its GCS link (PX4: 18570).",
    )
    gcs_remote_port: int = Field(
        14550,
        ge=1,
        le=65535,
        title="GCS port",
        description="Port every vehicle's GCS link sends to (QGroundControl listens on 14550).",
    )

    def api_remote_port(self, index: int) -> int:
        """Client port of vehicle ``index``'s API link."""
        if self.px4_compat_ports:
            return self.api_remote_base + min(index, 9)
        port = self.api_remote_base + index
        # A GCS listens on gcs_remote_port: an API client cannot share it.
        if self.api_remote_base <= self.gcs_remote_port <= port:
            port += 1
        return port

    def resolved_api_local_base(self, vehicles: int) -> int:
        """First API bind port for ``vehicles`` vehicles (see ``api_local_base``)."""
        if self.api_local_base is not None:
            return self.api_local_base
        base = self.api_remote_base + 40
        last_client = self.api_remote_port(vehicles - 1)
        if base <= last_client and self.api_remote_base < base + vehicles:
            base = last_client + 1
        return base

    def api_local_port(self, index: int, vehicles: int) -> int:
        return self.resolved_api_local_base(vehicles) + index

    def gcs_local_port(self, index: int) -> int:
        return self.gcs_local_base + index

    @classmethod
    def free(cls, vehicles: int, *, gcs: bool = True, **overrides: Any) -> PortsConfig:
        """A layout whose every port (the vehicles' and their clients') is free right now, for
        running beside PX4 SITL or another emulator (``ports: auto``). Raises OSError if no
        free range is found."""
        rng = random.Random()
        for _ in range(200):
            api_remote = rng.randrange(20000, 60000 - 4 * (vehicles + 10), 10)
            api_local = api_remote + vehicles + 5
            gcs_local = api_local + vehicles + 5
            gcs_remote = gcs_local + vehicles + 5
            ports = [*range(api_remote, api_remote + vehicles)]
            ports += range(api_local, api_local + vehicles)
            if gcs:
                ports += [*range(gcs_local, gcs_local + vehicles), gcs_remote]
            if all(udp_port_free(port) for port in ports):
                return cls(
                    api_remote_base=api_remote,
                    api_local_base=api_local,
                    gcs_local_base=gcs_local,
                    gcs_remote_port=gcs_remote,
                    gcs_enabled=gcs,
                    **overrides,
                )
        raise OSError(f"no free range of UDP ports for {vehicles} vehicle(s)")


def udp_port_free(port: int) -> bool:
    """Whether a UDP socket can bind ``port`` on every address now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


class HomeConfig(_Model):
    """Geographic origin of the emulated world (PX4 SITL's default is Zurich Irchel park)."""

    latitude_deg: float = Field(
        47.397742, ge=-89.0, le=89.0, title="Latitude", description="Latitude of the origin, deg."
    )
    longitude_deg: float = Field(
        8.545594,
        ge=-180.0,
        le=180.0,
        title="Longitude",
        description="Longitude of the origin, deg.",
    )
    altitude_amsl_m: float = Field(
        488.0,
        ge=-500.0,
        le=9000.0,
        title="Ground altitude",
        description="Altitude of the (flat) ground above mean sea level, m.",
    )


class InitialPosition(_Model):
    """Where one vehicle starts, relative to the world origin (on the ground)."""

    north_m: float = Field(0.0, ge=-1e5, le=1e5, title="North", description="North offset, m.")
    east_m: float = Field(0.0, ge=-1e5, le=1e5, title="East", description="East offset, m.")
    yaw_deg: float = Field(
        0.0, ge=-360.0, le=360.0, title="Heading", description="Initial heading, deg from north."
    )


class PlacementConfig(_Model):
    """Initial positions: explicit ones first, the remaining vehicles on a grid."""

    positions: list[InitialPosition] = Field(
        default_factory=list,
        title="Explicit start positions",
        description="Start position of vehicle 0, 1, ...; vehicles beyond the list go on the grid.",
    )
    grid_spacing_m: float = Field(
        3.0,
        gt=0.0,
        le=1000.0,
        title="Grid spacing",
        description="Distance between neighbouring vehicles on the start grid, m.",
    )
    grid_columns: int = Field(
        10,
        ge=1,
        le=MAX_VEHICLES,
        title="Grid columns",
        description="Vehicles per grid row (rows go north, columns go east).",
    )


class PhysicsConfig(_Model):
    """Kinematic multicopter model; speed/acceleration limits are the MPC_* parameters."""

    rate_hz: float = Field(
        50.0,
        ge=5.0,
        le=1000.0,
        title="Physics rate",
        description="Physics, state-machine and telemetry scheduling rate in simulated Hz.",
    )
    velocity_time_constant_s: float = Field(
        0.15,
        gt=0.0,
        le=5.0,
        title="Velocity time constant",
        description="First-order lag of the velocity loop, s (acceleration is also limited).",
    )
    position_gain_1_s: float = Field(
        1.0,
        gt=0.0,
        le=20.0,
        title="Position gain",
        description="Proportional gain from position error to velocity command, 1/s.",
    )
    airspeed_drag_1_s: float = Field(
        0.0,
        ge=0.0,
        le=10.0,
        title="Airspeed drag",
        description="Horizontal deceleration per m/s of velocity in velocity and position "
        "control, 1/s (0: none; PX4 SIH's quadrotor ~1).",
    )
    velocity_integral_gain_1_s2: float = Field(
        0.0,
        ge=0.0,
        le=20.0,
        title="Velocity integral gain",
        description="Integral gain of the velocity loop that slowly wins back what drag takes, "
        "1/s^2 (0: none; PX4's MPC_XY_VEL_I_ACC is 0.4).",
    )
    tilt_time_constant_s: float = Field(
        0.0,
        ge=0.0,
        le=2.0,
        title="Tilt time constant",
        description="Lag of the horizontal acceleration behind the velocity loop's demand (the "
        "attitude change that produces it), s (0: none; PX4 SIH ~0.2).",
    )


class WindConfig(_Model):
    """Wind: a constant part plus gusts (Ornstein-Uhlenbeck per vehicle, seeded)."""

    north_m_s: float = Field(0.0, ge=-50, le=50, title="Wind north", description="Mean, m/s.")
    east_m_s: float = Field(0.0, ge=-50, le=50, title="Wind east", description="Mean, m/s.")
    gust_std_m_s: float = Field(
        0.0, ge=0.0, le=20.0, title="Gust strength", description="Gust standard deviation, m/s."
    )
    gust_time_constant_s: float = Field(
        3.0, gt=0.0, le=600.0, title="Gust time", description="Gust correlation time, s."
    )
    rejection_time_s: float = Field(
        1.5,
        gt=0.0,
        le=60.0,
        title="Wind rejection time",
        description="Time constant with which the velocity controller learns the wind; a wind "
        "change pushes the vehicle until it has been compensated, s.",
    )
    drag_1_s: float = Field(
        0.3,
        ge=0.0,
        le=10.0,
        title="Drag coefficient",
        description="Acceleration per m/s of uncompensated wind, 1/s.",
    )


class OdometryConfig(_Model):
    """Error model of LOCAL_POSITION_NED, the vehicle's own flow-based odometry."""

    position_noise_std_m: float = Field(
        0.0, ge=0.0, le=10.0, title="Position noise", description="White noise per sample, m."
    )
    velocity_noise_std_m_s: float = Field(
        0.0, ge=0.0, le=10.0, title="Velocity noise", description="White noise per sample, m/s."
    )
    drift_bias_std_m_s: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        title="Drift rate",
        description="Standard deviation of each vehicle's constant horizontal drift velocity, m/s.",
    )
    drift_random_walk_m_s_per_sqrt_s: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        title="Drift random walk",
        description="Random walk of the horizontal drift velocity, m/s per sqrt(s).",
    )


class StreamRates(_Model):
    """Telemetry rates of one link in simulated Hz; 0 switches a stream off.

    SET_MESSAGE_INTERVAL changes them at run time, per link, like PX4.
    """

    heartbeat_hz: float = Field(1.0, ge=0.2, le=50, title="HEARTBEAT", description="Rate, Hz.")
    sys_status_hz: float = Field(1.0, ge=0, le=100, title="SYS_STATUS", description="Rate, Hz.")
    extended_sys_state_hz: float = Field(
        5.0, ge=0, le=100, title="EXTENDED_SYS_STATE", description="Rate, Hz."
    )
    global_position_int_hz: float = Field(
        10.0, ge=0, le=100, title="GLOBAL_POSITION_INT", description="Rate, Hz."
    )
    local_position_ned_hz: float = Field(
        10.0, ge=0, le=100, title="LOCAL_POSITION_NED", description="Rate, Hz."
    )
    attitude_hz: float = Field(10.0, ge=0, le=100, title="ATTITUDE", description="Rate, Hz.")
    attitude_quaternion_hz: float = Field(
        10.0, ge=0, le=100, title="ATTITUDE_QUATERNION", description="Rate, Hz."
    )
    home_position_hz: float = Field(
        1.0, ge=0, le=100, title="HOME_POSITION", description="Rate, Hz."
    )
    battery_status_hz: float = Field(
        1.0, ge=0, le=100, title="BATTERY_STATUS", description="Rate, Hz."
    )
    gps_raw_int_hz: float = Field(1.0, ge=0, le=100, title="GPS_RAW_INT", description="Rate, Hz.")
    vfr_hud_hz: float = Field(4.0, ge=0, le=100, title="VFR_HUD", description="Rate, Hz.")
    altitude_hz: float = Field(2.0, ge=0, le=100, title="ALTITUDE", description="Rate, Hz.")
    mission_current_hz: float = Field(
        1.0, ge=0, le=100, title="MISSION_CURRENT", description="Rate, Hz."
    )
    hil_state_quaternion_hz: float = Field(
        0.0,
        ge=0,
        le=100,
        title="HIL_STATE_QUATERNION",
        description="Rate, Hz, of the ground-truth state (PX4 streams it only on SIH's own "
        "link, see truth_stream).",
    )
    highres_imu_hz: float = Field(
        10.0,
        ge=0,
        le=100,
        title="HIGHRES_IMU",
        description="Rate, Hz, of the IMU, magnetometer and barometer readings in SI units. "
        "PX4 streams 50 Hz on the onboard/API link and none on the GCS link; 10 Hz here, like "
        "the other API streams below PX4's rates, because 50 Hz puts a datagram into every "
        "physics step of every vehicle (58 instead of 23 per simulated second). 50 restores "
        "PX4's rate; MAVSDK's set_rate_imu() changes it at run time.",
    )
    scaled_imu_hz: float = Field(
        0.0,
        ge=0,
        le=100,
        title="SCALED_IMU",
        description="Rate, Hz, of the IMU readings in integer units (PX4 streams it on USB "
        "links only; SET_MESSAGE_INTERVAL turns it on).",
    )


def _gcs_rates() -> StreamRates:
    return StreamRates(
        extended_sys_state_hz=1.0,
        global_position_int_hz=5.0,
        local_position_ned_hz=1.0,
        attitude_hz=5.0,
        attitude_quaternion_hz=0.0,
        home_position_hz=0.5,
        battery_status_hz=0.5,
        altitude_hz=1.0,
        highres_imu_hz=0.0,
    )


class TelemetryConfig(_Model):
    """Telemetry rates per link (PX4 uses higher rates on the API/onboard link)."""

    api: StreamRates = Field(
        default_factory=StreamRates,
        title="API link rates",
        description="Stream rates on the API/offboard link (MAVSDK).",
    )
    gcs: StreamRates = Field(
        default_factory=_gcs_rates,
        title="GCS link rates",
        description="Stream rates on the GCS link (QGroundControl, MAVProxy).",
    )


class FlightLogConfig(_Model):
    """The flight logs every vehicle records (ULog, in memory) and serves over the MAVLink log
    protocol and FTP; when they start and stop is PX4's SDLOG_MODE parameter."""

    enabled: bool = Field(
        True,
        title="Record flight logs",
        description="Record a ULog per flight (PX4's logger does; SDLOG_MODE chooses when).",
    )
    rate_hz: float = Field(
        10.0,
        gt=0.0,
        le=100.0,
        title="Sample rate",
        description="Samples per simulated second of each logged topic (PX4 logs most "
        "topics faster; 10 Hz keeps a flight at ~2 kB/s and costs ~0.07 % of a core per "
        "armed vehicle).",
    )
    max_logs: int = Field(
        20,
        ge=1,
        le=10_000,
        title="Logs kept",
        description="Logs each vehicle keeps; the oldest goes when a new one starts.",
    )
    max_log_bytes: int = Field(
        16 * 1024 * 1024,
        ge=4096,
        title="Log size limit",
        description="A log stops growing at this size, bytes.",
    )


class FtpConfig(_Model):
    """What the vehicles' MAVLink FTP servers do beyond PX4's."""

    ardupilot_extensions: bool = Field(
        False,
        title="ArduPilot's FTP extensions",
        description="Also serve the parameters as ArduPilot's packed file @PARAM/param.pck and "
        "keep the session number the client chose, as ArduPilot does. MAVProxy 1.8 needs "
        "both to download parameters over FTP: it numbers its sessions at random, while PX4 "
        "answers every open with session 0 and has no param.pck (it answers FILE_NOT_FOUND, "
        "as the emulator does by default, and MAVProxy falls back to PARAM_REQUEST_LIST). "
        "MAVProxy then takes every parameter for a float, as with ArduPilot.",
    )


class PaceChange(_Model):
    """From ``after_s`` wall seconds after the start on, simulated time runs at ``speed``."""

    after_s: float = Field(
        ...,
        ge=0.0,
        le=1e6,
        title="After",
        description="Wall seconds after the clock's start from which the speed applies.",
    )
    speed: float = Field(
        ...,
        gt=0.0,
        le=1000.0,
        title="Speed factor",
        description="Simulated seconds per wall second from then on.",
    )


class ClockConfig(_Model):
    """How simulated time relates to wall time."""

    @model_validator(mode="after")
    def _pace_in_order(self) -> ClockConfig:
        after = [change.after_s for change in self.pace]
        if after != sorted(after):
            raise ValueError("clock.pace: give the changes in order of after_s")
        if self.pace and self.mode != "realtime":
            raise ValueError("clock.pace: only a realtime clock changes pace (mode: realtime)")
        return self

    mode: Literal["realtime", "lockstep"] = Field(
        "realtime",
        title="Clock mode",
        description="realtime: simulated time = speed x wall time. lockstep: time advances only "
        "as far as every registered participant has released it, as fast as the CPU allows.",
    )
    speed: float = Field(
        1.0,
        gt=0.0,
        le=1000.0,
        title="Speed factor",
        description="Simulated seconds per wall second in realtime mode. MAVSDK's own timers "
        "are wall-clock (1 s heartbeats, 3 s disconnect, 20 Hz offboard resend), so keep "
        "COM_OF_LOSS_T > speed x 0.05 s and COM_DL_LOSS_T > speed x 1 s.",
    )
    lockstep_max_speed: float | None = Field(
        None,
        gt=0.0,
        le=100000.0,
        title="Lockstep speed cap",
        description="In lockstep mode, never run faster than this many simulated seconds per "
        "wall second (None: as fast as possible).",
    )
    participant_timeout_s: float | None = Field(
        10.0,
        gt=0.0,
        title="Participant stall timeout",
        description="In lockstep mode, a participant that holds the clock back this many wall "
        "seconds is dropped with a warning, so a dead participant cannot stall the clock "
        "(None: wait forever).",
    )
    pace: list[PaceChange] = Field(
        default_factory=list,
        title="Speed changes",
        description="Realtime mode: later speed factors, in order of after_s. A simulator "
        "sharing its host's CPU does not keep its pace: PX4 SITL (SIH) starved of CPU while "
        "four instances and the mission's processes started ran its clock at 0.63-0.7x, then "
        "at 1x (measured 2026-12-02). With unix_time: host, clients see the boot clock change "
        "pace against UNIX time as they did on PX4.",
    )
    unix_time: Literal["simulated", "host"] = Field(
        "simulated",
        title="SYSTEM_TIME UNIX clock",
        description="Where SYSTEM_TIME.time_unix_usec comes from. simulated: the host's UNIX "
        "time at start plus simulated time, so it runs exactly with the boot clock. host: in "
        "realtime mode the host's clock (time.time()) when the message is built, like PX4 "
        "SITL, whose simulated boot clock does not run exactly at wall speed (SIH: 0.986x at "
        "speed factor 1; set speed 0.986 to reproduce the drift). In lockstep mode simulated "
        "time has no relation to the host's clock, so host behaves like simulated.",
    )


class BootClockConfig(_Model):
    """When each vehicle's autopilot booted, before the emulator's simulated time 0.

    PX4 stamps its messages with its boot clock (time_boot_ms, time_usec). Instances started
    one after another have boot clocks that differ by their start delays, so a client must map
    every vehicle's clock separately. Vehicle i's boot clock reads simulated time + offset_i;
    everything inside the emulator (physics, timeouts, faults) stays on simulated time.
    """

    offset_s: list[Annotated[float, Field(ge=0.0, le=1e6)]] = Field(
        default_factory=list,
        title="Boot clock offsets",
        description="Boot-clock offset of vehicle 0, 1, ..., s (one per vehicle, or empty). "
        "Exclusive with spread_s.",
    )
    spread_s: float = Field(
        0.0,
        ge=0.0,
        le=1e6,
        title="Random boot clock spread",
        description="If > 0 (and offset_s empty), every vehicle's offset is drawn uniformly "
        "from [0, spread_s] s, seeded.",
    )
    seed: int | None = Field(
        None,
        ge=0,
        title="Boot clock seed",
        description="Seed of the random offsets (None: the emulator's seed).",
    )


class GpsErrorConfig(_Model):
    """Error of the position the vehicle reports as its own (GPS through the EKF):
    GLOBAL_POSITION_INT, GPS_RAW_INT, VFR_HUD and ALTITUDE altitudes.

    Per vehicle, a first-order Gauss-Markov bias in north, east and down (standard deviation
    bias_std_m, correlation time bias_time_constant_s, stationary from the start) plus white
    noise drawn every physics step. The vehicles fly on their true position: only what they
    report is wrong, and the emulator's truth stays exact.
    """

    bias_std_m: float = Field(
        0.0,
        ge=0.0,
        le=100.0,
        title="Bias standard deviation",
        description="Stationary standard deviation of each axis of the bias, m (SIH-like: "
        "0.2-0.3).",
    )
    bias_time_constant_s: float = Field(
        30.0,
        gt=0.0,
        le=1e5,
        title="Bias correlation time",
        description="Correlation time of the bias, s (SIH-like: 20-60).",
    )
    noise_std_m: float = Field(
        0.0,
        ge=0.0,
        le=100.0,
        title="White noise",
        description="Standard deviation of the white noise on each axis, m.",
    )

    @property
    def active(self) -> bool:
        return self.bias_std_m > 0 or self.noise_std_m > 0


class TruthStreamConfig(_Model):
    """SIH's ground-truth link: vehicle i binds local_base + i and sends HIL_STATE_QUATERNION
    (and a 1 Hz HEARTBEAT, like every PX4 MAVLink instance) to remote_base + i on
    ports.remote_host, from its own system id, component 1 (PX4: 19450+i -> 19410+i, 25 Hz).
    """

    enabled: bool = Field(
        False, title="Enabled", description="Open the ground-truth link on every vehicle."
    )
    rate_hz: float = Field(
        25.0,
        gt=0.0,
        le=100.0,
        title="Rate",
        description="HIL_STATE_QUATERNION rate in simulated Hz (PX4 SIH: 25).",
    )
    local_base: int = Field(
        19450,
        ge=1,
        le=65535,
        title="Ground-truth local port base",
        description="Vehicle i binds local_base + i for its ground-truth link (PX4: 19450).",
    )
    remote_base: int = Field(
        19410,
        ge=1,
        le=65535,
        title="Ground-truth client port base",
        description="Vehicle i sends ground truth to remote_base + i (PX4: 19410).",
    )
    fields: Literal["px4", "mavlink"] = Field(
        "px4",
        title="Field conventions",
        description="px4: exactly as PX4 (v1.16) fills the message: time_usec left 0, "
        "accelerations copied in m/s^2 (truncated to integers) into the mG fields, airspeeds "
        "0, integers truncated towards zero. mavlink: as the MAVLink definition reads: "
        "time_usec on the vehicle's boot clock, accelerations in mG, airspeeds the speed "
        "through the air, integers rounded.",
    )


class SigningConfig(_Model):
    """MAVLink 2 message signing (PX4 behaviour, see sitl/signing.py). Without a key a vehicle
    accepts everything until a ground station provisions one with SETUP_SIGNING; with one it
    signs what it sends and refuses unsigned packets except HEARTBEAT, RADIO_STATUS,
    ADSB_VEHICLE and COLLISION.
    """

    passphrase: SecretStr | None = Field(
        None,
        title="Start-up passphrase",
        description="Start every vehicle with signing on, the key being SHA-256 of this "
        "passphrase (what MAVProxy's 'signing setup <passphrase>' sends). It replaces a key "
        "stored in key_dir.",
    )
    key_hex: SecretStr | None = Field(
        None,
        title="Start-up key",
        description="Start every vehicle with signing on with this key: 64 hex digits (32 "
        "bytes). It replaces a key stored in key_dir. Give passphrase or key_hex, not both.",
    )
    key_dir: Path | None = Field(
        None,
        title="Key directory",
        description="Keep each vehicle's key and timestamp across runs in "
        "<key_dir>/vehicle_<sysid>/mavlink-signing-key.bin (PX4's 40-byte format, mode 0600); "
        "a vehicle with a stored key starts with signing on. None: keys live in memory only.",
    )

    @field_validator("key_hex")
    @classmethod
    def _hex_key(cls, value: SecretStr | None) -> SecretStr | None:
        if value is None:
            return None
        text = value.get_secret_value()
        try:
            key = bytes.fromhex(text)
        except ValueError:
            raise ValueError("key_hex must be hexadecimal digits") from None
        if len(key) != 32:
            raise ValueError(f"key_hex must be 64 hex digits (32 bytes), got {len(text)}")
        return value

    @model_validator(mode="after")
    def _one_key(self) -> SigningConfig:
        if self.passphrase is not None and self.key_hex is not None:
            raise ValueError("give signing.passphrase or signing.key_hex, not both")
        if self.passphrase is not None and not self.passphrase.get_secret_value():
            raise ValueError("signing.passphrase must not be empty")
        return self

    def initial_key(self) -> bytes | None:
        """The key vehicles start with (None: the stored one, if any)."""
        if self.key_hex is not None:
            return bytes.fromhex(self.key_hex.get_secret_value())
        if self.passphrase is not None:
            return key_from_passphrase(self.passphrase.get_secret_value())
        return None


class KillFault(_Model):
    """The vehicle's autopilot dies: it stops sending and answering, motors stop."""

    kind: Literal["kill"] = Field(title="Kind", description="Fault kind discriminator.")
    vehicle_index: int = Field(ge=0, title="Vehicle", description="0-based index (sysid - 1).")
    at_s: float = Field(ge=0.0, title="Time", description="Simulated time of the fault, s.")


class LinkDropFault(_Model):
    """A vehicle's link carries nothing, in either direction, for a while."""

    kind: Literal["link_drop"] = Field(title="Kind", description="Fault kind discriminator.")
    vehicle_index: int = Field(ge=0, title="Vehicle", description="0-based index (sysid - 1).")
    link: Literal["api", "gcs", "all"] = Field("all", title="Link", description="Which link drops.")
    at_s: float = Field(ge=0.0, title="Start", description="Simulated start time, s.")
    duration_s: float | None = Field(
        None, gt=0.0, title="Duration", description="How long, s (None: for good)."
    )


class SensorFault(_Model):
    """A sensor stops delivering data."""

    kind: Literal["sensor"] = Field(title="Kind", description="Fault kind discriminator.")
    vehicle_index: int = Field(ge=0, title="Vehicle", description="0-based index (sysid - 1).")
    sensor: Literal["flow", "gps"] = Field(
        title="Sensor",
        description="flow: the optical-flow odometry (LOCAL_POSITION_NED stops, flow health "
        "bit clears). gps: GPS_RAW_INT reports no fix, GLOBAL_POSITION_INT stops.",
    )
    at_s: float = Field(ge=0.0, title="Start", description="Simulated start time, s.")
    duration_s: float | None = Field(
        None, gt=0.0, title="Duration", description="How long, s (None: for good)."
    )


class FailureFault(_Model):
    """A PX4 failure, as MAV_CMD_INJECT_FAILURE (or PX4's ``failure`` shell command) injects it:
    gps / optical_flow / battery / rc_signal / mavlink_signal off, motor off (instance 1-8, 0
    all); see :mod:`sitl.failure_injection`."""

    kind: Literal["failure"] = Field(title="Kind", description="Fault kind discriminator.")
    vehicle_index: int = Field(ge=0, title="Vehicle", description="0-based index (sysid - 1).")
    unit: Literal["gps", "optical_flow", "motor", "battery", "rc_signal", "mavlink_signal"] = Field(
        title="Failure unit", description="PX4's name of the failing unit."
    )
    type: Literal["off", "stuck", "wrong", "ok"] = Field(
        "off",
        title="Failure type",
        description="off: the unit stops; stuck/wrong: motors only (no effect without ESC "
        "telemetry); ok: ends an earlier failure.",
    )
    instance: int = Field(
        0, ge=0, le=8, title="Instance", description="Motor 1-8, 0 for all (others: 0)."
    )
    at_s: float = Field(ge=0.0, title="Start", description="Simulated start time, s.")
    duration_s: float | None = Field(
        None, gt=0.0, title="Duration", description="How long, s (None: for good)."
    )


PX4_ARMING_DENIED_TEXT = "Arming denied: Resolve system health failures first"
"""What PX4's commander says when its health and arming checks refuse an arm command."""


class DenyArmingFault(_Model):
    """The next ``count`` arm commands are refused as PX4 refuses an arm when a health check
    fails after clients saw the vehicle healthy: COMMAND_ACK TEMPORARILY_REJECTED and a
    CRITICAL STATUSTEXT. Forced arms are refused too (PX4 runs its checks on every arm
    command from MAVLink, forced or not).
    """

    kind: Literal["deny_arming"] = Field(title="Kind", description="Fault kind discriminator.")
    vehicle_index: int = Field(ge=0, title="Vehicle", description="0-based index (sysid - 1).")
    at_s: float = Field(
        0.0, ge=0.0, title="Time", description="Simulated time from which it applies, s."
    )
    count: int = Field(
        1, ge=1, le=1_000_000, title="Refusals", description="How many arm attempts to refuse."
    )
    reason: str = Field(
        PX4_ARMING_DENIED_TEXT,
        min_length=1,
        max_length=200,
        title="STATUSTEXT",
        description="The text of the STATUSTEXT sent with each refusal (PX4's by default; PX4 "
        "ends it with a tab and splits texts longer than 50 characters into chunks).",
    )
    retry_window_s: float = Field(
        2.0,
        ge=0.0,
        le=600.0,
        title="Retransmission window",
        description="An identical arm command from the same client on the same link within "
        "this many simulated seconds of a refused attempt is a retransmission of it (MAVSDK "
        "resends a command 0.5 s after it if no ACK came, three times): it is refused again, "
        "with the same STATUSTEXT, without using up a refusal. 0: every arm command counts.",
    )


Fault = Annotated[
    KillFault | LinkDropFault | SensorFault | DenyArmingFault | FailureFault,
    Field(discriminator="kind"),
]


class EmulatorConfig(_Model):
    """Everything the emulator needs to start N vehicles."""

    vehicles: int = Field(
        1,
        ge=1,
        le=MAX_VEHICLES,
        title="Vehicle count",
        description="Number of vehicles; vehicle i has system id i + 1, component id 1.",
    )
    seed: int = Field(
        0,
        ge=0,
        title="Random seed",
        description="Seed of every random process (wind gusts, odometry noise and drift, GPS "
        "error, random boot-clock offsets).",
    )
    ports: PortsConfig = Field(
        default_factory=PortsConfig,
        title="Ports",
        description="UDP port layout; 'auto': free ports picked at start (beside PX4 SITL or "
        "another emulator on PX4's defaults).",
    )
    home: HomeConfig = Field(
        default_factory=HomeConfig, title="Origin", description="Geographic origin."
    )
    placement: PlacementConfig = Field(
        default_factory=PlacementConfig,
        title="Start positions",
        description="Where vehicles start relative to the origin.",
    )
    physics: PhysicsConfig = Field(
        default_factory=PhysicsConfig, title="Physics", description="Kinematic model settings."
    )
    wind: WindConfig = Field(default_factory=WindConfig, title="Wind", description="Wind model.")
    odometry: OdometryConfig = Field(
        default_factory=OdometryConfig,
        title="Odometry errors",
        description="Noise and drift of LOCAL_POSITION_NED.",
    )
    telemetry: TelemetryConfig = Field(
        default_factory=TelemetryConfig, title="Telemetry", description="Stream rates per link."
    )
    clock: ClockConfig = Field(
        default_factory=ClockConfig, title="Clock", description="Time keeping."
    )
    boot_clock: BootClockConfig = Field(
        default_factory=BootClockConfig,
        title="Boot clocks",
        description="Per-vehicle offset of the boot clock that stamps the vehicle's messages.",
    )
    gps_error: GpsErrorConfig = Field(
        default_factory=GpsErrorConfig,
        title="GPS position error",
        description="Bias and noise of the positions the vehicles report (default: exact).",
    )
    truth_stream: TruthStreamConfig = Field(
        default_factory=TruthStreamConfig,
        title="Ground-truth stream",
        description="SIH's HIL_STATE_QUATERNION link (off by default).",
    )
    flight_logs: FlightLogConfig = Field(
        default_factory=FlightLogConfig,
        title="Flight logs",
        description="ULog flight logs for the MAVLink log protocol and FTP.",
    )
    ftp: FtpConfig = Field(
        default_factory=FtpConfig,
        title="MAVLink FTP",
        description="What the FTP servers do beyond PX4's.",
    )
    signing: SigningConfig = Field(
        default_factory=SigningConfig,
        title="Message signing",
        description="MAVLink 2 signing: start-up key and where keys are kept.",
    )
    params: dict[str, float] = Field(
        default_factory=dict,
        title="PX4 parameters",
        description="Parameter values that differ from the PX4 defaults, by PX4 name, for every "
        "vehicle (e.g. MPC_XY_VEL_MAX, MIS_TAKEOFF_ALT, COM_OF_LOSS_T, NAV_DLL_ACT).",
    )
    preflight_ready_after_s: float = Field(
        1.0,
        ge=0.0,
        le=600.0,
        title="Preflight time",
        description="Simulated seconds after power-on before the estimator is ready and the "
        "vehicle can arm (PX4 SITL: health OK after about 1 s).",
    )
    battery_drain_percent_per_min: float = Field(
        1.0,
        ge=0.0,
        le=100.0,
        title="Battery drain",
        description="Battery percentage used per minute while armed.",
    )
    faults: list[Fault] = Field(
        default_factory=list,
        title="Faults",
        description="Faults injected at given simulated times.",
    )
    tlog_dir: Path | None = Field(
        None,
        title="Telemetry log directory",
        description="If set, every vehicle records its MAVLink traffic, both directions, to "
        "<tlog_dir>/vehicle_<sysid>.tlog.",
    )

    @field_validator("params")
    @classmethod
    def _known_params(cls, value: dict[str, float]) -> dict[str, float]:
        return validate_overrides(value)

    @model_validator(mode="before")
    @classmethod
    def _free_ports(cls, data: Any) -> Any:
        """``ports: auto``: pick free ones now, for as many vehicles as configured."""
        if isinstance(data, dict) and data.get("ports") == "auto":
            vehicles = data.get("vehicles", cls.model_fields["vehicles"].default)
            data = {**data, "ports": PortsConfig.free(int(vehicles))}
        return data

    @model_validator(mode="after")
    def _consistent(self) -> EmulatorConfig:
        n = self.vehicles
        for fault in self.faults:
            if fault.vehicle_index >= n:
                raise ValueError(
                    f"fault on vehicle_index {fault.vehicle_index} but only {n} vehicle(s) exist"
                )
        offsets = self.boot_clock.offset_s
        if offsets and len(offsets) != n:
            raise ValueError(
                f"boot_clock.offset_s has {len(offsets)} value(s) for {n} vehicle(s); give one "
                "per vehicle, or use boot_clock.spread_s"
            )
        if offsets and self.boot_clock.spread_s > 0:
            raise ValueError("boot_clock: give offset_s or spread_s, not both")
        ports = self.ports
        local = ports.resolved_api_local_base(n)
        ranges = {
            "ports.api_local_base": (local, local + n - 1),
            "ports.api_remote_base": (ports.api_remote_base, ports.api_remote_port(n - 1)),
        }
        if ports.gcs_enabled:
            ranges["ports.gcs_local_base"] = (ports.gcs_local_base, ports.gcs_local_base + n - 1)
        truth = self.truth_stream
        if truth.enabled:
            ranges["truth_stream.local_base"] = (truth.local_base, truth.local_base + n - 1)
            ranges["truth_stream.remote_base"] = (truth.remote_base, truth.remote_base + n - 1)
        for name, (lo, hi) in ranges.items():
            if hi > 65535:
                raise ValueError(f"{name}: ports {lo}..{hi} for {n} vehicles exceed 65535")
        if ports.gcs_enabled:
            gcs = ports.gcs_remote_port
            for name, (lo, hi) in ranges.items():
                # api_remote_port() skips the GCS port; every other range must not hold it.
                if name != "ports.api_remote_base" and lo <= gcs <= hi:
                    raise ValueError(f"{name} ({lo}..{hi}) contains ports.gcs_remote_port {gcs}")
        names = list(ranges)
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                (alo, ahi), (blo, bhi) = ranges[a], ranges[b]
                if alo <= bhi and blo <= ahi:
                    raise ValueError(
                        f"{a} ({alo}..{ahi}) overlaps {b} ({blo}..{bhi}) for {n} vehicles"
                    )
        return self

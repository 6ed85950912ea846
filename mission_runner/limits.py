"""Bounds the scenario model and the command line's options share. No imports: building the
command line (``--help`` on a companion computer) reads them without loading the scenario model,
which loads the bus and its MQTT client."""

#: What one wait of a flight may last [s] (timeouts, delays): an hour is beyond any of them, and
#: the event loop's timers overflow long before 1e300.
MAX_WAIT_S = 3600.0
#: Noise figures (standard deviations) [m]: a ranging radio or an odometry worse than this
#: measures nothing.
MAX_NOISE_STD_M = 100.0
#: Fastest speed factor of the bundled emulator's real-time clock (sitl.config).
MAX_CLOCK_SPEED = 1000.0
#: MAVLink system ids are one byte (0 is broadcast): a flying vehicle's id is its system id.
MAX_MAVLINK_ID = 255

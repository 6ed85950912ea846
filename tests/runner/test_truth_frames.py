"""The range aid's hand-made MAVLink framing against pymavlink's: HIL_STATE_QUATERNION frames as
pymavlink packs them (signed or not, zero-truncated, several to a datagram) read as pymavlink
reads them; what pymavlink would refuse (bad CRC, cut short, another system) counted and never
used; the vision ODOMETRY byte for byte pymavlink's frame."""

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from mission_runner.runner.mavlink_frames import OdometryFrames, TruthDecoder
from mission_runner.runner.ranges import (
    ATTITUDE_NOISE_STD_RAD,
    VisionOdometry,
    VisionSettings,
    _Positions,
    _TruthProtocol,
)

from .flying import load

ADDRESS = ("127.0.0.1", 19450)
QUATERNION = [0.9238795, 0.0, 0.0, 0.3826834]


def hil_frame(system_id=1, *, seq=0, signed=False, accelerations=(10, -20, -981), **changes):
    """A HIL_STATE_QUATERNION frame packed by pymavlink (zero accelerations: a truncated
    payload)."""
    packer = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=1)
    packer.seq = seq
    if signed:
        packer.signing.secret_key = bytes(range(32))
        packer.signing.sign_outgoing = True
        packer.signing.link_id = 7
        packer.signing.timestamp = 123_456_789
    values = {
        "time_usec": 0,
        "attitude_quaternion": QUATERNION,
        "rollspeed": 0.01,
        "pitchspeed": -0.02,
        "yawspeed": 0.5,
        "lat": 473977420 + seq,
        "lon": 85455940 - seq,
        "alt": 488123,
        "vx": 150,
        "vy": -75,
        "vz": -12,
        "ind_airspeed": 0,
        "true_airspeed": 0,
        "xacc": accelerations[0],
        "yacc": accelerations[1],
        "zacc": accelerations[2],
    } | changes
    return mavlink.MAVLink_hil_state_quaternion_message(**values).pack(packer)


def pymavlink_reads(data):
    parser = mavlink.MAVLink(None)
    return [m for m in parser.parse_buffer(data) or [] if m.get_type() == "HIL_STATE_QUATERNION"]


def assert_same(state, message):
    assert (state.lat, state.lon, state.alt) == (message.lat, message.lon, message.alt)
    assert (state.vx, state.vy, state.vz) == (message.vx, message.vy, message.vz)
    assert list(state.attitude_quaternion) == message.attitude_quaternion


@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed"])
@pytest.mark.parametrize("accelerations", [(10, -20, -981), (0, 0, 0)], ids=["full", "truncated"])
def test_a_frame_reads_as_pymavlink_reads_it(signed, accelerations):
    data = hil_frame(signed=signed, accelerations=accelerations)
    assert bool(data[2] & mavlink.MAVLINK_IFLAG_SIGNED) == signed
    full = mavlink.MAVLink_hil_state_quaternion_message.unpacker.size
    assert (data[1] < full) == (accelerations == (0, 0, 0))  # pymavlink cut the zeros
    decoder = TruthDecoder(1)
    (state,) = decoder.states(data)
    (expected,) = pymavlink_reads(data)
    assert_same(state, expected)
    assert decoder.malformed == 0


def test_every_frame_of_a_datagram_is_read_in_order():
    data = hil_frame(seq=1) + hil_frame(seq=2, signed=True) + hil_frame(seq=3)
    decoder = TruthDecoder(1)
    states = decoder.states(data)
    assert [s.lat for s in states] == [473977421, 473977422, 473977423]
    for state, expected in zip(states, pymavlink_reads(data), strict=True):
        assert_same(state, expected)


def test_other_messages_and_v1_frames_are_skipped_by_their_length():
    heartbeat = mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3)
    v2 = heartbeat.pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))
    v1 = heartbeat.pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1), force_mavlink1=True)
    v1_truth = mavlink.MAVLink_hil_state_quaternion_message(
        0, QUATERNION, 0, 0, 0, 1, 2, 3, 4, 5, 6, 0, 0, 0, 0, 0
    ).pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1), force_mavlink1=True)
    decoder = TruthDecoder(1)
    states = decoder.states(v2 + v1 + v1_truth + hil_frame(seq=5))
    assert [s.lat for s in states] == [473977425]
    assert decoder.malformed == 0


class Transport:
    def __init__(self):
        self.sent = []

    def sendto(self, data, addr=None):
        self.sent.append((data, addr))


def protocol(vision=None):
    truth = _TruthProtocol(_Positions(load("paper_tracking_flyable")), 1, 100.0, vision)
    transport = Transport()
    truth.connection_made(transport)
    return truth, transport


def test_a_frame_with_a_bad_crc_is_counted_and_never_used():
    data = bytearray(hil_frame())
    data[20] ^= 0x01  # a bit of the attitude
    truth, transport = protocol()
    truth.datagram_received(bytes(data), ADDRESS)
    assert truth.malformed == 1
    assert truth.positions.vehicles[1].received == 0
    assert transport.sent == []  # not even the rate request: nothing was heard from it


def test_a_frame_cut_short_is_counted_and_never_completed_by_the_next_datagram():
    data = hil_frame()
    truth, transport = protocol()
    truth.datagram_received(data[:40], ADDRESS)
    truth.datagram_received(data[40:], ADDRESS)
    assert truth.malformed == 2  # the tail is no frame either
    assert truth.positions.vehicles[1].received == 0
    assert transport.sent == []


def test_another_systems_frames_are_counted_and_never_mixed_in():
    truth, _ = protocol()
    truth.datagram_received(hil_frame(2) + hil_frame(1, lat=473977000), ADDRESS)
    assert truth.malformed == 1
    assert truth.positions.vehicles[1].received == 1
    assert truth.positions.frame.reference[0] == pytest.approx(47.3977)


def test_the_first_frame_asks_for_the_rate_and_each_goes_into_the_positions():
    truth, transport = protocol()
    truth.datagram_received(hil_frame(seq=1), ADDRESS)
    truth.datagram_received(hil_frame(seq=2), ADDRESS)
    asked = [pymavlink_command(data) for data, _ in transport.sent]
    assert [(c.command, c.param1) for c in asked] == [
        (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION),
        (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS),
    ]
    assert truth.malformed == 0


def test_each_truth_is_stamped_on_arrival_by_the_aids_unix_clock():
    """The bracketing of a step's t_k compares these stamps with the mission clock's UNIX time:
    both read one clock."""
    now_s = [1000.0]
    truth = _TruthProtocol(
        _Positions(load("paper_tracking_flyable")), 1, 100.0, unix_s=lambda: now_s[0]
    )
    truth.datagram_received(hil_frame(seq=1), ADDRESS)
    positions = truth.positions.vehicles[1]
    assert positions.newest_s() == 1000.0
    now_s[0] = 1000.25
    truth.datagram_received(hil_frame(seq=2), ADDRESS)
    assert positions.newest_s() == 1000.25 and positions.received == 2


def pymavlink_command(data):
    (message,) = mavlink.MAVLink(None).parse_buffer(data)
    return message


def odometry_by_pymavlink(seq, position, quaternion, velocity, variances):
    position_var, velocity_var = variances
    packer = mavlink.MAVLink(
        None, srcSystem=3, srcComponent=mavlink.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    )
    packer.seq = seq

    def covariance(linear, angular):
        values = [math.nan] * 21
        for index in (0, 6, 11):
            values[index] = linear
        for index in (15, 18, 20):
            values[index] = angular
        return values

    return mavlink.MAVLink_odometry_message(
        0,
        mavlink.MAV_FRAME_LOCAL_NED,
        mavlink.MAV_FRAME_LOCAL_NED,
        *position,
        quaternion,
        *velocity,
        math.nan,
        math.nan,
        math.nan,
        covariance(position_var, ATTITUDE_NOISE_STD_RAD**2),
        covariance(velocity_var, math.nan),
        0,
        mavlink.MAV_ESTIMATOR_TYPE_VIO,
        100,
    ).pack(packer)


def test_the_odometry_frame_is_pymavlinks_byte_for_byte_with_its_sequence_counted_up():
    frames = OdometryFrames(
        3,
        mavlink.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY,
        position_variance_m2=0.02**2,
        attitude_variance_rad2=ATTITUDE_NOISE_STD_RAD**2,
        velocity_variance_m2_s2=0.05**2,
    )
    rng = np.random.default_rng(5)
    for index, seq in enumerate([0, 1, 2, 254, 255, 0, 1]):
        if index == 3:
            frames.seq = 254  # on through 255 back to 0
        position, velocity = rng.normal(0.0, 10.0, 3), rng.normal(0.0, 2.0, 3)
        quaternion = list(rng.normal(0.0, 1.0, 4))
        expected = odometry_by_pymavlink(seq, position, quaternion, velocity, (0.02**2, 0.05**2))
        assert frames.frame(position, quaternion, velocity) == expected


def test_the_vision_odometry_counts_its_sequence_and_draws_its_noise_from_the_generator():
    """In drawn order, six per message, across the blocks it draws ahead."""
    settings = VisionSettings(rate_hz=50.0, position_noise_std_m=0.02, velocity_noise_std_m_s=0.05)
    vision = VisionOdometry(3, settings, np.random.default_rng(9))
    (truth,) = pymavlink_reads(hil_frame(3))
    count = VisionOdometry.NOISE_BLOCK + 44
    scale = np.array([0.02] * 3 + [0.05] * 3)
    noise = np.random.default_rng(9).normal(0.0, 1.0, (count, 6)) * scale
    sent = [vision.message(0.02 * index, truth) for index in range(count)]
    parsed = mavlink.MAVLink(None).parse_buffer(b"".join(sent))
    assert [m.get_seq() for m in parsed] == [index % 256 for index in range(count)]
    for message, row in zip(parsed, noise, strict=True):
        assert message.get_srcSystem() == 3
        assert [message.x, message.y, message.z] == pytest.approx(row[:3], abs=1e-6)
        velocity = [message.vx - 1.5, message.vy + 0.75, message.vz + 0.12]
        assert velocity == pytest.approx(row[3:], abs=1e-6)
        assert message.q == pytest.approx(QUATERNION)
        assert message.pose_covariance[0] == pytest.approx(0.02**2)


def test_a_vision_odometry_at_its_truths_own_rate_keeps_that_rate_through_jitter():
    """Each ODOMETRY is made from one truth sample, so the aid asks for the truth at the vision's
    rate (--vision 50: 50 Hz, not 100): arrivals a few ms early or late (PX4 SIH on a loaded
    machine) must still each give one, and a faster truth no more than the rate."""
    vision = VisionOdometry(3, VisionSettings(rate_hz=50.0), np.random.default_rng(9))
    (truth,) = pymavlink_reads(hil_frame(3))
    jitter_s = np.random.default_rng(4).uniform(-0.004, 0.004, 500)
    sent = [vision.message(0.02 * index + jitter_s[index], truth) for index in range(500)]
    assert sum(frame is not None for frame in sent) >= 495
    # A truth twice as fast still gives the vision's rate, not more.
    faster = VisionOdometry(3, VisionSettings(rate_hz=50.0), np.random.default_rng(9))
    sent = [faster.message(0.01 * index + jitter_s[index] / 2, truth) for index in range(500)]
    assert 245 <= sum(frame is not None for frame in sent) <= 255

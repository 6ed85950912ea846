"""Message encoding: round trips, strict decoding, and bad payloads as typed errors."""

from __future__ import annotations

import contextlib
import json
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mission_runner.bus import (
    MESSAGE_TYPES,
    ControlCommand,
    Message,
    MessageDecodeError,
    MessageValueError,
    MissionControl,
    RangeSet,
    StepMessage,
    TargetObservation,
    TopicKind,
    VehicleStatus,
    shared_range,
)

finite = st.floats(allow_nan=False, allow_infinity=False)
non_negative = st.floats(min_value=0.0, allow_nan=False, allow_infinity=False)
vehicle_ids = st.integers(1, 64)

step_messages = st.builds(
    StepMessage,
    vehicle_id=vehicle_ids,
    step=st.integers(0, 10**9),
    time_s=finite,
    phase_rad=finite,
    odometry_north_m=finite,
    odometry_east_m=finite,
) | st.builds(
    StepMessage,
    vehicle_id=vehicle_ids,
    step=st.integers(0, 10**9),
    time_s=finite,
    phase_rad=finite,
    odometry_north_m=finite,
    odometry_east_m=finite,
    target_odometry_north_m=finite,
    target_odometry_east_m=finite,
    target_velocity_north_m_s=finite,
    target_velocity_east_m_s=finite,
    command_north_m_s=finite,
    command_east_m_s=finite,
)
shared_ranges = st.builds(
    StepMessage,
    vehicle_id=st.just(1),
    step=st.integers(0, 10**9),
    time_s=finite,
    phase_rad=finite,
    odometry_north_m=finite,
    odometry_east_m=finite,
    ranges_m=st.dictionaries(st.integers(2, 4096), non_negative.map(shared_range)).map(
        lambda ranges: tuple(sorted(ranges.items()))
    ),
)
range_sets = st.builds(
    RangeSet,
    vehicle_id=st.just(1),
    time_s=finite,
    ranges_m=st.dictionaries(st.integers(2, 1024) | st.just(0), non_negative, max_size=64).map(
        lambda ranges: tuple(ranges.items())
    ),
    step=st.none() | st.integers(0, 10**9),
)
target_observations = st.builds(
    TargetObservation,
    vehicle_id=vehicle_ids,
    time_s=finite,
    range_m=non_negative,
    velocity_north_m_s=finite,
    velocity_east_m_s=finite,
)
mission_controls = st.builds(
    MissionControl,
    command=st.sampled_from(ControlCommand),
    time_s=finite,
    reason=st.none() | st.text(),
)
vehicle_statuses = st.builds(
    VehicleStatus,
    vehicle_id=vehicle_ids,
    time_s=finite,
    state=st.text(min_size=1),
    step=st.integers(0, 10**9),
    tracking_ok=st.booleans(),
    detail=st.text(),
)
any_message = (
    step_messages
    | shared_ranges
    | range_sets
    | target_observations
    | mission_controls
    | (vehicle_statuses)
)

STEP = StepMessage(
    vehicle_id=2,
    step=41,
    time_s=5.125,
    phase_rad=1.5707963267948966,
    odometry_north_m=12.5,
    odometry_east_m=-3.25,
)


@given(any_message)
def test_every_message_round_trips_exactly(message: Message) -> None:
    payload = message.to_payload()
    assert isinstance(payload, bytes)
    assert type(message).from_payload(payload) == message


@given(any_message)
def test_payload_is_compact_json_without_none_fields(message: Message) -> None:
    payload = message.to_payload()
    data = json.loads(payload)
    compact = json.dumps(data, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    assert payload == compact
    assert None not in data.values()


def test_step_message_payload_names_units_in_keys() -> None:
    assert json.loads(STEP.to_payload()) == {
        "vehicle_id": 2,
        "step": 41,
        "time_s": 5.125,
        "phase_rad": 1.5707963267948966,
        "odometry_north_m": 12.5,
        "odometry_east_m": -3.25,
    }
    assert not STEP.has_target


def test_shared_ranges_travel_as_compact_pairs() -> None:
    message = StepMessage(2, 41, 5.125, 0.0, 0.0, 0.0, ranges_m=((1, shared_range(4.123456789)),))
    assert b'"ranges_m":[[1,4.1235]]' in message.to_payload()
    decoded = StepMessage.from_payload(message.to_payload())
    assert decoded.ranges_m == ((1, 4.1235),)
    assert isinstance(decoded.ranges_m, tuple)


def test_the_command_in_force_travels_as_a_pair() -> None:
    message = StepMessage(2, 41, 5.125, 0.0, 0.0, 0.0, command_north_m_s=1.5, command_east_m_s=-2)
    decoded = StepMessage.from_payload(message.to_payload())
    assert decoded.command_m_s == (1.5, -2.0)
    assert STEP.command_m_s is None


def test_integers_are_accepted_for_float_fields_and_stored_as_floats() -> None:
    message = StepMessage(1, 0, 0, 0, 1, 2)
    assert isinstance(message.odometry_north_m, float)
    assert StepMessage.from_payload(message.to_payload()) == message


def test_every_topic_kind_has_a_message_type() -> None:
    assert set(MESSAGE_TYPES) == set(TopicKind)


@pytest.mark.parametrize(
    ("build", "problem"),
    [
        (lambda: StepMessage(0, 0, 0.0, 0.0, 0.0, 0.0), "vehicle_id must be >= 1"),
        (lambda: StepMessage(1, -1, 0.0, 0.0, 0.0, 0.0), "step must be >= 0"),
        (lambda: StepMessage(1, 0, math.nan, 0.0, 0.0, 0.0), "time_s must be finite"),
        (lambda: StepMessage(1, 0, 0.0, math.inf, 0.0, 0.0), "phase_rad must be finite"),
        (lambda: StepMessage(True, 0, 0.0, 0.0, 0.0, 0.0), "vehicle_id must be an integer"),
        (lambda: StepMessage(1, 0, "0", 0.0, 0.0, 0.0), "time_s must be a number"),
        (
            lambda: StepMessage(1, 0, 0.0, 0.0, 0.0, 0.0, target_odometry_north_m=1.0),
            "set as a pair",
        ),
        (lambda: StepMessage(2, 0, 0.0, 0.0, 0.0, 0.0, ranges_m=((2, 1.0),)), "another vehicle"),
        (lambda: StepMessage(2, 0, 0.0, 0.0, 0.0, 0.0, ranges_m=((0, 1.0),)), "another vehicle"),
        (lambda: StepMessage(2, 0, 0.0, 0.0, 0.0, 0.0, ranges_m=((3, -1.0),)), "must be >= 0"),
        (lambda: StepMessage(2, 0, 0.0, 0.0, 0.0, 0.0, ranges_m=((3, 1.0), (3, 2.0))), "twice"),
        (
            lambda: StepMessage(2, 0, 0.0, 0.0, 0.0, 0.0, ranges_m=((3, math.nan),)),
            r"ranges_m\[0\]\[1\] must be finite",
        ),
        (lambda: StepMessage(2, 0, 0.0, 0.0, 0.0, 0.0, ranges_m=((3,),)), "must have 2 entries"),
        (
            lambda: StepMessage(2, 0, 0.0, 0.0, 0.0, 0.0, command_north_m_s=1.0),
            r"command_\*_m_s must be set as a pair",
        ),
        (
            lambda: StepMessage(
                2, 0, 0.0, 0.0, 0.0, 0.0, command_north_m_s=math.inf, command_east_m_s=0.0
            ),
            "command_north_m_s must be finite",
        ),
        (lambda: StepMessage(2, 0, 0.0, 0.0, 0.0, 0.0, ranges_m="3:1.0"), "must be an array"),
        (
            lambda: StepMessage(
                2, 0, 0.0, 0.0, 0.0, 0.0, ranges_m=tuple((p, 1.0) for p in range(3, 5000))
            ),
            "at most 4096",
        ),
        (lambda: RangeSet(1, 0.0, ((1, 1.0),)), r"not the vehicle itself \(1\), got 1"),
        (lambda: RangeSet(1, 0.0, ((-1, 1.0),)), "peer must be >= 0"),
        (lambda: RangeSet(1, 0.0, ((0, -0.1),)), "range to 0 must be >= 0"),
        (lambda: RangeSet(1, 0.0, ((2, 1.0), (3, 2.0), (2, 1.5))), "names a peer twice"),
        (lambda: RangeSet(1, 0.0, ((2, math.nan),)), r"ranges_m\[0\]\[1\] must be finite"),
        (lambda: RangeSet(1, 0.0, ((2, 1.0, 3.0),)), r"ranges_m\[0\] must have 2 entries"),
        (lambda: RangeSet(1, 0.0, ((2.5, 1.0),)), "must be an integer"),
        (lambda: RangeSet(1, 0.0, step=-1), "step must be >= 0"),
        (lambda: RangeSet(0, 0.0), "vehicle_id must be >= 1"),
        (
            lambda: RangeSet(1, 0.0, tuple((p, 1.0) for p in range(2, 1027))),
            "1025 entries, at most 1024",
        ),
        (lambda: MissionControl("takeoff", 0.0), "command must be one of"),
        (lambda: MissionControl("land", 0.0, reason="x" * 1001), "at most 1000 characters"),
        (lambda: VehicleStatus(1, 0.0, "", 0, True), "state must not be empty"),
        (lambda: VehicleStatus(1, 0.0, "ok", 0, 1), "tracking_ok must be true or false"),
    ],
)
def test_invalid_fields_raise_a_value_error_naming_the_field(build, problem: str) -> None:
    with pytest.raises(MessageValueError, match=problem) as raised:
        build()
    assert isinstance(raised.value, ValueError)


def test_messages_are_immutable() -> None:
    with pytest.raises(AttributeError):
        STEP.step = 42  # type: ignore[misc]


@pytest.mark.parametrize(
    ("payload", "problem"),
    [
        (b"", "not valid JSON"),
        (b"\xff\xfe", "not UTF-8"),
        (b"[1, 2]", "expected a JSON object"),
        (b'"step"', "expected a JSON object"),
        (b'{"vehicle_id": 2}', "missing field"),
        (STEP.to_payload()[:-1] + b',"speed_m_s":1}', "unknown field"),
        (STEP.to_payload().replace(b"5.125", b"NaN"), "non-finite"),
        (STEP.to_payload().replace(b"5.125", b"Infinity"), "non-finite"),
        (STEP.to_payload().replace(b"5.125", b"1e999"), "time_s must be finite"),
        # An integer of 400 digits is valid JSON but no float: once an OverflowError out of the
        # decoder, which ended the controller's receive loop.
        (STEP.to_payload().replace(b"5.125", b"1" * 400), "time_s must be finite"),
        (STEP.to_payload().replace(b"41", b"41.0"), "step must be an integer"),
        (STEP.to_payload().replace(b"41", b"-1"), "step must be >= 0"),
        (STEP.to_payload().replace(b"12.5", b'"12.5"'), "must be a number"),
        (STEP.to_payload().replace(b"41", b"1" * 5000), "not valid JSON"),
        (b"[" * 100_000, "not valid JSON"),
    ],
)
def test_bad_payloads_raise_decode_errors(payload: bytes, problem: str) -> None:
    with pytest.raises(MessageDecodeError, match=problem) as raised:
        StepMessage.from_payload(payload)
    assert raised.value.message_type == "StepMessage"


def test_payload_of_one_type_does_not_decode_as_another() -> None:
    status = VehicleStatus(2, 1.0, "following", 3, True)
    with pytest.raises(MessageDecodeError):
        StepMessage.from_payload(status.to_payload())
    with pytest.raises(MessageDecodeError):
        RangeSet.from_payload(STEP.to_payload())


@given(st.binary(max_size=200))
def test_arbitrary_bytes_never_raise_anything_but_decode_errors(payload: bytes) -> None:
    for message_type in MESSAGE_TYPES.values():
        with contextlib.suppress(MessageDecodeError):
            message_type.from_payload(payload)


@given(
    st.dictionaries(
        st.sampled_from(["vehicle_id", "step", "time_s", "x"]),
        st.none() | st.booleans() | st.integers() | finite | st.text(max_size=3),
    )
)
def test_arbitrary_objects_never_raise_anything_but_decode_errors(data: dict) -> None:
    payload = json.dumps(data).encode()
    for message_type in MESSAGE_TYPES.values():
        with contextlib.suppress(MessageDecodeError):
            message_type.from_payload(payload)


def test_control_command_decodes_to_the_enum() -> None:
    decoded = MissionControl.from_payload(b'{"command":"land","time_s":3,"reason":"battery"}')
    assert decoded == MissionControl(ControlCommand.LAND, 3.0, "battery")
    assert decoded.command is ControlCommand.LAND


@pytest.mark.parametrize(
    ("payload", "problem"),
    [
        (b'{"vehicle_id":1,"time_s":0.5,"ranges_m":[[2,4.0],[2,5.0]]}', "names a peer twice"),
        (b'{"vehicle_id":1,"time_s":0.5,"ranges_m":[[1,4.0]]}', "not the vehicle itself"),
        (b'{"vehicle_id":1,"time_s":0.5,"ranges_m":[[2,-4.0]]}', "must be >= 0"),
        (b'{"vehicle_id":1,"time_s":0.5,"ranges_m":[[2,NaN]]}', "non-finite"),
        (b'{"vehicle_id":1,"time_s":0.5,"ranges_m":{"2":4.0}}', "must be an array"),
        (b'{"vehicle_id":1,"time_s":0.5,"ranges_m":[[true,4.0]]}', "must be an integer"),
        (b'{"vehicle_id":1,"time_s":0.5}', "missing field"),
        (
            b'{"vehicle_id":1,"time_s":0.5,"ranges_m":[%s]}'
            % b",".join(b"[%d,1.0]" % p for p in range(2, 1100)),
            "at most 1024",
        ),
    ],
)
def test_hostile_range_sets_raise_decode_errors(payload: bytes, problem: str) -> None:
    with pytest.raises(MessageDecodeError, match=problem):
        RangeSet.from_payload(payload)


def test_an_empty_range_set_is_a_message() -> None:
    """Every range of a round dropped out: the set still says the round is over."""
    empty = RangeSet(3, 1.25, step=10)
    assert RangeSet.from_payload(empty.to_payload()) == empty
    assert json.loads(empty.to_payload())["ranges_m"] == []

"""What a vehicle says it speaks: AUTOPILOT_VERSION's capability bits and identity, checked bit by
bit against what a running PX4 SITL answers, and as MAVSDK's info plugin reads them;
PROTOCOL_VERSION byte for byte as PX4 sends it."""

from __future__ import annotations

import asyncio

import pytest
from mavsdk.asyncio.plugins.info import InfoAsync
from pymavlink.dialects.v20 import common as mavlink

from sitl import Emulator, EmulatorConfig
from sitl.messages import (
    MAVLINK_MSG_ID_PROTOCOL_VERSION,
    MAVLinkProtocolVersionMessage,
    decode_protocol_version,
)
from sitl.telemetry import CAPABILITIES
from tests.sitl.helpers import Bench, RawClient, free_port_config
from tests.sitl.mavsdk_helpers import api_config, emulated_drones

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED

#: AUTOPILOT_VERSION.capabilities of PX4 SITL (SIH), read from a running instance: 0xE8FF.
PX4_SITL_CAPABILITIES = {
    "MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT",
    "MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT",
    "MAV_PROTOCOL_CAPABILITY_MISSION_INT",
    "MAV_PROTOCOL_CAPABILITY_COMMAND_INT",
    "MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE",
    "MAV_PROTOCOL_CAPABILITY_FTP",
    "MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET",
    "MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED",
    "MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION",
    "MAV_PROTOCOL_CAPABILITY_MAVLINK2",
    "MAV_PROTOCOL_CAPABILITY_MISSION_FENCE",
    "MAV_PROTOCOL_CAPABILITY_MISSION_RALLY",
}


def bit_names(capabilities: int) -> set[str]:
    entries = mavlink.enums["MAV_PROTOCOL_CAPABILITY"]
    return {
        entry.name
        for value, entry in entries.items()
        if value & (value - 1) == 0 and capabilities & value and not entry.name.endswith("END")
    }


def version_of(bench: Bench) -> mavlink.MAVLink_message:
    assert bench.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 148) == ACCEPTED
    message = bench.link.sent[-1]
    assert message.get_type() == "AUTOPILOT_VERSION"
    return message


def test_capability_bits_are_px4_sitls() -> None:
    assert bit_names(CAPABILITIES) == PX4_SITL_CAPABILITIES
    assert CAPABILITIES == 0xE8FF
    assert version_of(Bench()).capabilities == CAPABILITIES


def test_no_bit_claims_what_px4_does_not_claim() -> None:
    names = bit_names(CAPABILITIES)
    # 0x1000 was once set here for PARAM_ENCODE_BYTEWISE (0x10); it means compass calibration.
    assert "MAV_PROTOCOL_CAPABILITY_COMPASS_CALIBRATION" not in names
    assert "MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE" in names
    # Handled (offboard) but, as on PX4, not advertised.
    assert "MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT" not in names
    assert "MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST" not in names
    assert "MAV_PROTOCOL_CAPABILITY_TERRAIN" not in names


def test_the_advertised_protocols_are_served() -> None:
    bench = Bench()
    bench.step()
    # FLIGHT_TERMINATION: the command is accepted and the motors stop.
    assert bench.command(mavlink.MAV_CMD_DO_FLIGHTTERMINATION, 1) == ACCEPTED
    # MISSION_FENCE / MISSION_RALLY: an upload of either type is accepted.
    for mission_type in (mavlink.MAV_MISSION_TYPE_FENCE, mavlink.MAV_MISSION_TYPE_RALLY):
        bench.link.clear()
        bench.deliver(mavlink.MAVLink_mission_count_message(1, 1, 0, mission_type))
        acks = bench.link.of_type("MISSION_ACK")
        assert [(a.type, a.mission_type) for a in acks] == [
            (mavlink.MAV_MISSION_ACCEPTED, mission_type)
        ]


def test_each_vehicle_has_its_own_identity_like_px4_sitl_instances() -> None:
    bench = Bench(3)
    versions = [
        bench.autopilots[i].telemetry.build(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0.0)
        for i in range(3)
    ]
    assert [v.uid2[0] for v in versions] == [0, 1, 2]  # PX4 SITL: instance in the GUID
    assert len({v.uid for v in versions}) == 3


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_info_reads_version_and_identity() -> None:
    async with emulated_drones(api_config(2)) as (_, drones):
        infos = [InfoAsync(drone.system) for drone in drones]
        versions = [await info.get_version() for info in infos]
        identities = [await info.get_identification() for info in infos]
    assert {(v.flight_sw_major, v.flight_sw_minor, v.flight_sw_patch) for v in versions} == {
        (1, 15, 0)
    }
    assert identities[0].hardware_uid != identities[1].hardware_uid
    assert {i.legacy_uid for i in identities} == {0x5349544C00000001, 0x5349544C00000002}


# ---------------------------------------------------------------- PROTOCOL_VERSION
#: PROTOCOL_VERSION as PX4 SITL (system 8, sequence 0x70) sent it: version 200, min 100, max 203,
#: library_version_hash = the first 8 bytes of its MAVLink library's git hash.
PX4_PROTOCOL_VERSION_PACKET = bytes.fromhex(
    "fd1600007008012c0100c8006400cb0000000000000000006521d1aee97ea4515341"
)


def test_protocol_version_is_encoded_byte_for_byte_as_px4_does() -> None:
    payload = PX4_PROTOCOL_VERSION_PACKET[10:-2]
    px4 = decode_protocol_version(payload)
    assert (px4.version, px4.min_version, px4.max_version) == (200, 100, 203)
    encoder = mavlink.MAVLink(None, srcSystem=8, srcComponent=1)
    encoder.seq = 0x70
    again = MAVLinkProtocolVersionMessage(200, 100, 203, [0] * 8, px4.library_version_hash)
    assert again.pack(encoder) == PX4_PROTOCOL_VERSION_PACKET  # CRC extra included


@pytest.mark.parametrize(
    "request_",
    [
        (mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION, 1),
        (mavlink.MAV_CMD_REQUEST_MESSAGE, MAVLINK_MSG_ID_PROTOCOL_VERSION),
    ],
)
def test_protocol_version_answers_both_requests_after_the_ack(request_: tuple[int, int]) -> None:
    bench = Bench()
    assert bench.command(*request_) == ACCEPTED
    kinds = [m.get_type() for m in bench.link.sent]
    assert kinds[-2:] == ["COMMAND_ACK", "PROTOCOL_VERSION"]
    answer = bench.link.sent[-1]
    assert (answer.version, answer.min_version, answer.max_version) == (200, 100, 203)


def test_protocol_version_request_may_be_broadcast_like_on_px4() -> None:
    bench = Bench()
    assert bench.command(mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION, 1, target=0) == ACCEPTED
    assert bench.command(mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION, 1, target_component=42) == (
        ACCEPTED
    )
    assert bench.command(mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION, 1, target=9) is None


@pytest.mark.asyncio
async def test_protocol_version_over_udp_passes_pymavlinks_crc_check(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # pymavlink's common dialect lacks the message: teach this process's decoder the definition
    # so that it checks the CRC and the layout of what arrives.
    monkeypatch.setitem(
        mavlink.mavlink_map, MAVLINK_MSG_ID_PROTOCOL_VERSION, MAVLinkProtocolVersionMessage
    )
    config = EmulatorConfig(vehicles=1, ports=free_port_config(1, gcs=False))
    async with Emulator(config), RawClient(config.ports.api_remote_port(0)) as client:
        await client.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "a heartbeat")
        with client.matching(lambda m: m.get_type() == "PROTOCOL_VERSION") as answer:
            assert await client.command(1, mavlink.MAV_CMD_REQUEST_PROTOCOL_VERSION, 1) == ACCEPTED
            message = await asyncio.wait_for(answer, 3)
    assert (message.version, message.min_version, message.max_version) == (200, 100, 203)
    assert client.counts.get("PROTOCOL_VERSION") == 1

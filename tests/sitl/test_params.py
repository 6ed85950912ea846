"""PX4 parameter table, byte-wise INT32 encoding, store."""

from __future__ import annotations

import logging
import math

import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl import Emulator, EmulatorConfig
from sitl.config import ClockConfig
from sitl.params import (
    MAV_PARAM_TYPE_INT32,
    MAV_PARAM_TYPE_REAL32,
    PARAM_NAMES,
    PARAM_TABLE,
    ParamStore,
    int32_to_wire_float,
    validate_overrides,
    wire_float_to_int32,
)
from tests.sitl.helpers import RawClient, free_port_config

CLIENT_NAMES = [
    "MIS_TAKEOFF_ALT",
    "RTL_RETURN_ALT",
    "COM_OF_LOSS_T",
    "COM_OBL_RC_ACT",
    "NAV_DLL_ACT",
    "COM_DL_LOSS_T",
    "MPC_XY_VEL_MAX",
    "MPC_Z_VEL_MAX_UP",
    "MPC_ACC_HOR",
]


def test_the_names_clients_ask_for_exist_with_px4_types() -> None:
    for name in CLIENT_NAMES:
        assert name in PARAM_TABLE
    assert PARAM_TABLE["NAV_DLL_ACT"].type == "INT32"
    assert PARAM_TABLE["COM_DL_LOSS_T"].type == "INT32"
    assert PARAM_TABLE["MIS_TAKEOFF_ALT"].type == "REAL32"
    assert list(PARAM_NAMES) == sorted(PARAM_NAMES)


@pytest.mark.parametrize("value", [0, 1, 10, -1, 10040, 2**31 - 1, -(2**31)])
def test_int32_travels_bytewise(value: int) -> None:
    wire = int32_to_wire_float(value)
    assert wire_float_to_int32(wire) == value


def test_small_ints_are_not_their_float_value_on_the_wire() -> None:
    # PX4 puts the int's bytes in the float: 10 becomes a denormal, not 10.0.
    assert int32_to_wire_float(10) != 10.0
    assert int32_to_wire_float(10) == pytest.approx(1.4e-44, rel=0.01)


def test_store_wire_values_and_decoding() -> None:
    store = ParamStore()
    value, kind = store.wire_value("COM_DL_LOSS_T")
    assert kind == MAV_PARAM_TYPE_INT32 and wire_float_to_int32(value) == 10
    value, kind = store.wire_value("MIS_TAKEOFF_ALT")
    assert kind == MAV_PARAM_TYPE_REAL32 and value == 2.5
    decoded = store.decode_wire_value("NAV_DLL_ACT", int32_to_wire_float(2), MAV_PARAM_TYPE_INT32)
    assert decoded == 2


def test_set_checks_range_type_and_notifies() -> None:
    seen: list[tuple[str, float]] = []
    store = ParamStore({"MIS_TAKEOFF_ALT": 5.0}, on_change=lambda n, v: seen.append((n, v)))
    assert store["MIS_TAKEOFF_ALT"] == 5.0
    store.set("NAV_DLL_ACT", 2)
    assert seen == [("NAV_DLL_ACT", 2)]
    with pytest.raises(ValueError, match="within"):
        store.set("MPC_XY_VEL_MAX", 50.0)
    with pytest.raises(ValueError, match="integer"):
        store.set("NAV_DLL_ACT", 1.5)
    with pytest.raises(ValueError, match="finite"):
        store.set("MIS_TAKEOFF_ALT", math.nan)
    with pytest.raises(ValueError, match="unknown"):
        store.set("NOPE", 1.0)
    assert store["MPC_XY_VEL_MAX"] == 12.0


def test_overrides_are_validated() -> None:
    assert validate_overrides({"COM_OBL_RC_ACT": 4.0}) == {"COM_OBL_RC_ACT": 4}
    with pytest.raises(ValueError, match="unknown parameter 'MPC_XY_VEL'"):
        validate_overrides({"MPC_XY_VEL": 1.0})


@pytest.mark.asyncio
async def test_a_flood_of_refused_param_sets_is_answered_but_reported_once_a_second(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """As PX4: every write answered (PARAM_ERROR for an unknown name, no STATUSTEXT; the
    value kept for one out of range), while the log and the links get one report a second."""
    config = EmulatorConfig(
        vehicles=1, ports=free_port_config(1, gcs=False), clock=ClockConfig(speed=2.0)
    )
    caplog.set_level(logging.INFO, logger="sitl.mavlink_receiver")
    async with Emulator(config) as emulator, RawClient(config.ports.api_remote_port(0)) as client:
        await client.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "a heartbeat")
        client.keep_messages = True
        real32 = mavlink.MAV_PARAM_TYPE_REAL32
        for _ in range(100):
            client.send(mavlink.MAVLink_param_set_message(1, 1, b"NO_SUCH_PARAM", 1.0, real32))
            client.send(mavlink.MAVLink_param_set_message(1, 1, b"MPC_XY_VEL_MAX", 1e6, real32))
        with client.matching(lambda m: m.get_type() == "PING" and m.seq == 9) as pong:
            client.send(mavlink.MAVLink_ping_message(0, 9, 0, 0))
            await pong
        await emulator.run_for(0.1)
        kinds = [m.get_type() for m in client.messages]
        errors = [m for m in client.messages if m.get_type() == "PARAM_ERROR"]
        texts = [m.text for m in client.messages if m.get_type() == "STATUSTEXT"]
        echoes = [m for m in client.messages if m.get_type() == "PARAM_VALUE"]
        assert len(errors) == 100 and {e.param_id for e in errors} == {"NO_SUCH_PARAM"}
        assert {e.error for e in errors} == {mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST}
        assert len(echoes) == 100 and {e.param_value for e in echoes} == {12.0}  # kept
        assert texts == [], kinds.count("STATUSTEXT")  # the first report was the unknown one
        assert emulator.autopilot(0).param_sets_rejected == 200
        assert len([r for r in caplog.records if "rejected" in r.getMessage()]) == 1
        await emulator.run_for(1.0)
        client.send(mavlink.MAVLink_param_set_message(1, 1, b"MPC_XY_VEL_MAX", 1e6, real32))
        text = await client.expect(lambda m: m.get_type() == "STATUSTEXT", 3, "a report")
        assert text.text == "Param MPC_XY_VEL_MAX rejected (+199 more)"

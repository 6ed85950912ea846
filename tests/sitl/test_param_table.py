"""The parameters clients read and set: PX4's names, types, ranges and PX4 SITL's values, over the
parameter protocol to MAVSDK's param plugin and a pymavlink ground station."""

from __future__ import annotations

import asyncio
import json
import lzma
import os
import re
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl import Emulator, EmulatorConfig
from sitl.params import (
    FLT_MAX,
    INT32_MAX,
    INT32_MIN,
    MAV_PARAM_TYPE_INT32,
    PARAM_NAMES,
    PARAM_TABLE,
    int32_to_wire_float,
    wire_float_to_int32,
)
from tests.sitl.helpers import Bench, RawClient, free_port_config
from tests.sitl.mavsdk_helpers import api_config, emulated_drones

#: PX4's parameter metadata, as its build generates it (name, type, default, min, max, values).
PX4_METADATA = Path(
    os.environ.get(
        "PX4_PARAMETERS_JSON",
        "/opt/px4/PX4-Autopilot/build/px4_sitl_default/etc/extras/parameters.json.xz",
    )
)

#: What the common client workflows touch, by family (QGroundControl's setup pages, MAVSDK's
#: action/calibration/failure plugins, MAVProxy's parameter files).
WORKFLOW_PARAMS = [
    "BAT1_N_CELLS", "BAT1_V_CHARGED", "BAT1_V_EMPTY", "BAT1_CAPACITY", "BAT_LOW_THR",
    "BAT_CRIT_THR", "BAT_EMERGEN_THR", "CAL_ACC0_ID", "CAL_GYRO0_ID", "CAL_MAG0_ID",
    "CAL_MAG0_ROT", "CAL_BARO0_ID", "CAL_MAG_SIDES", "COM_ARM_WO_GPS", "COM_DL_LOSS_T",
    "COM_LOW_BAT_ACT", "COM_OBL_RC_ACT", "COM_OF_LOSS_T", "COM_RC_IN_MODE", "COM_RC_LOSS_T",
    "COM_FLTMODE1", "COM_DISARM_LAND", "COM_PREARM_MODE", "NAV_DLL_ACT", "NAV_RCL_ACT",
    "NAV_ACC_RAD", "MPC_XY_VEL_MAX", "MPC_XY_CRUISE", "MPC_Z_VEL_MAX_UP", "MPC_TKO_SPEED",
    "MPC_LAND_SPEED", "MIS_TAKEOFF_ALT", "MIS_YAW_TMT", "RTL_RETURN_ALT", "RTL_DESCEND_ALT",
    "RTL_LAND_DELAY", "RTL_TYPE", "GF_ACTION", "GF_MAX_HOR_DIST", "GF_MAX_VER_DIST",
    "SYS_AUTOSTART", "SYS_HAS_MAG", "SYS_FAILURE_EN", "SDLOG_MODE", "SDLOG_PROFILE",
    "MAV_SYS_ID", "MAV_COMP_ID", "MAV_TYPE", "MAV_PROTO_VER", "RC_MAP_THROTTLE",
    "SENS_BOARD_ROT", "EKF2_GPS_CTRL", "EKF2_HGT_REF", "MNT_MODE_IN", "CBRK_SUPPLY_CHK",
]  # fmt: skip


def test_the_workflow_parameters_exist() -> None:
    assert set(WORKFLOW_PARAMS) <= set(PARAM_TABLE)
    assert len(PARAM_TABLE) > 200
    assert list(PARAM_NAMES) == sorted(PARAM_NAMES)  # PX4's order


def test_values_are_px4_sitls_where_clients_look_at_them() -> None:
    # A PX4 SITL SIH quadrotor reports these: sensors calibrated (device ids set), a
    # quadrotor airframe, four cells, failure injection allowed.
    defaults = {name: spec.default for name, spec in PARAM_TABLE.items()}
    assert defaults["CAL_ACC0_ID"] == 1310988 and defaults["CAL_MAG0_ID"] == 197388
    assert defaults["SYS_AUTOSTART"] == 10040 and defaults["MAV_TYPE"] == 2
    assert defaults["BAT1_N_CELLS"] == 4 and defaults["SYS_FAILURE_EN"] == 1
    assert defaults["BAT_LOW_THR"] == pytest.approx(0.15)


def test_every_default_is_in_its_range_and_of_its_type() -> None:
    for spec in PARAM_TABLE.values():
        assert spec.check(spec.default) == spec.default, spec.name
        if spec.type == "INT32":
            assert INT32_MIN <= spec.minimum <= spec.maximum <= INT32_MAX, spec.name
            assert wire_float_to_int32(int32_to_wire_float(int(spec.default))) == spec.default
        else:
            assert -FLT_MAX <= spec.minimum <= spec.maximum <= FLT_MAX, spec.name


@pytest.mark.skipif(not PX4_METADATA.exists(), reason=f"no PX4 build metadata at {PX4_METADATA}")
def test_names_types_and_ranges_are_px4s() -> None:
    with lzma.open(PX4_METADATA) as packed:
        px4 = {p["name"]: p for p in json.load(packed)["parameters"]}
    # The emulator bounds some parameters PX4 leaves open (it flies by them), and keeps its own
    # minimum cell count (it divides by it) and RC input mode range (PX4 v1.15's meanings).
    own_bounds = {"BAT1_N_CELLS", "COM_RC_IN_MODE"}
    for name, spec in PARAM_TABLE.items():
        assert name in px4, f"{name} is no PX4 parameter"
        meta = px4[name]
        assert spec.type == {"Int32": "INT32", "Float": "REAL32"}[meta["type"]], name
        if name in own_bounds:
            continue
        if "min" in meta:
            assert spec.minimum == pytest.approx(meta["min"]), name
        if "max" in meta:
            assert spec.maximum == pytest.approx(meta["max"]), name
        listed = [v["value"] for v in meta.get("values", [])]
        if listed and "min" not in meta:
            assert spec.minimum == min(listed) and spec.maximum == max(listed), name


def test_a_reported_parameter_is_set_and_echoed_but_out_of_range_refused() -> None:
    bench = Bench()
    bench.deliver(
        mavlink.MAVLink_param_set_message(
            1, 1, b"GF_ACTION", int32_to_wire_float(3), MAV_PARAM_TYPE_INT32
        )
    )
    echo = bench.link.sent[-1]
    assert (echo.param_id, wire_float_to_int32(echo.param_value)) == ("GF_ACTION", 3)
    assert echo.param_index == PARAM_NAMES.index("GF_ACTION")
    bench.deliver(mavlink.MAVLink_param_set_message(1, 1, b"BAT_LOW_THR", 0.9, 9))
    assert bench.link.sent[-1].param_value == pytest.approx(0.15)  # PX4 range 0.12..0.5


@pytest.mark.asyncio
async def test_a_ground_station_lists_every_parameter_once_in_order() -> None:
    config = EmulatorConfig(vehicles=1, ports=free_port_config(1))
    async with Emulator(config), RawClient(config.ports.gcs_remote_port) as gcs:
        await gcs.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "a heartbeat")
        gcs.keep_messages = True
        with gcs.matching(
            lambda m: m.get_type() == "PARAM_VALUE" and m.param_index == len(PARAM_NAMES) - 1
        ) as last:
            gcs.send(mavlink.MAVLink_param_request_list_message(1, 1))
            await asyncio.wait_for(last, 3)
        values = [m for m in gcs.messages if m.get_type() == "PARAM_VALUE"]
        assert [m.param_id for m in values] == list(PARAM_NAMES)
        assert {m.param_count for m in values} == {len(PARAM_NAMES)}
        with gcs.matching(lambda m: m.get_type() == "PARAM_VALUE") as reply:
            gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"", 7))
            by_index = await asyncio.wait_for(reply, 3)
        assert by_index.param_id == PARAM_NAMES[7]


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_gets_every_parameter_with_its_type_and_sets_one() -> None:
    async with emulated_drones(api_config()) as (emulator, drones):
        drone = drones[0]
        everything = await drone.param.get_all_params()
        ints = {p.name: p.value for p in everything.int_params}
        floats = {p.name: p.value for p in everything.float_params}
        assert set(ints) | set(floats) == set(PARAM_TABLE)
        assert set(ints) == {n for n, s in PARAM_TABLE.items() if s.type == "INT32"}
        assert ints["CAL_ACC0_ID"] == 1310988 and ints["MNT_MODE_IN"] == -1
        assert floats["BAT1_V_CHARGED"] == pytest.approx(4.05)
        await drone.param.set_param_float("GF_MAX_HOR_DIST", 120.0)
        assert await drone.param.get_param_float("GF_MAX_HOR_DIST") == pytest.approx(120.0)
        assert emulator.autopilot(0).params["GF_MAX_HOR_DIST"] == 120.0


@pytest.mark.asyncio
async def test_the_docs_say_how_many_parameters_a_vehicle_serves() -> None:
    root = Path(__file__).parents[2]
    stated = [
        count
        for doc in (root / "sitl" / "README.md", root / "docs" / "sitl-compatibility.md")
        for count in re.findall(r"^\| parameters \| 897 \| (\d+):", doc.read_text(), re.MULTILINE)
    ]
    assert len(stated) == 2, "the overview and the comparison each state the count once"
    config = EmulatorConfig(vehicles=1, ports=free_port_config(1, gcs=False))
    async with Emulator(config), RawClient(config.ports.api_remote_port(0)) as client:
        await client.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "a heartbeat")
        with client.matching(lambda m: m.get_type() == "PARAM_VALUE") as value:
            client.send(mavlink.MAVLink_param_request_read_message(1, 1, b"", 0))
            served = (await asyncio.wait_for(value, 3)).param_count
    assert [int(count) for count in stated] == [served, served]

"""Emulator settings: defaults, validation, documentation of every field."""

from __future__ import annotations

import contextlib
import socket

import pytest
from pydantic import BaseModel, ValidationError

from sitl import config as cfg
from sitl.config import EmulatorConfig, PortsConfig, udp_port_free


def test_defaults_follow_px4_sitl() -> None:
    config = EmulatorConfig()
    assert config.vehicles == 1
    ports = config.ports
    assert (ports.api_local_port(0, 1), ports.api_remote_port(0)) == (14580, 14540)
    assert (ports.gcs_local_base, ports.gcs_remote_port) == (18570, 14550)
    assert config.clock.mode == "realtime" and config.clock.speed == 1.0


def test_port_layout_with_and_without_px4_sharing() -> None:
    ports = PortsConfig()
    # Own client port per vehicle, skipping the GCS port 14550.
    assert [ports.api_remote_port(i) for i in (0, 9, 10, 49)] == [14540, 14549, 14551, 14590]
    compat = PortsConfig(px4_compat_ports=True)
    assert [compat.api_remote_port(i) for i in (0, 9, 10, 49)] == [14540, 14549, 14549, 14549]


@pytest.mark.parametrize("vehicles", [1, 10, 11, 39, 40, 50, 250])
def test_the_default_layout_works_for_any_vehicle_count(vehicles: int) -> None:
    config = EmulatorConfig(vehicles=vehicles)
    ports = config.ports
    clients = {ports.api_remote_port(i) for i in range(vehicles)}
    binds = {ports.api_local_port(i, vehicles) for i in range(vehicles)}
    binds |= {ports.gcs_local_port(i) for i in range(vehicles)}
    assert len(clients) == vehicles and len(binds) == 2 * vehicles
    assert not clients & binds
    assert ports.gcs_remote_port not in clients | binds
    if vehicles <= 10:  # exactly PX4 SITL
        assert ports.api_local_port(0, vehicles) == 14580
        assert max(clients) == 14539 + vehicles


def test_explicit_overlaps_are_refused() -> None:
    with pytest.raises(ValidationError, match="overlaps"):
        EmulatorConfig(vehicles=5, ports=PortsConfig(api_local_base=14542))
    with pytest.raises(ValidationError, match=r"contains ports\.gcs_remote_port"):
        EmulatorConfig(vehicles=5, ports=PortsConfig(gcs_local_base=14548))


def test_bad_values_are_validation_errors_with_a_path() -> None:
    with pytest.raises(ValidationError) as info:
        EmulatorConfig.model_validate({"vehicles": 0, "clock": {"speed": -1}, "typo": 1})
    locations = {tuple(e["loc"]) for e in info.value.errors()}
    assert ("vehicles",) in locations
    assert ("clock", "speed") in locations
    assert ("typo",) in locations


def test_params_are_checked_by_name_and_range() -> None:
    assert EmulatorConfig(params={"NAV_DLL_ACT": 2}).params == {"NAV_DLL_ACT": 2}
    with pytest.raises(ValidationError, match="unknown parameter"):
        EmulatorConfig(params={"NAV_DLL": 2})
    with pytest.raises(ValidationError, match="within"):
        EmulatorConfig(params={"MPC_XY_VEL_MAX": 99})


def test_faults_are_a_tagged_union_checked_against_the_vehicle_count() -> None:
    config = EmulatorConfig.model_validate(
        {
            "vehicles": 2,
            "faults": [
                {"kind": "kill", "vehicle_index": 1, "at_s": 5},
                {"kind": "link_drop", "vehicle_index": 0, "at_s": 1, "duration_s": 2},
                {"kind": "sensor", "vehicle_index": 0, "sensor": "flow", "at_s": 3},
            ],
        }
    )
    assert [type(f).__name__ for f in config.faults] == [
        "KillFault",
        "LinkDropFault",
        "SensorFault",
    ]
    with pytest.raises(ValidationError, match="only 2 vehicle"):
        EmulatorConfig.model_validate(
            {"vehicles": 2, "faults": [{"kind": "kill", "vehicle_index": 2, "at_s": 0}]}
        )
    with pytest.raises(ValidationError):
        EmulatorConfig.model_validate(
            {"faults": [{"kind": "sensor", "vehicle_index": 0, "sensor": "lidar", "at_s": 0}]}
        )


def test_port_ranges_beyond_65535_are_refused() -> None:
    with pytest.raises(ValidationError, match="exceed 65535"):
        EmulatorConfig(vehicles=10, ports=PortsConfig(api_local_base=65530))


def _models() -> list[type[BaseModel]]:
    return [
        obj
        for obj in vars(cfg).values()
        if isinstance(obj, type) and issubclass(obj, BaseModel) and obj.__module__ == cfg.__name__
    ]


@pytest.mark.parametrize("model", _models(), ids=lambda m: m.__name__)
def test_every_field_has_a_title_and_a_description(model: type[BaseModel]) -> None:
    assert model.model_config.get("extra") == "forbid"
    for name, field in model.model_fields.items():
        assert field.title, f"{model.__name__}.{name} has no title"
        assert field.description, f"{model.__name__}.{name} has no description"


def test_ports_auto_picks_free_ports_for_every_vehicle_and_client():
    # PX4 SITL (or anything else) on the default ports must not stop an emulated run.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as squatter:
        with contextlib.suppress(OSError):  # already held by something else: the point
            squatter.bind(("0.0.0.0", 14580))
        config = EmulatorConfig.model_validate({"vehicles": 3, "ports": "auto"})
    ports = config.ports
    used = [
        *(ports.api_remote_port(i) for i in range(3)),
        *(ports.api_local_port(i, 3) for i in range(3)),
        *(ports.gcs_local_port(i) for i in range(3)),
        ports.gcs_remote_port,
    ]
    assert 14580 not in used and len(set(used)) == len(used)
    assert all(udp_port_free(port) for port in used)

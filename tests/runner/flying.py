"""Helpers for tests that fly scenarios through the full stack (MAVSDK + UDP + emulator)."""

import contextlib
import math
import os
import re
import signal
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from mission_runner.checks import load_scenario
from sitl.config import PortsConfig
from tests.sitl.helpers import free_port_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def flight_configs():
    """Bundled scenarios that carry a ``flight:`` block and fly in one process (the ones on an
    MQTT bus are for vehicle processes: ``test_px4_like_processes.py`` flies them)."""
    names = []
    for path in sorted(CONFIGS.glob("*.yaml")):
        data = yaml.safe_load(path.read_text()) or {}
        if "flight" in data and (data.get("bus") or {}).get("kind") != "mqtt":
            names.append(path.stem)
    return names


def load(name):
    return load_scenario(CONFIGS / f"{name}.yaml")


def free_ports(scenario):
    """Emulator overrides that put every vehicle on free UDP ports (tests run beside real SITL)."""
    return {"ports": free_port_config(len(scenario.vehicles), gcs=False).model_dump()}


def start(*arguments, stdin=subprocess.DEVNULL):
    """``python -m <arguments>`` as a child process, output (both streams) as text lines; its
    stdin /dev/null (never the terminal of whoever runs the tests) unless ``stdin`` says (PIPE:
    the test types commands into ``process.stdin``)."""
    return subprocess.Popen(
        [sys.executable, "-m", *arguments],
        stdin=stdin,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        text=True,
    )


def type_line(process, line):
    """Type ``line`` (and Enter) into ``process``'s stdin."""
    process.stdin.write(line + "\n")
    process.stdin.flush()


def wait_for(process, pattern, seen):
    """Read ``process``'s output until a line matches ``pattern``; every line goes to ``seen``."""
    for line in process.stdout:
        seen.append(line)
        if re.search(pattern, line):
            return line
    raise AssertionError(f"no line matching {pattern!r}:\n{''.join(seen[-40:])}")


def mqtt_scenario_file(tmp_path, broker, name, steps, base="paper_tracking_flyable"):
    """``configs/<base>.yaml`` renamed, shortened to ``steps`` and put on ``broker``'s bus."""
    data = yaml.safe_load((CONFIGS / f"{base}.yaml").read_text())
    data["name"] = name
    data["timing"]["steps"] = steps
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    path = tmp_path / "swarm.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


@dataclass
class Swarm:
    """The processes of a mission flown as it flies for real (see :func:`swarm`)."""

    world: subprocess.Popen
    ports: PortsConfig | None = None
    ground: subprocess.Popen | None = None
    vehicles: list[subprocess.Popen] = field(default_factory=list)
    world_output: str = ""


@contextlib.contextmanager
def swarm(
    scenario,
    tmp_path,
    *,
    vehicles=4,
    ground_arguments=(),
    ground_stdin=subprocess.DEVNULL,
    gcs=False,
    world_arguments=(),
):
    """``mission-runner emulate`` (emulator and world, on free ports; the vehicles' GCS links
    too with ``gcs``; more of its options in ``world_arguments``), then a ``ground`` station
    (its stdin ``ground_stdin``) and one ``vehicle``
    process per drone, all on the scenario's bus. Processes still running at the end are killed,
    the world is stopped and its output kept in ``world_output``."""
    ports = free_port_config(vehicles, gcs=gcs)
    gcs_arguments = (
        [
            "--gcs-port-base",
            str(ports.gcs_local_base),
            "--gcs-remote-port",
            str(ports.gcs_remote_port),
        ]
        if gcs
        else ["--no-gcs"]
    )
    world = start(
        "mission_runner.cli",
        "emulate",
        scenario,
        *gcs_arguments,
        "--api-port-base",
        str(ports.api_remote_base),
        "--api-local-port-base",
        str(ports.api_local_base),
        *world_arguments,
    )
    flying = Swarm(world, ports=ports)
    try:
        wait_for(world, "world on the mqtt bus", [])
        flying.ground = start(
            "mission_runner.cli", "ground", scenario, *ground_arguments, stdin=ground_stdin
        )
        flying.vehicles = [
            start(
                "mission_runner.cli",
                "vehicle",
                scenario,
                "--id",
                str(i + 1),
                "--url",
                f"udpin://0.0.0.0:{ports.api_remote_base + i}",
                "--out",
                str(tmp_path / f"vehicle_{i + 1}"),
            )
            for i in range(vehicles)
        ]
        yield flying
    finally:
        for process in [flying.ground, *flying.vehicles]:
            if process is not None:
                if process.poll() is None:
                    process.kill()
                process.communicate(timeout=30)  # reaped, its pipes closed (a failed test too)
        world.send_signal(signal.SIGINT)
        flying.world_output, _ = world.communicate(timeout=30)


#: PX4's custom mode of OFFBOARD (main mode 6).
OFFBOARD_MODE = 6 << 16


@dataclass
class StreamAfterTakeover:
    """What a vehicle's tlog (the emulator's, both directions in order) shows after someone
    other than the runner took it (its first heartbeat no longer armed in OFFBOARD after one
    that was): see :func:`stream_after_takeover`."""

    #: Runner setpoints (SET_POSITION_TARGET_LOCAL_NED from MAVSDK, system 245) that reached
    #: the vehicle after that heartbeat, before the runner's mode command (if any) ...
    setpoints_before_hold: int
    #: ... and after that command (the HOLD of its ``offboard.stop()``), up to the end.
    setpoints_after_hold: int
    #: Whether the runner sent a mode command (DO_SET_MODE from 245) after the takeover at all.
    hold_sent: bool
    #: Whether a heartbeat showed the vehicle armed again after a disarm (the pilot's re-arm).
    rearmed: bool
    #: PX4 custom modes in the heartbeats while armed again.
    modes_after_rearm: set[int]
    #: The greatest height above home (GLOBAL_POSITION_INT) after the re-arm [m].
    highest_after_rearm_m: float


def stream_after_takeover(tlog_path, system_id):
    """Read ``tlog_path`` (vehicle ``system_id``'s) into a :class:`StreamAfterTakeover`."""
    from pymavlink import mavutil

    armed_bit = mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    log = mavutil.mavlink_connection(str(tlog_path), dialect="common")
    phase = "flying"  # -> "taken" -> "held" (the runner's mode command seen)
    driven = was_armed = rearmed = False
    counts = {"taken": 0, "held": 0}
    modes: set[int] = set()
    highest_m = -math.inf
    with contextlib.closing(log):
        messages = list(iter(log.recv_match, None))
    for message in messages:
        kind, source = message.get_type(), message.get_srcSystem()
        if kind == "HEARTBEAT" and source == system_id and message.get_srcComponent() == 1:
            armed = bool(message.base_mode & armed_bit)
            in_offboard = armed and message.custom_mode == OFFBOARD_MODE
            driven = driven or in_offboard
            if phase == "flying" and driven and not in_offboard:
                phase = "taken"
            elif phase != "flying" and armed and not was_armed:
                rearmed = True
            if armed and rearmed:
                modes.add(message.custom_mode)
            was_armed = armed
        elif kind == "SET_POSITION_TARGET_LOCAL_NED" and source == 245 and phase != "flying":
            counts[phase] += 1
        elif kind == "COMMAND_LONG" and source == 245 and phase == "taken":
            if message.command == mavutil.mavlink.MAV_CMD_DO_SET_MODE:
                phase = "held"
        elif kind == "GLOBAL_POSITION_INT" and source == system_id and rearmed:
            highest_m = max(highest_m, message.relative_alt / 1000.0)
    return StreamAfterTakeover(
        counts["taken"], counts["held"], phase == "held", rearmed, modes, highest_m
    )

"""Helpers for tests that fly scenarios through the full stack (MAVSDK + UDP + emulator)."""

import os
import subprocess
import sys
from pathlib import Path

import yaml

from mission_runner.config import load_scenario
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


def start(*arguments):
    """``python -m <arguments>`` as a child process, output (both streams) as text lines."""
    return subprocess.Popen(
        [sys.executable, "-m", *arguments],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        text=True,
    )

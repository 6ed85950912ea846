"""Helpers for tests that fly scenarios through the full stack (MAVSDK + UDP + emulator)."""

from pathlib import Path

import yaml

from mission_runner.config import load_scenario
from tests.sitl.helpers import free_port_config

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def flight_configs():
    """Bundled scenarios that carry a ``flight:`` block: the ones meant to be flown."""
    return sorted(
        path.stem
        for path in CONFIGS.glob("*.yaml")
        if "flight" in (yaml.safe_load(path.read_text()) or {})
    )


def load(name):
    return load_scenario(CONFIGS / f"{name}.yaml")


def free_ports(scenario):
    """Emulator overrides that put every vehicle on free UDP ports (tests run beside real SITL)."""
    return {"ports": free_port_config(len(scenario.vehicles), gcs=False).model_dump()}

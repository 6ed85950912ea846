"""MAVProxy, an unmodified third-party ground station, against an emulated vehicle's GCS link.

MAVProxy asks for the parameters as ArduPilot's @PARAM/param.pck over MAVLink FTP first. PX4
answers FILE_NOT_FOUND and MAVProxy falls back to PARAM_REQUEST_LIST at once, as it does here by
default (before the emulator spoke FTP, MAVProxy waited 11 s for its FTP request to time out);
with ``ftp.ardupilot_extensions`` the parameters come over FTP.
"""

import asyncio
import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from sitl.config import EmulatorConfig, FtpConfig
from sitl.emulator import Emulator
from sitl.params import PARAM_NAMES
from tests.sitl.helpers import free_port_config

pytestmark = [
    pytest.mark.asyncio,
    pytest.mark.skipif(
        shutil.which("mavproxy.py") is None,
        reason="MAVProxy is not installed (pip install -e '.[test]')",
    ),
    pytest.mark.timeout(90),
]


async def mavproxy_until_parameters(
    port: int, cwd: Path, last_line: str = "Received"
) -> tuple[list[str], float]:
    """Run MAVProxy on udpin ``port`` until it prints a line starting with ``last_line`` (by
    default: it has the parameters); its output and the seconds from detecting the vehicle to
    having the parameters."""
    mavproxy = shutil.which("mavproxy.py")
    assert mavproxy is not None
    process = await asyncio.create_subprocess_exec(
        mavproxy,
        f"--master=udpin:127.0.0.1:{port}",
        "--non-interactive",
        cwd=cwd,  # it writes mav.tlog and mav.parm where it runs
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert process.stdout is not None
    seen: list[str] = []
    detected_at: float | None = None
    received_at: float | None = None
    try:
        async with asyncio.timeout(60):
            while not any(line.startswith(last_line) for line in seen):
                raw = await process.stdout.readline()
                if not raw:
                    break
                line = raw.decode(errors="replace").strip()
                seen.append(line)
                if line.startswith("Detected vehicle"):
                    detected_at = time.monotonic()
                if line.startswith("Received") and received_at is None:
                    received_at = time.monotonic()
    finally:
        process.kill()
        await process.wait()
    assert detected_at is not None and received_at is not None, "\n".join(seen)
    return seen, received_at - detected_at


async def test_mavproxy_detects_the_vehicle_and_falls_back_at_once_as_with_px4(
    tmp_path: Path,
) -> None:
    ports = free_port_config(1, gcs=True)
    async with Emulator(EmulatorConfig(vehicles=1, ports=ports)):
        seen, took_s = await mavproxy_until_parameters(ports.gcs_remote_port, tmp_path)
    text = "\n".join(seen)
    assert "Detected vehicle 1:1" in text, text
    assert "LOITER" in text, text  # PX4's HOLD as MAVProxy names it
    assert f"Received {len(PARAM_NAMES)} parameters" in seen, text
    assert "FTP: request timed out" not in text, text  # the FILE_NOT_FOUND came back
    assert took_s < 8.0, text  # MAVProxy re-asks once a second; its FTP timeout was 11 s


async def test_mavproxy_downloads_the_parameters_over_ftp_with_ardupilots_extensions(
    tmp_path: Path,
) -> None:
    ports = free_port_config(1, gcs=True)
    config = EmulatorConfig(
        vehicles=1,
        ports=ports,
        ftp=FtpConfig(ardupilot_extensions=True),
        params={"NAV_DLL_ACT": 2, "MIS_TAKEOFF_ALT": 4.5},
    )
    async with Emulator(config):
        # It says so once it has written mav.parm.
        seen, took_s = await mavproxy_until_parameters(
            ports.gcs_remote_port, tmp_path, last_line=f"Saved {len(PARAM_NAMES)} parameters"
        )
    text = "\n".join(seen)
    assert f"Received {len(PARAM_NAMES)} parameters (ftp)" in seen, text
    assert took_s < 8.0, text
    saved = dict(
        line.split()[:2] for line in (tmp_path / "mav.parm").read_text().splitlines() if line
    )
    assert set(saved) == set(PARAM_NAMES)
    assert float(saved["NAV_DLL_ACT"]) == 2 and float(saved["MIS_TAKEOFF_ALT"]) == 4.5
    assert float(saved["CAL_ACC0_ID"]) == 1310988

"""MAVProxy, an unmodified third-party ground station, against an emulated vehicle's GCS link."""

import asyncio
import os
import shutil
import subprocess

import pytest

from sitl.config import EmulatorConfig
from sitl.emulator import Emulator
from tests.sitl.helpers import free_port_config

pytestmark = pytest.mark.asyncio

MAVPROXY = shutil.which("mavproxy.py")


@pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (pip install -e '.[test]')")
@pytest.mark.timeout(90)
async def test_mavproxy_detects_the_vehicle_its_mode_and_downloads_the_parameters(tmp_path):
    ports = free_port_config(1, gcs=True)
    async with Emulator(EmulatorConfig(vehicles=1, ports=ports)):
        process = await asyncio.create_subprocess_exec(
            MAVPROXY,
            f"--master=udpin:127.0.0.1:{ports.gcs_remote_port}",
            "--non-interactive",
            cwd=tmp_path,  # it writes mav.tlog and mav.parm where it runs
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        seen = []
        try:
            while not any("Received" in line and "parameters" in line for line in seen):
                line = await process.stdout.readline()
                if not line:
                    break
                seen.append(line.decode(errors="replace").strip())
        finally:
            process.kill()
            await process.wait()
    text = "\n".join(seen)
    assert "Detected vehicle 1:1" in text, text
    assert "LOITER" in text, text  # PX4's HOLD as MAVProxy names it
    assert any(line.startswith("Received") and "parameters" in line for line in seen), text

"""The ``sitl`` command: settings from YAML and options, clean start and stop."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from sitl.cli import build_parser, load_config, main
from tests.sitl.helpers import free_port_config

REPO = Path(__file__).resolve().parents[2]


def test_options_override_the_yaml_file(tmp_path: Path) -> None:
    settings = tmp_path / "scenario.yaml"
    settings.write_text(
        "emulator:\n  vehicles: 3\n  clock: {speed: 2.0}\n  params: {MIS_TAKEOFF_ALT: 4.0}\n"
    )
    args = build_parser().parse_args(
        ["--config", str(settings), "--speed", "4", "--api-port-base", "24540", "--no-gcs"]
    )
    config = load_config(args)
    assert config.vehicles == 3
    assert config.clock.speed == 4.0
    assert config.params == {"MIS_TAKEOFF_ALT": 4.0}
    assert config.ports.api_remote_port(0) == 24540
    assert config.ports.api_local_port(0, 3) == 24580
    assert not config.ports.gcs_enabled


def test_invalid_settings_exit_with_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--vehicles", "0"]) == 2
    assert "vehicles" in capsys.readouterr().err


def test_a_taken_port_exits_with_1_and_says_which(capsys: pytest.CaptureFixture[str]) -> None:
    ports = free_port_config(1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as blocker:
        blocker.bind(("0.0.0.0", ports.gcs_local_base))
        code = main(
            [
                "--api-port-base",
                str(ports.api_remote_base),
                "--api-local-port-base",
                str(ports.api_local_base),
                "--gcs-port-base",
                str(ports.gcs_local_base),
                "--gcs-remote-port",
                str(ports.gcs_remote_port),
            ]
        )
    assert code == 1
    err = capsys.readouterr().err
    assert str(ports.gcs_local_base) in err and "--gcs-port-base" in err


def test_runs_until_sigterm_and_writes_tlogs(tmp_path: Path) -> None:
    ports = free_port_config(2)
    command = [
        sys.executable,
        "-m",
        "sitl",
        "--vehicles",
        "2",
        "--speed",
        "5",
        "--api-port-base",
        str(ports.api_remote_base),
        "--api-local-port-base",
        str(ports.api_local_base),
        "--gcs-port-base",
        str(ports.gcs_local_base),
        "--gcs-remote-port",
        str(ports.gcs_remote_port),
        "--tlog-dir",
        str(tmp_path),
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as client,
        subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO
        ) as process,
    ):
        client.bind(("127.0.0.1", ports.api_remote_base))
        client.settimeout(10)
        assert process.stdout is not None
        lines = [process.stdout.readline() for _ in range(3)]
        assert "2 vehicle(s) ready" in lines[0]
        assert f"udpin://0.0.0.0:{ports.api_remote_base}" in lines[1]
        assert client.recv(2048)  # telemetry flows
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=10)
    assert process.returncode == 0, err
    assert "stopped after" in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["vehicle_001.tlog", "vehicle_002.tlog"]
    assert (tmp_path / "vehicle_001.tlog").stat().st_size > 0

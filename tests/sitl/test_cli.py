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


def test_sih_fidelity_options() -> None:
    args = build_parser().parse_args(
        [
            "--vehicles",
            "3",
            "--host-unix-time",
            "--boot-offset-spread",
            "12",
            "--gps-bias-std",
            "0.3",
            "--gps-bias-time",
            "45",
            "--gps-noise-std",
            "0.05",
            "--truth-stream",
            "--truth-rate",
            "50",
            "--truth-port-base",
            "29450",
            "--truth-remote-port-base",
            "29410",
            "--deny-arming",
            "1",
            "--deny-arming",
            "2:3",
        ]
    )
    config = load_config(args)
    assert config.clock.unix_time == "host" and config.clock.speed == 1.0
    assert config.boot_clock.spread_s == 12.0 and config.boot_clock.offset_s == []
    gps = config.gps_error
    assert (gps.bias_std_m, gps.bias_time_constant_s, gps.noise_std_m) == (0.3, 45.0, 0.05)
    truth = config.truth_stream
    assert (truth.enabled, truth.rate_hz, truth.local_base, truth.remote_base) == (
        True,
        50.0,
        29450,
        29410,
    )
    assert [(f.kind, f.vehicle_index, f.count) for f in config.faults] == [
        ("deny_arming", 1, 1),
        ("deny_arming", 2, 3),
    ]
    offsets = load_config(build_parser().parse_args(["-n", "2", "--boot-offsets", "0", "7.5"]))
    assert offsets.boot_clock.offset_s == [0.0, 7.5]


def test_sih_like_preset_under_file_and_options(tmp_path: Path) -> None:
    plain = load_config(build_parser().parse_args([]))
    assert plain.clock.unix_time == "simulated" and not plain.truth_stream.enabled
    assert not plain.gps_error.active and plain.boot_clock.spread_s == 0.0
    sih = load_config(build_parser().parse_args(["--sih-like"]))
    assert sih.clock.speed == 0.986 and sih.clock.unix_time == "host"
    assert sih.truth_stream.enabled and sih.gps_error.bias_std_m == 0.2
    assert sih.boot_clock.spread_s == 10.0
    settings = tmp_path / "emulator.yaml"
    settings.write_text("gps_error: {bias_std_m: 0.5}\ntruth_stream: {rate_hz: 10}\n")
    mixed = load_config(
        build_parser().parse_args(
            ["--config", str(settings), "--sih-like", "--speed", "2", "--boot-offsets", "3"]
        )
    )
    assert mixed.gps_error.bias_std_m == 0.5  # the file wins over the preset
    assert mixed.gps_error.bias_time_constant_s == 30.0  # the preset fills the rest
    assert mixed.truth_stream.rate_hz == 10.0 and mixed.truth_stream.enabled
    assert mixed.clock.speed == 2.0  # options win over both
    assert mixed.boot_clock.offset_s == [3.0] and mixed.boot_clock.spread_s == 0.0


def test_a_bad_deny_arming_option_exits_with_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--deny-arming", "one"]) == 2
    assert "--deny-arming" in capsys.readouterr().err
    assert main(["--deny-arming", "3"]) == 2  # only one vehicle
    assert "vehicle_index" in capsys.readouterr().err


def test_with_a_scenario_only_the_fidelity_options_given_override_its_emulator() -> None:
    from sitl.cli import fidelity_overrides

    plain = load_config(build_parser().parse_args([]))
    assert fidelity_overrides(plain, {"faults": [{"kind": "kill"}]}) == {}
    given = load_config(
        build_parser().parse_args(["-n", "2", "--gps-bias-std", "0.3", "--deny-arming", "1"])
    )
    overrides = fidelity_overrides(given, {"faults": [{"kind": "kill"}]})
    assert set(overrides) == {"gps_error", "faults"}
    assert overrides["gps_error"]["bias_std_m"] == 0.3
    assert [f["kind"] for f in overrides["faults"]] == ["kill", "deny_arming"]


def test_the_old_scenario_option_points_to_the_mission_runner(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["--scenario", "configs/paper_tracking_flyable.yaml"]) == 2
    err = capsys.readouterr().err
    assert "mission-runner emulate configs/paper_tracking_flyable.yaml" in err

"""`mission-runner run` when something it needs is not there: one line, a runtime-failure exit
code, nothing left running (the command returns, so its emulator and tasks ended)."""

import json
import socket

import pytest
import yaml

from mission_runner.cli import EXIT_BAD_INPUT, EXIT_RUNTIME_FAILURE, main
from tests.sitl.helpers import free_port_config

from .flying import CONFIGS


def closed_port():
    """A TCP port nothing listens on (bound, then released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.timeout(60)
def test_an_unreachable_broker_fails_the_run_in_bounded_time_with_one_line(tmp_path, capsys):
    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["name"] = "no_broker"
    data["bus"] = {"kind": "mqtt", "mqtt": {"port": closed_port(), "connect_timeout_s": 2.0}}
    data["flight"]["emulator"] = {"ports": free_port_config(4).model_dump()}
    path = tmp_path / "no_broker.yaml"
    path.write_text(yaml.safe_dump(data))

    code = main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet", "--no-figures"])

    assert code == EXIT_RUNTIME_FAILURE
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith("error: bus 127.0.0.1:") and "no connection within 2 s" in error
    # The summary says why, as the terminal does (not "unhandled errors in a TaskGroup").
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["status"] == "error"
    assert summary["detail"] == error.removeprefix("error: ")


@pytest.mark.timeout(60)
def test_a_taken_mavsdk_port_is_one_line_naming_the_setting(tmp_path, capsys):
    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    ports = free_port_config(4)
    data["flight"]["emulator"] = {"ports": ports.model_dump()}
    path = tmp_path / "taken.yaml"
    path.write_text(yaml.safe_dump(data))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:  # as a ground station would
        taken.bind(("0.0.0.0", ports.api_remote_base))
        code = main(["run", str(path), "--out", str(tmp_path / "out"), "--quiet", "--no-figures"])

    assert code == EXIT_RUNTIME_FAILURE
    error = capsys.readouterr().err
    assert error.count("\n") == 1, error
    assert error.startswith(f"error: MAVSDK cannot open udpin://0.0.0.0:{ports.api_remote_base}")
    assert "flight.emulator.ports.api_remote_base" in error
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["status"] == "error" and "BIND_ERROR" in summary["detail"]


@pytest.mark.timeout(120)
def test_a_vehicle_id_beyond_mavlink_is_bad_input_before_anything_flies(tmp_path, capsys):
    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["timing"]["steps"] = 8
    data["expect"] = {}
    data["vehicles"][3]["id"] = 256
    data["flight"]["emulator"] = {"ports": free_port_config(4).model_dump()}
    path = tmp_path / "ids.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"

    code = main(["run", str(path), "--out", str(out), "--quiet", "--no-figures"])

    assert code == EXIT_BAD_INPUT
    assert "vehicles[3].id: 256 is not a MAVLink system id (1..255)" in capsys.readouterr().err
    assert not out.exists()

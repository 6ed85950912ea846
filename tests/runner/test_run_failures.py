"""`mission-runner run` when something it needs is not there: one line, a runtime-failure exit
code, nothing left running (the command returns, so its emulator and tasks ended)."""

import socket

import pytest
import yaml

from mission_runner.cli import EXIT_RUNTIME_FAILURE, main
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

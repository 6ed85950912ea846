"""A run's recording written by a process of its own (``mission-runner run``): the same file as
written in the command's process, in before summary.json, and still written when the worker has
died."""

from pathlib import Path

import pytest
import yaml

from mission_runner.checks import validate_scenario
from mission_runner.figure_process import RecordingProcess
from mission_runner.outputs import write_results
from mission_runner.recording import RECORDING
from mission_runner.sim.simulator import simulate

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture(scope="module")
def result():
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["timing"]["steps"] = 20
    return simulate(validate_scenario(data, "paper_tracking (short)"))


def test_the_recording_written_in_its_process_is_the_one_written_here(tmp_path, result, caplog):
    here, there = tmp_path / "here", tmp_path / "there"
    write_results(result, here, figures=False)
    with RecordingProcess() as recording:
        write_results(result, there, figures=False, recording_process=recording)
        # In when write_results returns, not when the worker gets round to it.
        written = (there / RECORDING).read_bytes()
    assert "process failed" not in caplog.text  # the worker wrote it
    assert written == (here / RECORDING).read_bytes()
    assert sorted(p.name for p in there.iterdir()) == sorted(p.name for p in here.iterdir())


def test_the_recording_is_written_here_when_the_worker_has_died(tmp_path, result, caplog):
    with RecordingProcess() as recording:
        recording.start()
        worker = recording._process
        worker.kill()
        worker.wait(timeout=10)
        write_results(result, tmp_path, figures=False, recording_process=recording)
    assert "recording process failed" in caplog.text
    assert (tmp_path / RECORDING).stat().st_size > 0
    assert not list(tmp_path.glob(".*.partial")), "a temporary file was left behind"

"""A run's recording written by a process of its own (``mission-runner run``): the same file as
written in the command's process, in before summary.json, and still written when the worker has
died."""

import logging
from pathlib import Path

import pytest
import yaml

from mission_runner.checks import validate_scenario
from mission_runner.figure_process import RecordingProcess
from mission_runner.outputs import write_results
from mission_runner.recording import RECORDING, LogLine, read_recording, write_recording
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


def _lines(result):
    """Log lines as a flight's capture has them: before k = 0, during the steps, and the
    landing's, stamped with the last step's time."""
    step_s = result.scenario.timing.step_s
    last_s = (result.commands_m_s.shape[1] - 1) * step_s
    return [
        LogLine(None, logging.INFO, "runner", "armed"),
        LogLine(3 * step_s, logging.WARNING, "runner", "a range dropped"),
        LogLine(last_s, logging.INFO, "runner", "landing detected"),
        LogLine(last_s, logging.INFO, "runner", "disarmed"),
    ]


def _messages(path):
    return sorted((m.topic, m.log_time_ns, repr(m.message)) for m in read_recording(path))


def test_a_recording_handed_in_two_parts_holds_what_one_hand_over_writes(tmp_path, result):
    """A flight hands its mission's steps before it lands, the landing's lines and the verdict
    after: the file holds the same messages as one written at once, the landing's lines after
    the steps; and a worker that died writes the same file here."""
    lines, verdict = _lines(result), "expectations: PASS"
    write_recording(result, tmp_path / "once.mcap", logs=lines, verdict=verdict)
    written = {}
    for name, kill in (("worker", False), ("here", True)):
        path = tmp_path / f"{name}.mcap"
        with RecordingProcess() as recording:
            recording.start()
            if kill:
                recording._process.kill()
                recording._process.wait(timeout=10)
            recording.submit_mission(result, path, records={}, start_s=0.0, logs=lines[:2])
            assert not path.exists()
            recording.submit(result, path, records={}, start_s=0.0, logs=lines, verdict=verdict)
            recording.collect(result, path)
        written[name] = path.read_bytes()
    assert written["worker"] == written["here"]
    assert _messages(tmp_path / "worker.mcap") == _messages(tmp_path / "once.mcap")
    events = [
        m.message.message
        for m in read_recording(tmp_path / "worker.mcap", topics=["/log", "/mission/events"])
    ]
    assert events[-3:] == ["landing detected", "disarmed", verdict]


def test_a_run_that_ends_between_the_parts_leaves_no_recording(tmp_path, result):
    path = tmp_path / RECORDING
    with RecordingProcess() as recording:
        recording.submit_mission(result, path, records={}, start_s=0.0, logs=_lines(result))
    # Leaving ended the worker's input: it wrote nothing, and left no temporary file
    assert sorted(p.name for p in tmp_path.iterdir()) == []

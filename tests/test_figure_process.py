"""Figures drawn in a process of their own (``mission-runner run``): the same files as drawn in
the command's process, all written before summary.json names them, and still written when the
worker process has died."""

import json
from pathlib import Path

import pytest
import yaml

from mission_runner.checks import validate_scenario
from mission_runner.figure_process import FigureProcess
from mission_runner.outputs import write_results
from mission_runner.sim.simulator import simulate

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
FIGURES = ["xy.png", "phases.png", "localization_error.png", "tracking_error.png"]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def result():
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["timing"]["steps"] = 40
    return simulate(validate_scenario(data, "paper_tracking (short)"))


def assert_figures_written(out_dir: Path) -> None:
    document = json.loads((out_dir / "summary.json").read_text())
    assert document["figures"] == FIGURES
    for name in FIGURES:
        assert (out_dir / name).read_bytes().startswith(PNG_SIGNATURE), name
    assert not list(out_dir.glob(".*.partial")), "a temporary file was left behind"


def test_figures_drawn_in_their_process_are_in_before_the_summary(tmp_path, result):
    here, there = tmp_path / "here", tmp_path / "there"
    write_results(result, here, figures=True)
    with FigureProcess() as figures:
        write_results(result, there, figures=True, figure_process=figures)
        # Written when write_results returns, not when the worker gets round to it.
        assert_figures_written(there)
    for name in FIGURES:
        assert (there / name).stat().st_size > 0
    assert sorted(p.name for p in there.iterdir()) == sorted(p.name for p in here.iterdir())


def test_figures_are_drawn_here_when_the_worker_has_died(tmp_path, result, caplog):
    with FigureProcess() as figures:
        figures.start()
        worker = figures._process
        worker.kill()
        worker.wait(timeout=10)
        write_results(result, tmp_path, figures=True, figure_process=figures)
    assert "figure process failed" in caplog.text
    assert_figures_written(tmp_path)


def test_a_worker_never_handed_a_result_leaves_without_drawing(tmp_path):
    with FigureProcess() as figures:
        figures.start()
        worker = figures._process
    assert worker.returncode == 0
    assert not list(tmp_path.iterdir())


def test_no_figures_asked_for_none_drawn(tmp_path, result):
    with FigureProcess() as figures:
        document = write_results(result, tmp_path, figures=False, figure_process=figures)
    assert "figures" not in document
    assert not list(tmp_path.glob("*.png"))

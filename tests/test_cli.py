"""``mission-runner simulate`` end to end, in-process."""

import csv
import json
from pathlib import Path

import yaml

from mission_runner.cli import EXIT_BAD_INPUT, EXIT_EXPECTATION_FAILED, EXIT_OK, main

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_simulate_writes_summary_timeseries_and_figures(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["simulate", str(CONFIGS / "paper_tracking.yaml"), "--out", str(out)]) == EXIT_OK
    summary = json.loads((out / "summary.json").read_text())
    assert summary["expectations"]["passed"] is True
    assert summary["metrics"]["final_tracking_error_m"] < 0.05
    assert summary["parameters"]["algorithm"]["beta"] == 7.0
    assert set(summary["versions"]) >= {"mission_runner", "numpy", "python"}
    rows = list(csv.DictReader((out / "timeseries.csv").read_text().splitlines()))
    assert len(rows) == 601
    assert float(rows[-1]["tracking_error_m"]) < 0.05
    assert {"v1_north_m", "v4_phase_rad", "v2_cmd_east_m_s"} <= set(rows[0])
    for name in ("xy.png", "phases.png", "localization_error.png", "tracking_error.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob(".*.partial"))
    assert "expectations: PASS" in capsys.readouterr().out


def test_batch_writes_the_distribution(tmp_path):
    out = tmp_path / "batch"
    code = main(
        [
            "simulate",
            str(CONFIGS / "paper_tracking.yaml"),
            "--out",
            str(out),
            "--runs",
            "8",
            "--no-figures",
            "--quiet",
        ]
    )
    assert code == EXIT_OK
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 8
    assert summary["batch"]["final_tracking_error_m"]["worst"] < 0.05
    assert len((out / "batch.csv").read_text().splitlines()) == 9


def test_failed_expectation_exits_1(tmp_path):
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["expect"] = {"tracking_converged_step": {"max": 10}}
    config = tmp_path / "strict.yaml"
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    code = main(["simulate", str(config), "--out", str(out), "--no-figures", "--quiet"])
    assert code == EXIT_EXPECTATION_FAILED
    assert json.loads((out / "summary.json").read_text())["expectations"]["passed"] is False


def test_bad_config_writes_nothing_and_names_the_path(tmp_path, capsys):
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["algorithm"]["forgetting_factor"] = 1.5
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "never"
    assert main(["simulate", str(config), "--out", str(out)]) == EXIT_BAD_INPUT
    assert not out.exists()
    assert "algorithm.forgetting_factor" in capsys.readouterr().err

"""Parameter sweeps over the batched simulator."""

import csv
import io
from pathlib import Path

import pytest

from mission_runner.checks import load_scenario, validate_scenario
from mission_runner.cli import EXIT_BAD_INPUT, EXIT_OK, main
from mission_runner.errors import ConfigError
from mission_runner.sim.sweep import Axis, set_path, sweep, sweep_csv

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def short(steps=60):
    data = load_scenario(CONFIGS / "paper_tracking.yaml").model_dump(mode="json")
    data["timing"]["steps"] = steps
    return validate_scenario(data)


def test_values_are_read_as_yaml():
    axis = Axis.parse("algorithm.estimator_settings.gate_chi2=9,null,10.5")
    assert axis.values == (9, None, 10.5)
    assert Axis.parse("algorithm.estimator=rlse,ekf").values == ("rlse", "ekf")
    for bad in ("algorithm.beta", "=1,2", "algorithm..beta=1", "[0].x=1"):
        with pytest.raises(ValueError, match=r"PATH=V1|not a YAML path"):
            Axis.parse(bad)


def test_paths_reach_list_items_and_every_item():
    data = short().model_dump(mode="json")
    set_path(data, "vehicles[1].speed_limit_m_s", 11.0)
    set_path(data, "vehicles[*].altitude_m", 3.0)
    set_path(data, "algorithm.estimator_settings.gate_chi2", None)
    assert [v["speed_limit_m_s"] for v in data["vehicles"]] == [10.0, 11.0, 10.0, 10.0]
    assert {v["altitude_m"] for v in data["vehicles"]} == {3.0}
    assert data["algorithm"]["estimator_settings"]["gate_chi2"] is None
    with pytest.raises(KeyError, match=r"vehicles\[9\]"):
        set_path(data, "vehicles[9].speed_limit_m_s", 1.0)


def test_a_bad_value_is_named_at_its_path_before_anything_runs():
    with pytest.raises(ConfigError) as caught:
        sweep(short(), [Axis("algorithm.beta", (7.0, 9.0))], runs=2, source="x.yaml")
    assert "x.yaml with algorithm.beta=9.0" in str(caught.value)
    assert caught.value.problems[0][0] == "algorithm.beta"


def test_every_combination_is_simulated_and_tabled():
    axes = [Axis("algorithm.estimator", ("rlse", "ekf")), Axis("seed", (1, 2, 3))]
    points = sweep(short(), axes, runs=2)
    assert [tuple(p.values.values()) for p in points] == [
        (e, s) for e in ("rlse", "ekf") for s in (1, 2, 3)
    ]
    rows = list(csv.DictReader(io.StringIO(sweep_csv(points))))
    assert len(rows) == 6
    assert rows[0]["runs"] == "2" and rows[3]["algorithm.estimator"] == "ekf"
    assert float(rows[0]["tail_tracking_error_rms_m_p95"]) >= float(
        rows[0]["tail_tracking_error_rms_m_p5"]
    )


def test_the_command_writes_the_table_and_the_figure(tmp_path):
    config = tmp_path / "short.yaml"
    config.write_text(
        (CONFIGS / "paper_tracking.yaml").read_text().replace("steps: 600", "steps: 40")
    )
    out = tmp_path / "sweep"
    arguments = ["--set", "algorithm.forgetting_factor=0.7,0.9", "--runs", "2", "--quiet"]
    code = main(["sweep", str(config), *arguments, "--out", str(out)])
    assert code == EXIT_OK
    assert (out / "sweep.csv").read_text().count("\n") == 3
    assert (out / "sweep.png").stat().st_size > 0
    bad = ["sweep", str(config), "--set", "algorithm.forgetting_factor=2", "--out", str(out)]
    assert main([*bad, "--quiet"]) == EXIT_BAD_INPUT

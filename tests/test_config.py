"""Every invalid scenario stops with one clear error naming the YAML path and the rule."""

from pathlib import Path

import pytest
import yaml

from mission_runner.config import load_scenario, parse_scenario
from mission_runner.errors import ConfigError

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def base():
    return yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())


def problems_of(data):
    with pytest.raises(ConfigError) as caught:
        parse_scenario(yaml.safe_dump(data), source="test.yaml")
    assert str(caught.value).startswith("test.yaml: invalid scenario")
    return caught.value.problems


def edit(path, value):
    data = base()
    *parents, last = path
    node = data
    for key in parents:
        node = node[key]
    if value is DELETE:
        del node[last]
    else:
        node[last] = value
    return data


DELETE = object()


@pytest.mark.parametrize(
    ("path", "value", "where", "rule"),
    [
        (("algorithm", "beta"), 8.0, "algorithm.beta", "must be < 1/timing.step_s = 8"),
        (("algorithm", "beta"), 9.5, "algorithm.beta", "must be < 1/timing.step_s"),
        (("algorithm", "forgetting_factor"), 0.0, "algorithm.forgetting_factor", "greater than 0"),
        (
            ("algorithm", "forgetting_factor"),
            1.5,
            "algorithm.forgetting_factor",
            "less than or equal to 1",
        ),
        (("algorithm", "radius_m"), 0.0, "algorithm.radius_m", "greater than 0"),
        (("algorithm", "radius_m"), float("nan"), "algorithm.radius_m", "finite number"),
        (("algorithm", "beta"), "fast", "algorithm.beta", "valid number"),
        (("algorithm", "betta"), 7.0, "algorithm.betta", "Extra inputs are not permitted"),
        (("timing", "steps"), DELETE, "timing.steps", "Field required"),
        (("timing", "steps"), 2.5, "timing.steps", "valid integer"),
        (
            ("vehicles", 2, "initial_phase_rad"),
            float("inf"),
            "vehicles[2].initial_phase_rad",
            "finite",
        ),
        (("vehicles", 1, "id"), 1, "vehicles[1].id", "duplicate vehicle id 1"),
        (
            ("vehicles", 0, "senses_target"),
            False,
            "vehicles",
            "at least one vehicle must have senses_target",
        ),
        (("vehicles", 0, "senses_target"), "yes", "vehicles[0].senses_target", "valid boolean"),
        (
            ("vehicles", 0, "initial_position_m"),
            [1.0],
            "vehicles[0].initial_position_m",
            "at least 2",
        ),
        (("vehicles", 0, "speed_limit_m_s"), 0.3, "vehicles[0].speed_limit_m_s", "saturation_m_s"),
        (
            ("target", "path", "kind"),
            "spiral",
            "target.path",
            "does not match any of the expected tags",
        ),
        (("target", "path", "velocity_m_s"), DELETE, "target.path.velocity_m_s", "Field required"),
        (
            ("events",),
            [{"kind": "vehicle_lost", "vehicle": 7, "at_step": 3}],
            "events[0].vehicle",
            "no vehicle with id 7",
        ),
        (
            ("events",),
            [{"kind": "vehicle_lost", "vehicle": 2}],
            "events[0]",
            "exactly one of at_step or at_s",
        ),
        (
            ("events",),
            [{"kind": "vehicle_lost", "vehicle": 2, "at_s": 1e6}],
            "events[0]",
            "after the last step",
        ),
        (
            ("expect",),
            {"final_tracking_eror_m": {"max": 1}},
            "expect.final_tracking_eror_m",
            "Input should be",
        ),
        (
            ("algorithm", "shape"),
            {"scale_north": {"kind": "expression", "expression": "__import__('os')"}},
            "algorithm.shape.scale_north.expression",
            "unknown function '__import__'",
        ),
        (
            ("algorithm", "shape"),
            {"scale_east": {"kind": "sinusoid", "amplitude": 2.0, "offset": 1.0, "period_s": 5}},
            "algorithm.shape.scale_east",
            "must stay finite and > 0",
        ),
        (
            ("algorithm", "shape"),
            {"shear_a": {"kind": "waypoints", "points": [[2, 0], [1, 1]]}},
            "algorithm.shape.shear_a.points",
            "strictly increasing",
        ),
    ],
)
def test_invalid_value_is_reported_at_its_yaml_path(path, value, where, rule):
    problems = problems_of(edit(path, value))
    assert any(location == where and rule in message for location, message in problems), problems


def test_several_problems_are_reported_together():
    data = edit(("algorithm", "beta"), 9.0)
    data["vehicles"][1]["id"] = 1
    locations = [location for location, _ in problems_of(data)]
    assert "algorithm.beta" in locations and "vehicles[1].id" in locations


def test_yaml_syntax_error_names_the_line(tmp_path):
    config = tmp_path / "broken.yaml"
    config.write_text("name: x\ntiming: {step_s: 0.1\n")
    with pytest.raises(ConfigError, match=r"(?s)broken.yaml.*line \d+, column \d+: not valid YAML"):
        load_scenario(config)


def test_missing_file_and_non_mapping(tmp_path):
    with pytest.raises(ConfigError, match="cannot read file"):
        load_scenario(tmp_path / "absent.yaml")
    with pytest.raises(ConfigError, match="must be a mapping"):
        parse_scenario("- 1\n- 2\n")


def test_every_bundled_scenario_is_valid():
    names = sorted(path.stem for path in CONFIGS.glob("*.yaml"))
    assert {"paper_tracking", "paper_narrow_passage", "crazyflie_experiment"} <= set(names)
    for name in names:
        assert load_scenario(CONFIGS / f"{name}.yaml").name == name


# The JSON Schema an editor checks scenarios against (``mission-runner schema``).

SCHEMA_FILE = CONFIGS / "scenario.schema.json"


@pytest.fixture(scope="module")
def validator():
    """A JSON Schema validator of the scenario's schema (checked to be a valid schema itself)."""
    from mission_runner.config import scenario_json_schema

    jsonschema = pytest.importorskip("jsonschema")
    document = scenario_json_schema()
    jsonschema.Draft202012Validator.check_schema(document)
    return jsonschema.Draft202012Validator(document)


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("*.yaml")), ids=lambda path: path.stem)
def test_every_bundled_scenario_meets_the_schema_and_names_it(validator, path):
    text = path.read_text()
    assert [error.message for error in validator.iter_errors(yaml.safe_load(text))] == []
    assert text.splitlines()[0] == "# yaml-language-server: $schema=scenario.schema.json"


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (("algorithm", "forgetting_factor"), 1.5),  # out of range
        (("timing", "steps"), "many"),  # wrong type
        (("algorithm", "radius"), 4.0),  # unknown key
        (("target", "path", "kind"), "spiral"),  # not one of the kinds
    ],
)
def test_the_schema_rejects_what_loading_rejects(validator, path, value):
    data = edit(path, value)
    assert problems_of(data)
    errors = list(validator.iter_errors(data))
    assert errors
    assert all(error.absolute_path[0] == path[0] for error in errors)


def test_the_bundled_schema_file_is_what_the_command_prints(capsys):
    from mission_runner.cli import EXIT_OK, main

    assert main(["schema"]) == EXIT_OK
    assert capsys.readouterr().out == SCHEMA_FILE.read_text(), (
        "configs/scenario.schema.json is stale: mission-runner schema --out "
        "configs/scenario.schema.json"
    )

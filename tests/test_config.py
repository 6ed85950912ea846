"""Every invalid scenario stops with one clear error naming the YAML path and the rule."""

import os
import threading
from pathlib import Path

import pytest
import yaml

from mission_runner.checks import MAX_FILE_BYTES, load_scenario, parse_scenario
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


# --- Inputs that once gave a traceback, a hang or a silent wrong result --------------------------


def problems_in_file(tmp_path, content: bytes):
    config = tmp_path / "scenario.yaml"
    config.write_bytes(content)
    with pytest.raises(ConfigError) as caught:
        load_scenario(config)
    assert str(caught.value).startswith(f"{config}: invalid scenario")
    return caught.value.problems


def test_a_file_that_is_not_utf8_is_refused_with_its_line(tmp_path):
    [(where, message)] = problems_in_file(tmp_path, b"name: x\ndescription: caf\xe9\n")
    assert where == "" and "not UTF-8 text: byte 0xe9 on line 2" in message


def test_a_huge_file_is_refused_without_reading_it_all(tmp_path):
    [(where, message)] = problems_in_file(tmp_path, b"#" * (MAX_FILE_BYTES + 1))
    assert where == "" and "larger than 1024 KiB" in message


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="no /dev/zero")
def test_an_endless_file_ends_at_once():
    with pytest.raises(ConfigError, match="larger than 1024 KiB"):
        load_scenario("/dev/zero")


def test_deep_nesting_is_refused_at_its_path():
    [(where, message)] = problems_of_text("name: x\ndescription: " + "[" * 10_000 + "]" * 10_000)
    assert where == "description[0][0][0]..." and "nested deeper than 32 levels" in message


def test_a_duplicate_key_is_refused_instead_of_keeping_the_last():
    text = yaml.safe_dump(base()).replace("beta: 7.0\n", "beta: 7.0\n  beta: 1.0\n")
    [(where, message)] = problems_of_text(text)
    assert where == "algorithm.beta" and "duplicate key" in message


def test_aliases_that_expand_to_billions_of_values_are_refused():
    text = "name: x\na: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n"
    for level in "bcdefg":
        previous = chr(ord(level) - 1)
        text += f"{level}: &{level} [{', '.join([f'*{previous}'] * 10)}]\n"
    [(where, message)] = problems_of_text(text)
    assert where == "f" and "more than 1000000 values" in message


def test_an_alias_inside_its_own_value_is_refused():
    [(where, message)] = problems_of_text("name: x\nloop: &a [1, *a]\n")
    assert where == "loop" and "alias refers to a value containing it" in message


def problems_of_text(text):
    with pytest.raises(ConfigError) as caught:
        parse_scenario(text, source="test.yaml")
    return caught.value.problems


def expression_signal(text):
    return {"kind": "expression", "expression": text}


@pytest.mark.parametrize(
    ("path", "value", "where", "rule"),
    [
        (
            ("algorithm", "shape"),
            {"scale_north": expression_signal("1/0")},
            "algorithm.shape.scale_north.expression",
            "is not finite at t = 0 s (evaluates to inf)",
        ),
        (
            ("algorithm", "shape"),
            {"translate_east_m": expression_signal("10**10**10")},
            "algorithm.shape.translate_east_m.expression",
            "is not finite at t = 0 s (evaluates to inf)",
        ),
        (
            ("algorithm", "shape"),
            {"shear_a": expression_signal("t/0")},
            "algorithm.shape.shear_a.expression",
            "is not finite at t = 0 s (evaluates to nan)",
        ),
        (
            ("algorithm", "shape"),
            {"shear_b": expression_signal("1 / (t - 2)")},
            "algorithm.shape.shear_b.expression",
            "is not finite at t = 2 s",
        ),
        (
            ("target", "path"),
            {"kind": "expression", "north": "log(t - 1)", "east": "0"},
            "target.path.north",
            "is not finite at t = 0 s (evaluates to nan)",
        ),
        (
            ("target", "path"),
            {"kind": "expression", "north": "0", "east": "exp(t)"},
            "target.path.east",
            "leaves the frame at t = 13.875 s",
        ),
        (
            ("target", "path"),
            {"kind": "line", "velocity_m_s": [1e300, 0.0]},
            "target.path",
            "leaves the frame at t = 0.125 s",
        ),
        (
            ("flight",),
            {"emulator": {"physics": {"dt_s": float("nan")}}},
            "flight.emulator.physics.dt_s",
            "must be a finite number (got nan)",
        ),
        (
            ("expect",),
            {"final_tracking_error_m": {"max": float("inf")}},
            "expect.final_tracking_error_m.max",
            "must be a finite number (got inf)",
        ),
        (
            ("algorithm", "radius_m"),
            1e-9,
            "algorithm.radius_m",
            "too small for 4 vehicles: neighbours on the circle would be 1.41e-09 m apart",
        ),
        (("algorithm", "radius_m"), 1e7, "algorithm.radius_m", "less than or equal to 1000000"),
        (
            ("algorithm", "shape"),
            {"scale_east": 1e-3, "scale_north": 1e-3},
            "algorithm.shape",
            "squeezes the circle so that neighbours may come 0.00566 m close",
        ),
        (
            ("algorithm", "shape"),
            {"translate_north_m": 2e6},
            "algorithm.shape",
            "takes the circle 2e+06 m from the target",
        ),
        (
            ("vehicles", 2, "initial_position_m"),
            [2.0, -3.95],
            "vehicles[2].initial_position_m",
            "0.05 m from vehicles[1] (id 2): vehicles must start at least 0.1 m apart",
        ),
        (
            ("vehicles", 0, "initial_position_m"),
            [1e300, 0.0],
            "vehicles[0].initial_position_m",
            "must be within 1e+06 m of the origin",
        ),
        (
            ("events",),
            [{"kind": "vehicle_lost", "vehicle": 2, "at_s": 1e308}],
            "events[0]",
            "after the last step",
        ),
    ],
)
def test_values_that_would_run_wrong_are_refused_at_their_path(path, value, where, rule):
    problems = problems_of(edit(path, value))
    assert any(location == where and rule in message for location, message in problems), problems


def test_vehicles_all_starting_at_one_point_are_each_named():
    data = base()
    for vehicle in data["vehicles"]:
        vehicle["initial_position_m"] = [1.0, 1.0]
    problems = problems_of(data)
    assert [where for where, _ in problems] == [
        f"vehicles[{index}].initial_position_m" for index in (1, 2, 3)
    ]
    assert all("0 m from vehicles[0] (id 1)" in message for _, message in problems)


def test_a_speed_limit_below_what_the_law_commands_is_a_warning_naming_the_paths(caplog):
    data = yaml.safe_load((CONFIGS / "paper_narrow_passage.yaml").read_text())
    for vehicle in data["vehicles"]:
        vehicle["speed_limit_m_s"] = 10.0  # the circle grows to 6 m: the law asks ~10.8 m/s
    with caplog.at_level("WARNING", logger="mission_runner.checks"):
        parse_scenario(yaml.safe_dump(data), source="narrow.yaml")
    lines = caplog.text.splitlines()
    assert len(lines) == 4
    assert "narrow.yaml: vehicles[0].speed_limit_m_s: 10 m/s is below the 10.8 m/s" in lines[0]
    for path in ("algorithm.saturation_m_s", "algorithm.radius_m", "algorithm.shape"):
        assert path in lines[0]
    assert "algorithm.omega_rad_s" in lines[0] and "target.path" in lines[0]


def test_a_vehicle_of_its_own_frequency_is_named_in_the_warning(caplog):
    data = base()
    data["vehicles"][2]["omega_rad_s"] = 3.0  # 4 m x 3 rad/s = 12 m/s on the circle
    with caplog.at_level("WARNING", logger="mission_runner.checks"):
        parse_scenario(yaml.safe_dump(data), source="fast.yaml")
    assert "vehicles[2].speed_limit_m_s" in caplog.text
    assert "vehicles[2].omega_rad_s" in caplog.text
    assert "vehicles[0]" not in caplog.text


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("*.yaml")), ids=lambda path: path.stem)
def test_bundled_scenarios_load_without_warnings(path, caplog):
    with caplog.at_level("WARNING", logger="mission_runner.checks"):
        load_scenario(path)
    assert caplog.text == ""


def test_outlier_bias_must_be_an_interval():
    data = edit(("sensors",), {"range_outlier_bias_m": [2.0, 0.5]})
    assert problems_of(data) == [
        ("sensors.range_outlier_bias_m", "must be [low, high] with 0 <= low <= high <= 1e+06 m")
    ]


def test_estimator_settings_are_checked_at_their_paths():
    data = edit(("algorithm", "estimator"), "kalman")
    data["algorithm"]["estimator_settings"] = {"gate_chi2": -1.0, "handover_updates": 0}
    paths = [path for path, _ in problems_of(data)]
    assert paths == [
        "algorithm.estimator",
        "algorithm.estimator_settings.gate_chi2",
        "algorithm.estimator_settings.handover_updates",
    ]


# --- Numbers that passed validation and then crashed, hung or meant nothing -----------------------

LE = "Input should be less than or equal to"
GE = "Input should be greater than or equal to"


@pytest.mark.parametrize(
    ("path", "value", "where", "rule"),
    [
        (  # once an OverflowError traceback when the event's steps were counted
            ("events",),
            [{"kind": "target_hidden", "at_step": 3, "duration_s": 1e308}],
            "events[0].duration_s",
            f"{LE} 1000000000",
        ),
        (("flight",), {"clock": "realtime", "speed": 1e300}, "flight.speed", f"{LE} 1000"),
        (("target", "altitude_m"), 1e300, "target.altitude_m", f"{LE} 1000"),
        (("target", "altitude_m"), -1e300, "target.altitude_m", f"{GE} -1000"),
        (("batch",), {"position_spread_m": 1e300}, "batch.position_spread_m", f"{LE} 1000000"),
        (("vehicles", 1, "altitude_m"), 1e300, "vehicles[1].altitude_m", f"{LE} 1000"),
        (("flight",), {"altitude_m": 5e4}, "flight.altitude_m", f"{LE} 1000"),
        (("vehicles", 0, "speed_limit_m_s"), 1e300, "vehicles[0].speed_limit_m_s", f"{LE} 100"),
        (("vehicles", 3, "omega_rad_s"), 1e300, "vehicles[3].omega_rad_s", f"{LE} 100"),
        (
            ("vehicles", 2, "initial_phase_rad"),
            1e300,
            "vehicles[2].initial_phase_rad",
            f"{LE} 1000",
        ),
        (("algorithm", "coupling_gain"), 1e300, "algorithm.coupling_gain", f"{LE} 1000"),
        (
            ("algorithm", "coupling_gain_last"),
            -1e300,
            "algorithm.coupling_gain_last",
            f"{GE} -1000",
        ),
        (("timing", "step_s"), 1e-300, "timing.step_s", f"{GE} 0.001"),
        (("sensors",), {"range_noise_std_m": 1e300}, "sensors.range_noise_std_m", f"{LE} 100"),
        (("flight",), {"silence_timeout_s": 1e300}, "flight.silence_timeout_s", f"{LE} 3600"),
        (("flight",), {"start_delay_s": 1e300}, "flight.start_delay_s", f"{LE} 3600"),
        (
            ("flight",),
            {"autopilot_params": {"MPC_ACC_HOR": 1e300}},
            "flight.autopilot_params",
            "MPC_ACC_HOR: 1e+300 does not fit a REAL32 parameter (|x| <= 3.402823e+38)",
        ),
        (
            ("flight",),
            {"autopilot_params": {"COM_OBL_RC_ACT": 2**40}},
            "flight.autopilot_params",
            "COM_OBL_RC_ACT: 1099511627776 does not fit an INT32 parameter",
        ),
        (
            ("expect",),
            {"final_tracking_error_m": {"min": 2.0, "max": 1.0}},
            "expect.final_tracking_error_m",
            "min 2 is above max 1: no value can pass",
        ),
        (  # the emulator's settings as strict as the rest of the file
            ("flight",),
            {"emulator": {"clock": {"speed": "2"}}},
            "flight.emulator.clock.speed",
            "Input should be a valid number",
        ),
        (
            ("flight",),
            {"emulator": {"ports": {"gcs_enabled": "yes", "api_remote_base": 14540.0}}},
            "flight.emulator.ports.gcs_enabled",
            "Input should be a valid boolean",
        ),
        (("name",), "..", "name", "must be a plain file name, not '..'"),
        (("name",), ".", "name", "must be a plain file name, not '.'"),
    ],
)
def test_numbers_beyond_what_is_physical_are_refused_naming_the_bound(path, value, where, rule):
    problems = problems_of(edit(path, value))
    assert any(location == where and rule in message for location, message in problems), problems


def test_a_flight_refuses_vehicle_ids_beyond_mavlink_but_the_model_does_not(tmp_path):
    data = base()
    data["vehicles"][1]["id"] = 256
    data["vehicles"][2]["id"] = 65535
    config = tmp_path / "ids.yaml"
    config.write_text(yaml.safe_dump(data))
    assert load_scenario(config).vehicles[1].id == 256  # numeric model: any number of vehicles
    with pytest.raises(ConfigError) as caught:
        load_scenario(config, flying=True)
    assert [where for where, _ in caught.value.problems] == ["vehicles[1].id", "vehicles[2].id"]
    assert "256 is not a MAVLink system id (1..255)" in caught.value.problems[0][1]


@pytest.mark.timeout(30)
@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes")
def test_a_named_pipe_is_read_while_written_and_refused_when_nobody_writes(tmp_path, monkeypatch):
    import mission_runner.checks as checks_module

    pipe = tmp_path / "scenario.yaml"
    os.mkfifo(pipe)
    text = (CONFIGS / "paper_tracking.yaml").read_bytes()
    writer = threading.Thread(target=pipe.write_bytes, args=(text,))
    writer.start()  # as `simulate <(generate)` gives it
    assert load_scenario(pipe).name == "paper_tracking"
    writer.join()
    monkeypatch.setattr(checks_module, "READ_TIMEOUT_S", 0.05)
    with pytest.raises(ConfigError) as caught:
        load_scenario(pipe)
    [(where, message)] = caught.value.problems
    assert where == "" and "not a regular file, and nothing more came from it within 0.05 s" in (
        message
    )

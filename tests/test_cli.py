"""``mission-runner simulate`` end to end, in-process."""

import csv
import fnmatch
import gc
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from mission_runner.bus import VehicleStatus
from mission_runner.checks import load_scenario
from mission_runner.cli import (
    EXIT_BAD_INPUT,
    EXIT_EXPECTATION_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_RUNTIME_FAILURE,
    EXIT_TERMINATED,
    main,
)
from mission_runner.cli.common import startup_heap
from mission_runner.cli.ground import score_without_truth
from mission_runner.outputs import RUN_FILES, RunSummary
from tests.sitl.helpers import free_port_config

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_simulate_writes_summary_timeseries_and_figures(tmp_path, capsys):
    # What a run writes and says is plumbing: 40 steps write what 600 do. That the bundled run
    # meets its expectations is test_every_scenario_meets_its_expectations's (slow) and the
    # tracking claim test_paper_claims's.
    def short(data):
        data["timing"]["steps"] = 40
        data["expect"] = {"max_consensus_speed_m_s": {"max": 0.4000001}}  # met at every step

    out = tmp_path / "run"
    assert main(["simulate", str(scenario_file(tmp_path, short)), "--out", str(out)]) == EXIT_OK
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "passed"
    assert summary["expectations"]["passed"] is True
    assert summary["parameters"]["algorithm"]["beta"] == 7.0
    assert set(summary["versions"]) >= {"mission_runner", "numpy", "python"}
    rows = list(csv.DictReader((out / "timeseries.csv").read_text().splitlines()))
    assert len(rows) == 41
    final = summary["metrics"]["final_tracking_error_m"]
    assert float(rows[-1]["tracking_error_m"]) == pytest.approx(final, rel=1e-8)  # 9 digits
    assert {"v1_north_m", "v4_phase_rad", "v2_cmd_east_m_s"} <= set(rows[0])
    for name in ("xy.png", "phases.png", "localization_error.png", "tracking_error.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob(".*.partial"))
    assert "expectations: PASS" in capsys.readouterr().out


def test_batch_writes_the_distribution(tmp_path):
    # The distribution's plumbing on 40 steps; its values (every run below 5 cm) are
    # test_paper_claims's 24-run batch.
    out = tmp_path / "batch"
    code = main(
        [
            "simulate",
            str(tiny_scenario_file(tmp_path)),
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
    spread = summary["batch"]["final_tracking_error_m"]
    assert 0 < spread["median"] <= spread["p95"] <= spread["worst"]
    rows = list(csv.DictReader((out / "batch.csv").read_text().splitlines()))
    assert len(rows) == 8
    worst = max(float(row["final_tracking_error_m"]) for row in rows)
    assert worst == pytest.approx(spread["worst"], rel=1e-8)  # batch.csv has 9 digits


def test_failed_expectation_exits_1(tmp_path):
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["timing"]["steps"] = 40  # not converged by step 10, in 40 steps as in 600
    data["expect"] = {"tracking_converged_step": {"max": 10}}
    config = tmp_path / "strict.yaml"
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    code = main(["simulate", str(config), "--out", str(out), "--no-figures", "--quiet"])
    assert code == EXIT_EXPECTATION_FAILED
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed"
    assert summary["expectations"]["passed"] is False


def test_bad_config_writes_nothing_and_names_the_path(tmp_path, capsys):
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["algorithm"]["forgetting_factor"] = 1.5
    config = tmp_path / "bad.yaml"
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "never"
    assert main(["simulate", str(config), "--out", str(out)]) == EXIT_BAD_INPUT
    assert not out.exists()
    assert "algorithm.forgetting_factor" in capsys.readouterr().err


# --- Bad input: exit 2, one message naming the YAML path, nothing written ------------------------


def scenario_file(tmp_path, change=None, name="bad.yaml"):
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    if change is not None:
        change(data)
    config = tmp_path / name
    config.write_text(yaml.safe_dump(data))
    return config


def tiny_scenario_file(tmp_path):
    """paper_tracking cut to 40 steps and without its expectations (which a run that short
    cannot meet): for tests of what a run writes, not of how it flies."""

    def change(data):
        data["timing"]["steps"] = 40
        data.pop("expect", None)

    return scenario_file(tmp_path, change, name="tiny.yaml")


def shape_expression(name, text):
    def change(data):
        data["algorithm"]["shape"] = {name: {"kind": "expression", "expression": text}}

    return change


def set_value(*path_and_value):
    *path, last, value = path_and_value

    def change(data):
        node = data
        for key in path:
            node = node[key]
        node[last] = value

    return change


def all_vehicles_at(*positions):
    def change(data):
        for vehicle, position in zip(data["vehicles"], positions, strict=False):
            vehicle["initial_position_m"] = list(position)

    return change


def write_bytes(content):
    def make(tmp_path):
        config = tmp_path / "bad.yaml"
        config.write_bytes(content)
        return config

    return make


def write_change(change):
    return lambda tmp_path: scenario_file(tmp_path, change)


BAD_INPUTS = {
    "not_utf8": (write_bytes(b"name: caf\xe9\n"), "<root>: not UTF-8 text: byte 0xe9 on line 1"),
    "too_large": (write_bytes(b"#" * (2 << 20)), "<root>: larger than 1024 KiB"),
    "endless": (lambda tmp_path: Path("/dev/zero"), "<root>: larger than 1024 KiB"),
    "deep_nesting": (
        write_bytes(b"name: x\ndescription: " + b"[" * 10_000 + b"]" * 10_000 + b"\n"),
        "description[0][0][0]...: nested deeper than 32 levels",
    ),
    "yaml_syntax": (write_bytes(b"name: x\ntiming: {step_s: 0.1\n"), "not valid YAML"),
    "division_by_zero": (
        write_change(shape_expression("scale_north", "1/0")),
        "algorithm.shape.scale_north.expression: is not finite at t = 0 s (evaluates to inf)",
    ),
    "huge_power": (
        write_change(shape_expression("translate_north_m", "10**10**10")),
        "algorithm.shape.translate_north_m.expression: is not finite at t = 0 s",
    ),
    "t_over_zero": (
        write_change(shape_expression("shear_a", "t/0")),
        "algorithm.shape.shear_a.expression: is not finite at t = 0 s (evaluates to nan)",
    ),
    "log_of_negative": (
        write_change(
            set_value("target", "path", {"kind": "expression", "north": "log(t-1)", "east": "0"})
        ),
        "target.path.north: is not finite at t = 0 s (evaluates to nan)",
    ),
    "nan": (
        write_change(set_value("algorithm", "beta", float("nan"))),
        "algorithm.beta: must be a finite number (got nan)",
    ),
    "tiny_radius": (
        write_change(set_value("algorithm", "radius_m", 1e-9)),
        "algorithm.radius_m: too small for 4 vehicles",
    ),
    "coincident_starts": (
        write_change(all_vehicles_at(*[(1.0, 1.0)] * 4)),
        "vehicles[1].initial_position_m: 0 m from vehicles[0] (id 1)",
    ),
    "overlapping_starts": (
        write_change(all_vehicles_at((0.0, 0.0), (0.0, 0.05))),
        "vehicles[1].initial_position_m: 0.05 m from vehicles[0] (id 1)",
    ),
    "target_leaves_the_frame": (
        write_change(set_value("target", "path", "velocity_m_s", [1e300, 0.0])),
        "target.path: leaves the frame at t = 0.125 s",
    ),
    "duplicate_key": (
        write_bytes(
            (CONFIGS / "paper_tracking.yaml")
            .read_bytes()
            .replace(b"  beta: 7.0\n", b"  beta: 7.0\n  beta: 70.0\n")
        ),
        "algorithm.beta: duplicate key",
    ),
}


@pytest.mark.parametrize("name", sorted(BAD_INPUTS))
def test_bad_input_exits_2_naming_the_yaml_path(name, tmp_path, capsys):
    make, expected = BAD_INPUTS[name]
    if name == "endless" and not Path("/dev/zero").exists():
        pytest.skip("no /dev/zero")
    out = tmp_path / "never"
    assert main(["simulate", str(make(tmp_path)), "--out", str(out), "--quiet"]) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert expected in error, error
    assert "Traceback" not in error
    assert not out.exists()


def test_a_batch_too_large_for_memory_is_refused_before_any_work(tmp_path, capsys):
    # Steps and runs multiply: few steps (loading a scenario of a million costs seconds), many runs.
    config = scenario_file(tmp_path, set_value("timing", "steps", 10_000))
    out = tmp_path / "never"
    code = main(["simulate", str(config), "--runs", "10000", "--out", str(out), "--quiet"])
    assert code == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert "timing.steps: 10000 steps x 4 vehicles x 10000 run(s) need about" in error
    assert "lower timing.steps, the number of vehicles or --runs" in error
    assert not out.exists()


@pytest.mark.parametrize("speed", ["0", "-1", "nan", "inf", "fast"])
def test_a_speed_that_is_not_a_positive_number_exits_2(speed, capsys):
    with pytest.raises(SystemExit) as stopped:
        main(["run", str(CONFIGS / "paper_tracking_flyable.yaml"), "--speed", speed])
    assert stopped.value.code == EXIT_BAD_INPUT
    assert "argument --speed" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("arguments", "option", "bound"),
    [
        (["run", "paper_tracking_flyable.yaml", "--speed", "1e300"], "--speed", "1000"),
        (["replay", "out", "--width", "100000"], "--width", "7680"),
        (["replay", "out", "--fps", "1e9"], "--fps", "100"),
        (["ground", "px4_sih_tracking.yaml", "--start-delay", "1e300"], "--start-delay", "3600"),
        (["ranges", "px4_sih_tracking.yaml", "--truth-rate", "1e9"], "--truth-rate", "1000"),
        (["vehicle", "px4_sih_tracking.yaml", "--id", "256"], "--id", "255"),
    ],
)
def test_an_option_beyond_its_bound_exits_2_naming_it(arguments, option, bound, capsys):
    command, config, *rest = arguments
    with pytest.raises(SystemExit) as stopped:
        main([command, str(CONFIGS / config), *rest])
    assert stopped.value.code == EXIT_BAD_INPUT
    assert f"argument {option}: must be <= {bound}, got" in capsys.readouterr().err


def test_an_error_during_the_run_leaves_a_summary_saying_so(tmp_path, monkeypatch, capsys):
    # A failure the simulator finds at step 10 (injected: no bundled input fails mid-run).
    from mission_runner.errors import SimulationError
    from mission_runner.sim import simulator

    track_target = simulator.track_target

    def failing_at_step_10(track, step, **kwargs):
        if step == 10:
            raise SimulationError("step 10: injected failure")
        return track_target(track, step, **kwargs)

    monkeypatch.setattr(simulator, "track_target", failing_at_step_10)
    config = scenario_file(tmp_path)
    out = tmp_path / "out"
    assert main(["simulate", str(config), "--out", str(out), "--quiet"]) == EXIT_BAD_INPUT
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "error"
    assert "injected failure" in summary["detail"]
    assert summary["steps_done"] == 10


def test_a_mission_that_loses_its_target_fails_its_expectations(tmp_path, capsys):
    # Losing the only vehicle that senses the target: predicted, then lost. Exit 1 unless the
    # scenario bounds target_lost_step (then it is what the scenario means to show).
    def lose_it(data):
        data["timing"]["steps"] = 40  # lost at 26: the rest of the 600 is the same verdict
        data["events"] = [{"kind": "vehicle_lost", "vehicle": 1, "at_step": 10}]
        data["algorithm"]["target_lost_after_s"] = 2.0

    config = scenario_file(tmp_path, lose_it)
    out = tmp_path / "out"
    code = main(["simulate", str(config), "--out", str(out), "--no-figures", "--quiet"])
    assert code == EXIT_EXPECTATION_FAILED
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed"
    assert summary["metrics"]["target_lost_step"] == 26
    assert summary["expectations"]["failures"][0].startswith("target lost at step 26")

    def expect_it(data):
        lose_it(data)
        data["expect"] = {"target_lost_step": {"max": 26}}

    config = scenario_file(tmp_path, expect_it)
    code = main(["simulate", str(config), "--out", str(out), "--no-figures", "--quiet"])
    assert code == 0


@pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning", "ignore:invalid:RuntimeWarning")
def test_estimates_that_diverge_fail_instead_of_reading_as_zero_error(tmp_path, capsys):
    # An absurd (but finite) initial gain makes every estimate NaN; the localization error once
    # skipped NaN edges and read 0, so this bound passed.
    def absurd_gain(data):
        data["timing"]["steps"] = 40  # diverged from the first step on
        data["algorithm"]["initial_gain"] = 1e300
        data["expect"] = {"final_localization_error_m": {"max": 1e-6}}

    config = scenario_file(tmp_path, absurd_gain)
    out = tmp_path / "out"
    code = main(["simulate", str(config), "--out", str(out), "--no-figures", "--quiet"])
    assert code == EXIT_EXPECTATION_FAILED
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed"
    assert summary["metrics"]["final_localization_error_m"] is None
    assert summary["expectations"]["failures"] == [
        "final_localization_error_m = inf: no value to compare"
    ]


# --- --out: checked before any work; a run never mixes with an earlier one -----------------------


def test_out_that_is_a_file_exits_2_with_one_line(tmp_path, capsys):
    taken = tmp_path / "taken"
    taken.write_text("mine")
    config = str(CONFIGS / "paper_tracking.yaml")
    assert main(["simulate", config, "--out", str(taken), "--quiet"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == f"error: output folder {taken} is a file, not a folder\n"
    assert main(["simulate", config, "--out", str(taken / "sub"), "--quiet"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == (
        f"error: output folder {taken / 'sub'} cannot be written: Not a directory\n"
    )
    assert taken.read_text() == "mine"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_out_that_is_not_writable_exits_2(tmp_path, capsys):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    code = main(["simulate", str(CONFIGS / "paper_tracking.yaml"), "--out", str(locked)])
    assert code == EXIT_BAD_INPUT
    assert "cannot be written: Permission denied" in capsys.readouterr().err


@pytest.fixture(scope="module")
def batch_run(tmp_path_factory):
    """A tiny scenario file and the folder its batch of three runs with figures wrote (to be
    read; a test that changes it changes a copy). Which files a run leaves is plumbing: a few
    steps write the same set as the full 600."""
    folder = tmp_path_factory.mktemp("batch_run")
    config, out = tiny_scenario_file(folder), folder / "out"
    assert main(["simulate", str(config), "--out", str(out), "--runs", "3", "--quiet"]) == EXIT_OK
    return config, out


def test_a_second_run_removes_the_first_runs_files_and_nothing_else(tmp_path, batch_run):
    config, first_run = batch_run
    out = tmp_path / "out"
    shutil.copytree(first_run, out)
    (out / "notes.txt").write_text("mine")
    (out / "tlogs").mkdir()
    (out / "tlogs" / "vehicle_1.tlog").write_bytes(b"old flight")
    first = {path.name for path in out.iterdir()}
    assert {"batch.csv", "batch_tracking_error.png", "xy.png"} <= first
    code = main(["simulate", str(config), "--out", str(out), "--no-figures", "--quiet"])
    assert code == EXIT_OK
    assert {path.name for path in out.iterdir()} == {
        "notes.txt",
        "tlogs",
        "summary.json",
        "timeseries.csv",
        "recording.mcap",  # written by every run, as the summary
    }
    assert not list((out / "tlogs").iterdir())
    assert (out / "notes.txt").read_text() == "mine"


def test_every_file_a_run_writes_is_one_the_next_run_removes(batch_run):
    _, out = batch_run
    written = [path.relative_to(out).as_posix() for path in out.rglob("*") if path.is_file()]
    assert written
    for name in written:
        assert any(fnmatch.fnmatch(name, pattern) for pattern in RUN_FILES), name


# --- Signals: SIGTERM stops like Ctrl-C, exit 128 + signal, summary.json says interrupted ---------


@pytest.mark.parametrize(
    ("stop", "code"), [(signal.SIGTERM, EXIT_TERMINATED), (signal.SIGINT, EXIT_INTERRUPTED)]
)
def test_a_signal_stops_simulate_with_its_exit_code_and_an_interrupted_summary(
    stop, code, tmp_path
):
    # Long enough to be running when the signal comes (minutes), not so long that loading it
    # costs seconds (1 000 000 steps did: 9 s before the run started).
    config = scenario_file(tmp_path, set_value("timing", "steps", 100_000), name="long.yaml")
    out = tmp_path / "out"
    root = Path(__file__).resolve().parents[1]
    process = subprocess.Popen(
        [sys.executable, "-m", "mission_runner.cli", "simulate", str(config), "--out", str(out)],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(root)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        summary = out / "summary.json"
        # Written once the handlers are in place and the run starts; the run then takes minutes.
        while process.poll() is None and not summary.exists():
            time.sleep(0.05)
        assert json.loads(summary.read_text())["status"] == "running"
        process.send_signal(stop)
        _, error = process.communicate(timeout=60)
    finally:
        process.kill()
    assert process.returncode == code, error
    assert error.strip().endswith(f"interrupted ({stop.name})")
    assert "Traceback" not in error
    document = json.loads(summary.read_text())
    assert document["status"] == "interrupted"
    assert document["scenario"] == "paper_tracking"
    assert 0 <= document["steps_done"] < 100_000
    assert not (out / "timeseries.csv").exists()


ASYNC_STOP = """
import asyncio, signal, sys
from mission_runner.cli import stopping

signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job: asyncio adds no handler then


async def fly():
    try:
        print("flying", flush=True)
        await asyncio.sleep(3600)
    except asyncio.CancelledError:
        print("cancelled: landing", flush=True)
        raise


with stopping.terminate_as_interrupt():
    try:
        stopping.run_async(fly())
    except KeyboardInterrupt:
        print("KeyboardInterrupt", flush=True)
"""


def test_sigterm_cancels_the_asyncio_main_task_even_where_sigint_is_ignored(tmp_path):
    root = Path(__file__).resolve().parents[1]
    process = subprocess.Popen(
        [sys.executable, "-c", ASYNC_STOP],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(root)},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert process.stdout.readline() == "flying\n"
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=60)
    finally:
        process.kill()
    # The coroutine sees a cancellation (where the flight code lands), the caller an interrupt.
    assert output == "cancelled: landing\nKeyboardInterrupt\n"
    assert process.returncode == 0


SECOND_STOP = """
import asyncio
from mission_runner.cli import stopping


async def fly():
    try:
        print("flying", flush=True)
        await asyncio.sleep(3600)
    except asyncio.CancelledError:
        print("landing", flush=True)
        try:
            await asyncio.sleep(3600)  # a landing that takes its time
        except asyncio.CancelledError:
            print("landing abandoned", flush=True)
            raise


with stopping.terminate_as_interrupt():
    try:
        stopping.run_async(fly(), stopping.RUN_STOPPING)
    except KeyboardInterrupt:
        print("KeyboardInterrupt", stopping.signals.received, flush=True)
"""


def _python_script(script: str, cwd: Path) -> subprocess.Popen[str]:
    """``script`` run by this Python against this checkout, its standard streams piped."""
    return subprocess.Popen(
        [sys.executable, "-c", script],
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.parametrize(
    ("first", "second"),
    [
        (signal.SIGINT, signal.SIGINT),
        (signal.SIGTERM, signal.SIGTERM),
        (signal.SIGINT, signal.SIGTERM),
    ],
)
def test_a_second_signal_abandons_the_landing_and_says_so(first, second, tmp_path):
    process = _python_script(SECOND_STOP, tmp_path)
    try:
        assert process.stdout.readline() == "flying\n"
        process.send_signal(first)
        assert process.stdout.readline() == "landing\n"
        process.send_signal(second)
        output, error = process.communicate(timeout=60)
    finally:
        process.kill()
    # No KeyboardInterrupt raised inside the event loop (asyncio's own second Ctrl-C): the
    # landing sees a cancellation, the caller one interrupt, named after the last signal.
    assert output == f"landing abandoned\nKeyboardInterrupt {second.name}\n"
    assert error.splitlines() == [
        f"run: {first.name}: landing every vehicle ({first.name} again: stop at once)",
        f"run: {second.name} again: stopping at once, vehicles left to PX4's offboard-loss "
        "failsafe (the emulated ones end with this process)",
    ]


OTHER_THREAD_STOP = """
import asyncio
import signal
import sys
import threading

from mission_runner.cli import stopping


def signaller():
    sys.stdin.readline()  # the test says when
    signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # to this thread, not the main one


async def fly():
    try:
        print("flying", flush=True)
        await asyncio.sleep(3600)
    except asyncio.CancelledError:
        print("landing", flush=True)
        raise


threading.Thread(target=signaller, daemon=True).start()
with stopping.terminate_as_interrupt():
    try:
        stopping.run_async(fly(), stopping.RUN_STOPPING)
    except KeyboardInterrupt:
        print("KeyboardInterrupt", stopping.signals.received, flush=True)
"""


def test_a_stop_signal_reaches_the_flight_whichever_thread_the_kernel_gives_it_to(tmp_path):
    """The process has threads besides the main one (numpy's BLAS workers) and a signal for
    the process may be handed to any: the loop, asleep for the hour of a flight, must wake
    (without its wakeup descriptor a second Ctrl-C once went unseen in CI)."""
    process = _python_script(OTHER_THREAD_STOP, tmp_path)
    try:
        assert process.stdout.readline() == "flying\n"
        process.stdin.write("now\n")
        process.stdin.flush()
        output, error = process.communicate(timeout=60)
    finally:
        process.kill()
    assert output == "landing\nKeyboardInterrupt SIGINT\n"
    assert error.splitlines() == ["run: SIGINT: landing every vehicle (SIGINT again: stop at once)"]


@pytest.mark.mavsdk
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_sigterm_stops_a_flight_with_exit_143_and_an_interrupted_summary(tmp_path):

    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["flight"]["emulator"] = {"ports": free_port_config(4, gcs=False).model_dump()}
    config = tmp_path / "flight.yaml"
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    root = Path(__file__).resolve().parents[1]
    process = subprocess.Popen(
        [sys.executable, "-m", "mission_runner.cli", "run", str(config), "--out", str(out)],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(root), "PYTHONUNBUFFERED": "1"},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        for line in process.stdout:  # the view prints a line per second of mission
            if line.startswith("k="):
                break
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=120)
    finally:
        process.kill()
    assert process.returncode == EXIT_TERMINATED, output
    assert output.strip().endswith("interrupted (SIGTERM)")
    assert "Traceback" not in output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted"
    assert 0 < summary["steps_done"] < data["timing"]["steps"]


# --- Runtime failures: exit 3, one line ----------------------------------------------------------


def test_a_taken_port_is_one_line_naming_the_setting(tmp_path, capsys):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("0.0.0.0", 0))
        port = taken.getsockname()[1]

        def gcs_port(data):
            # Every other port free too: PX4 SITL on this machine holds the defaults (14580...).
            ports = free_port_config(len(data["vehicles"]), gcs=True).model_dump(mode="json")
            ports = {key: value for key, value in ports.items() if value is not None}
            data["flight"]["emulator"] = {"ports": {**ports, "gcs_local_base": port}}

        config = tmp_path / "flyable.yaml"
        data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
        gcs_port(data)
        config.write_text(yaml.safe_dump(data))
        out = tmp_path / "out"
        assert main(["run", str(config), "--out", str(out), "--quiet"]) == EXIT_RUNTIME_FAILURE
    error = capsys.readouterr().err
    assert error.count("\n") == 1
    assert f"UDP port {port} for vehicle 0 is already in use" in error
    assert "ports.gcs_local_base" in error
    assert json.loads((out / "summary.json").read_text())["status"] == "error"


def test_broker_config_writes_a_mosquitto_config_logins_an_acl_and_a_key(tmp_path, capsys):
    out = tmp_path / "broker"
    config = CONFIGS / "px4_sih_tracking.yaml"
    assert main(["broker-config", str(config), "--out", str(out), "--port", "18883"]) == EXIT_OK
    text = capsys.readouterr().out
    assert (
        "users ground, operator, viewer, ranges, vehicle-1, vehicle-1-flight, vehicle-2, "
        "vehicle-2-flight" in text
    )
    assert f"mosquitto -c {out.resolve() / 'mosquitto.conf'}" in text
    assert "listener 18883" in (out / "mosquitto.conf").read_text()
    assert {p.name for p in out.iterdir()} == {
        "mosquitto.conf",
        "passwords",
        "acl",
        "credentials",
        "bus.key",
    }
    assert main(["broker-config", str(CONFIGS / "paper_tracking.yaml"), "--out", str(out)]) == (
        EXIT_BAD_INPUT
    )
    assert "bus.kind: a broker is for bus.kind: mqtt" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["ground", "control", "ranges", "vehicle"])
def test_an_mqtt_bus_without_a_key_is_refused_before_anything_connects(
    command, monkeypatch, capsys
):
    monkeypatch.delenv("MISSION_BUS_KEY")
    arguments = [command, str(CONFIGS / "px4_sih_tracking.yaml")]
    arguments += {"control": ["land"], "vehicle": ["--id", "1"]}.get(command, [])
    assert main(arguments) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert "an MQTT bus needs a key" in error and "--bus-key-file" in error


def test_a_bus_key_file_that_is_missing_or_short_is_refused(tmp_path, capsys):
    config = str(CONFIGS / "px4_sih_tracking.yaml")
    assert main(["ground", config, "--bus-key-file", str(tmp_path / "nope")]) == EXIT_BAD_INPUT
    assert "cannot read the bus key file" in capsys.readouterr().err
    short = tmp_path / "short.key"
    short.write_text("abc\n")
    assert main(["ground", config, "--bus-key-file", str(short)]) == EXIT_BAD_INPUT
    assert "at least 32" in capsys.readouterr().err


def test_a_ground_station_without_truth_scores_only_what_it_saw(tmp_path):
    # A real flight: no truth, so bounds on errors cannot be checked; one vehicle was taken over.
    scenario = load_scenario(CONFIGS / "px4_sih_tracking.yaml")
    ends = {1: "done", 2: "done", 3: "done", 4: "taken_over"}
    statuses = {i: VehicleStatus(i, 10.0, state, 600, False) for i, state in ends.items()}
    with RunSummary(tmp_path, scenario, config_path=None) as record:
        code = score_without_truth(scenario, record, statuses)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert code == EXIT_EXPECTATION_FAILED
    assert summary["status"] == "failed"
    assert summary["metrics"] == {"vehicles_in_formation_at_end": 3}
    assert summary["expectations"]["failures"] == ["vehicles_in_formation_at_end = 3 < min 4"]
    assert "tail_tracking_error_rms_m" in summary["expectations"]["not_checked"]
    assert summary["vehicles"]["4"] == {"state": "taken_over", "detail": ""}

    statuses[4] = VehicleStatus(4, 10.0, "done", 600, False)
    with RunSummary(tmp_path, scenario, config_path=None) as record:
        code = score_without_truth(scenario, record, statuses)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert code == EXIT_OK
    assert summary["status"] == "unchecked"  # never "passed" on what it could not see


# --- Inputs that once crashed, hung or wrote where they should not --------------------------------


def test_a_scenario_named_dot_dot_writes_nothing_outside_out(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    config = scenario_file(tmp_path, set_value("name", ".."))
    assert main(["simulate", str(config), "--quiet", "--no-figures"]) == EXIT_BAD_INPUT
    assert "name: must be a plain file name, not '..'" in capsys.readouterr().err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["bad.yaml"]


def test_diverged_batch_runs_write_no_nan_into_summary_json(tmp_path, capsys):
    # An absurd (but finite) initial gain: every estimate of every run diverges.
    def absurd_gain(data):
        data["timing"]["steps"] = 40  # diverged from the first step on
        data["algorithm"]["initial_gain"] = 1e300
        data["expect"] = {}

    config = scenario_file(tmp_path, absurd_gain)
    out = tmp_path / "out"
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        code = main(["simulate", str(config), "--runs", "3", "--out", str(out), "--no-figures"])
    assert code == EXIT_OK

    def refuse(constant):
        raise AssertionError(f"summary.json holds {constant}, which is not JSON")

    summary = json.loads((out / "summary.json").read_text(), parse_constant=refuse)
    assert summary["batch"]["final_localization_error_m"] == {
        "median": None,
        "p95": None,
        "worst": None,
        "not_finite": 3,
    }
    assert "(3 not finite)" in capsys.readouterr().out


def mqtt_scenario(tmp_path, port, name="control.yaml"):
    def mqtt(data):
        data["bus"] = {"kind": "mqtt", "mqtt": {"port": port, "connect_timeout_s": 2.0}}

    return scenario_file(tmp_path, mqtt, name=name)


def test_control_of_a_vehicle_not_in_the_scenario_is_bad_input_before_connecting(tmp_path, capsys):
    with socket.socket() as probe:  # a port nothing listens on: nothing must try it
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    config = mqtt_scenario(tmp_path, port)
    assert main(["control", str(config), "land", "--vehicle", "9"]) == EXIT_BAD_INPUT
    error = capsys.readouterr().err
    assert error == "error: vehicle 9 is not in the mission (ids 1, 2, 3, 4)\n"


def test_control_with_a_reason_too_long_to_be_received_is_bad_input(tmp_path, capsys):
    # Once sent and reported as sent, then dropped unread by every vehicle as oversized.
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    config = mqtt_scenario(tmp_path, port)
    assert main(["control", str(config), "land", "--reason", "x" * 20_000]) == EXIT_BAD_INPUT
    assert "the reason has 20000 characters; a command carries at most 1000" in (
        capsys.readouterr().err
    )


def test_without_a_prepare_control_says_whether_one_came_under_another_key(tmp_path):
    """The verdict of the test below (which needs a broker) from the bus's counters alone."""
    from mission_runner.bus import AuthCounters
    from mission_runner.runner.process import _no_prepare

    scenario = load_scenario(mqtt_scenario(tmp_path, 1883))
    topics = scenario.bus.topics(scenario.name)
    none = _no_prepare(scenario, topics, AuthCounters(), 5.0)
    assert none.startswith("no mission of paper_tracking is running")
    forged = _no_prepare(scenario, topics, AuthCounters(forged=2), 5.0)
    assert forged.startswith("the bus key does not match the mission's: 2 message(s) on ")


@pytest.mark.mqtt  # a broker: the fast lane's promise is none (the test above has its verdict)
@pytest.mark.timeout(60)
def test_control_with_another_key_says_the_key_does_not_match(tmp_path, mosquitto, capsys):
    import asyncio

    from mission_runner.bus import ControlCommand, MissionControl, Sender, open_bus

    config = mqtt_scenario(tmp_path, mosquitto.port)
    scenario = load_scenario(config)

    async def prepare():  # what a running ground station leaves on the control topic
        async with open_bus(scenario.bus, sender=Sender.ground()) as bus:
            message = MissionControl(ControlCommand.PREPARE, time.time(), mission_id="m1")
            topic = scenario.bus.topics(scenario.name).control()
            await bus.publish_message(topic, message, retain=True, timeout=5.0)

    asyncio.run(prepare())
    other_key = tmp_path / "other.key"
    other_key.write_text("another-key-0123456789abcdef0123456789abcdef\n")
    code = main(["control", str(config), "hold", "--bus-key-file", str(other_key)])
    assert code == EXIT_RUNTIME_FAILURE
    error = capsys.readouterr().err
    assert "the bus key does not match the mission's" in error, error
    assert "no mission" not in error


def test_a_command_line_loads_the_emulator_only_for_the_commands_that_need_it():
    """A vehicle process on a companion computer never pays for the emulator's and the PX4
    launcher's imports; emulate and px4-sitl still get their full options."""
    script = (
        "import sys; from mission_runner.cli.parser import build_parser; "
        "p = build_parser('vehicle'); p.parse_args(['vehicle', 'x.yaml', '--id', '1']); "
        "print('sitl' in sys.modules, 'mission_runner.px4sitl' in sys.modules); "
        "p = build_parser('emulate'); a = p.parse_args(['emulate', 'x.yaml', '--no-gcs']); "
        "print(a.no_gcs, 'sitl' in sys.modules)"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True
    )
    assert done.stdout.split() == ["False", "False", "True", "True"], done.stdout


def test_steps_held_on_stale_data_are_in_the_verdict_and_can_be_bounded(tmp_path):
    # The flood: the formation froze for 140 steps, every vehicle still reported done.
    from mission_runner.config import Expectation
    from mission_runner.runner.process import GroundOutcome

    scenario = load_scenario(CONFIGS / "px4_sih_tracking.yaml")
    bounded = {**scenario.expect, "steps_on_stale_data": Expectation(max=20)}
    scenario = scenario.model_copy(update={"expect": bounded})
    held = {1: 0, 2: 140, 3: 0, 4: 3}
    statuses = {
        i: VehicleStatus(i, 10.0, "done", 400, False, stale_steps=count)
        for i, count in held.items()
    }
    outcome = GroundOutcome("m1", 0.0, 1.0, statuses)
    assert outcome.lost == [] and outcome.stale_steps == 143
    with RunSummary(tmp_path, scenario, config_path=None) as record:
        code = score_without_truth(scenario, record, statuses, outcome.stale_steps)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert code == EXIT_EXPECTATION_FAILED
    assert summary["metrics"]["steps_on_stale_data"] == 143
    assert summary["expectations"]["failures"] == ["steps_on_stale_data = 143 > max 20"]
    # A vehicle that never said how many it held: unknown, never counted as none.
    statuses[2] = VehicleStatus(2, 10.0, "lost", 12, False)
    assert GroundOutcome("m1", 0.0, 1.0, statuses).stale_steps is None


def test_a_flight_counts_the_steps_its_controllers_held_or_skipped():
    import numpy as np

    from mission_runner.metrics import run_metrics
    from mission_runner.records import ControllerState, StepRecord, TruthSample
    from mission_runner.runner.scoring import score_flight

    scenario = load_scenario(CONFIGS / "paper_tracking_flyable.yaml")
    scenario = scenario.model_copy(
        update={"timing": scenario.timing.model_copy(update={"steps": 6})}
    )
    n = len(scenario.vehicles)
    samples = [
        TruthSample(k, k * 0.125, np.zeros(2), np.arange(2 * n, dtype=float).reshape(n, 2),
                    np.ones(n, dtype=bool))
        for k in range(7)
    ]  # fmt: skip
    states = ["following", "holding", "skipped", "held", "target_lost", "holding"]

    def record(k, state):
        return StepRecord(
            step=k,
            time_s=k * 0.125,
            state=ControllerState(state),
            velocity_ned_m_s=(0.0, 0.0, 0.0),
            consensus_m_s=(0.0, 0.0),
            phase_rad=0.0,
            neighbours_used=(),
            estimates_m={},
        )

    records = {v.id: [record(k, s) for k, s in enumerate(states)] for v in scenario.vehicles}
    metrics = run_metrics(score_flight(scenario, samples, records, None))
    # Held on stale data or skipped: 3 a vehicle; the operator's hold and a lost target are not.
    assert metrics["steps_on_stale_data"][0] == 3 * n


#: What building the command line must not load: the bus's MQTT clients, MAVSDK, the recording
#: (Foxglove, MCAP), the figures and the emulator's MAVLink.
HEAVY_MODULES = ("mavsdk", "aiomqtt", "paho", "foxglove", "mcap", "matplotlib", "pymavlink")
HELP_IMPORTS = (
    "import sys\n"
    "from mission_runner.cli import main\n"
    "try:\n"
    "    main(sys.argv[1:])\n"
    "except SystemExit:\n"
    "    pass\n"
    "print(' '.join(sorted({name.split('.')[0] for name in sys.modules})))\n"
)


def _commands():
    from mission_runner.cli.parser import build_parser

    return list(build_parser()._subparsers._group_actions[0].choices)


@pytest.mark.parametrize("command", [None, *_commands()])
def test_help_imports_no_bus_client_flight_stack_recording_or_figures(command):
    """``--help`` is quick: building the parser of any command imports none of its work."""
    arguments = ["--help"] if command is None else [command, "--help"]
    done = subprocess.run(
        [sys.executable, "-c", HELP_IMPORTS, *arguments],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    assert "usage: mission-runner" in done.stdout
    loaded = set(done.stdout.splitlines()[-1].split())
    assert not loaded & set(HEAVY_MODULES), sorted(loaded & set(HEAVY_MODULES))


def test_start_up_runs_without_the_collector_and_freezes_what_it_built() -> None:
    assert gc.isenabled()
    frozen = gc.get_freeze_count()
    try:
        with startup_heap():
            assert not gc.isenabled()
            built = [[i] for i in range(1000)]
        assert gc.isenabled()
        assert gc.get_freeze_count() >= frozen + len(built)
        with pytest.raises(ValueError, match="bad scenario"), startup_heap():
            raise ValueError("bad scenario")
        assert gc.isenabled()  # a failed start-up leaves the collector on
    finally:
        gc.unfreeze()

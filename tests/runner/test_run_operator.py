"""The operator commands a ``run`` (emulator, bus and every controller in one process) as a
ground station commands vehicle processes: lines typed on its stdin, and over an MQTT bus
``mission-runner control``. Every vehicle acts on the step after the one it was flying when the
command came (lockstep: the same step for all); a vehicle landed by the operator ends
``aborted``, on the ground and disarmed. Ctrl-C lands the swarm; a second one stops at once.

Real emulator over UDP, real MAVSDK, real mosquitto where a bus is involved; every wait is for an
output line of the process.
"""

import json
import re
import signal
import subprocess

import pytest
import yaml

from tests.sitl.helpers import free_port_config

from .flying import CONFIGS, start, type_line, wait_for

pytestmark = [pytest.mark.mavsdk, pytest.mark.slow]

STEPS = 200
STATES = re.compile(r"^k=\s*(\d+)\s+((?:v\d+:\S+\s+)+)tracking")
FROM_STEP = re.compile(r"vehicle (\d+): (\w+) by the operator, (?:from|no) step (?:from )?(\d+)")


def run_scenario(tmp_path, steps=STEPS, bus=None):
    """The flyable tracking mission, ``steps`` long, without expectations (a held or landed
    vehicle is not a failure here), on free UDP ports."""
    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["name"] = "run_operator"
    data["timing"]["steps"] = steps
    data["expect"] = {}
    data["flight"]["emulator"] = {"ports": free_port_config(4, gcs=False).model_dump()}
    if bus is not None:
        data["bus"] = bus
    path = tmp_path / "run.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def start_run(config, out, stdin=subprocess.DEVNULL):
    return start(
        "mission_runner.cli", "run", config, "--out", str(out), "--no-figures", stdin=stdin
    )


def states_of(line):
    """``(k, {vehicle: state})`` of a progress line, else None."""
    match = STATES.match(line)
    if match is None:
        return None
    pairs = (item.split(":") for item in match.group(2).split())
    return int(match.group(1)), {int(v[1:]): state for v, state in pairs}


def until_states(process, seen, done):
    """Read ``process``'s lines until a progress line whose states satisfy ``done``. Returns
    the operator's announced first steps (``{vehicle: step}``) and, per vehicle, the first
    progress step that showed it in each state, from what was read."""
    announced, first_seen = {}, {}
    for line in process.stdout:
        seen.append(line)
        if match := FROM_STEP.search(line):
            announced[int(match.group(1))] = int(match.group(3))
        if (progress := states_of(line)) is not None:
            k, states = progress
            for vehicle, state in states.items():
                first_seen.setdefault((vehicle, state), k)
            if done(states):
                return announced, first_seen
    raise AssertionError("".join(seen[-40:]))


@pytest.mark.timeout(120)
def test_typed_hold_resume_and_land_one_vehicle_act_on_the_next_step(tmp_path):
    out = tmp_path / "out"
    run = start_run(run_scenario(tmp_path), out, stdin=subprocess.PIPE)
    seen = []
    try:
        wait_for(run, r"^k=.*v1:following", seen)
        type_line(run, "hold")
        announced, first = until_states(run, seen, lambda states: set(states.values()) == {"held"})
        assert sorted(announced) == [1, 2, 3, 4]
        for vehicle, step in announced.items():
            assert first[vehicle, "held"] == step  # the step after the one it was flying
        type_line(run, "bogus")
        wait_for(run, r"run: error: unknown command 'bogus'", seen)
        type_line(run, "resume")
        announced, first = until_states(
            run, seen, lambda states: set(states.values()) == {"following"}
        )
        for vehicle, step in announced.items():
            assert first[vehicle, "following"] == step
        type_line(run, "land 2")
        wait_for(run, r"run: land sent to vehicle 2", seen)
        announced, first = until_states(run, seen, lambda states: 2 not in states)
        landed_from = announced[2]
        assert min(k for (vehicle, _), k in first.items() if vehicle != 2) >= landed_from
        # communicate() closes stdin: the end of the typed commands, not of the mission.
        rest, _ = run.communicate(timeout=90)
    finally:
        run.kill()
    output = "".join(seen) + rest
    assert run.returncode == 0, output
    assert "typed commands: end of input (the mission goes on)" in output
    summary = json.loads((out / "summary.json").read_text())
    ended = summary["vehicles"]["2"]
    assert ended["state"] == "aborted", ended
    assert ended["detail"].startswith("land by the operator; disarmed on the ground"), ended
    assert {summary["vehicles"][v]["state"] for v in "134"} == {"done"}
    assert summary["metrics"]["vehicles_disarmed_at_end"] == 4  # vehicle 2 too: landed
    assert "Traceback" not in output


@pytest.mark.timeout(120)
@pytest.mark.parametrize("signals", [1, 2])
def test_ctrl_c_lands_the_swarm_and_a_second_one_stops_at_once(signals, tmp_path):
    out = tmp_path / "out"
    run = start_run(run_scenario(tmp_path, steps=2000), out)
    seen = []
    try:
        wait_for(run, r"^k=\s*8\s", seen)
        run.send_signal(signal.SIGINT)
        wait_for(run, r"run: SIGINT: landing every vehicle", seen)
        wait_for(run, r"landing vehicles 1, 2, 3, 4", seen)
        if signals == 2:
            run.send_signal(signal.SIGINT)
        rest, _ = run.communicate(timeout=90)
    finally:
        run.kill()
    output = "".join(seen) + rest
    assert run.returncode == 130, output
    assert output.strip().endswith("interrupted (SIGINT)")
    assert "Traceback" not in output
    landed = "flight ended: landed and disarmed: 1, 2, 3, 4" in output
    stopped = "run: SIGINT again: stopping at once" in output
    assert (landed, stopped) == ((True, False) if signals == 1 else (False, True)), output
    assert json.loads((out / "summary.json").read_text())["status"] == "interrupted"


@pytest.mark.mqtt
@pytest.mark.timeout(120)
def test_control_reaches_a_run_on_an_mqtt_bus(tmp_path, mosquitto):
    bus = {"kind": "mqtt", "mqtt": {"host": mosquitto.host, "port": mosquitto.port}}
    config = run_scenario(tmp_path, steps=400, bus=bus)
    out = tmp_path / "out"
    run = start_run(config, out)
    seen = []

    def control(*arguments):
        operator = start("mission_runner.cli", "control", config, *arguments)
        output, _ = operator.communicate(timeout=30)
        assert operator.returncode == 0, output
        return output

    try:
        wait_for(run, r"^k=.*v1:following", seen)
        assert "hold sent to every vehicle" in control("hold")
        until_states(run, seen, lambda states: set(states.values()) == {"held"})
        control("resume")
        until_states(run, seen, lambda states: set(states.values()) == {"following"})
        assert "land sent to vehicle 3" in control("land", "--vehicle", "3")
        until_states(run, seen, lambda states: 3 not in states)
        rest, _ = run.communicate(timeout=90)
    finally:
        run.kill()
    output = "".join(seen) + rest
    assert run.returncode == 0, output
    summary = json.loads((out / "summary.json").read_text())
    ended = summary["vehicles"]["3"]
    assert ended["state"] == "aborted", ended
    assert ended["detail"].startswith("land by the operator; disarmed on the ground"), ended
    # The mission's retained prepare is gone with it: no later control finds this mission.
    late = start("mission_runner.cli", "control", config, "hold")
    output, _ = late.communicate(timeout=30)
    assert late.returncode == 3
    assert "no mission of run_operator is running" in output

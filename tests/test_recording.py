"""The MCAP recording, read back with the ``mcap`` reader: channels and their schemas, messages per
step, poses equal to the timeseries, a flight's controller records, a vehicle process's recording
without truth, and log lines on the mission clock."""

import csv
import logging
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader

from mission_runner.checks import load_scenario, validate_scenario
from mission_runner.cli import EXIT_OK, main
from mission_runner.outputs import write_results, write_vehicle_run
from mission_runner.recording import RECORDING, LogCapture, read_recording
from mission_runner.records import ControllerState, StepRecord, VehicleRun
from mission_runner.sim.simulator import simulate

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
IDS = (1, 2, 3, 4)


def short_scenario(steps=40, **changes):
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["timing"]["steps"] = steps
    data.update(changes)
    return validate_scenario(data, "paper_tracking (short)")


def summary_of(path):
    with open(path, "rb") as handle:
        summary = make_reader(handle).get_summary()
    counts = summary.statistics.channel_message_counts
    return {
        channel.topic: (summary.schemas[channel.schema_id].name, counts[channel_id])
        for channel_id, channel in summary.channels.items()
    }


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """``mission-runner simulate`` of the paper scenario: its output folder."""
    out = tmp_path_factory.mktemp("simulate")
    code = main(
        ["simulate", str(CONFIGS / "paper_tracking.yaml"), "--out", str(out), "--no-figures"]
    )
    assert code == EXIT_OK
    return out


def test_simulate_records_every_channel_with_foxglove_schemas(simulated):
    channels = summary_of(simulated / RECORDING)
    steps = load_scenario(CONFIGS / "paper_tracking.yaml").timing.steps
    expected = {
        "/tf": ("foxglove.FrameTransforms", steps + 1),
        "/target/pose": ("foxglove.PoseInFrame", steps + 1),
        "/formation/scene": ("foxglove.SceneUpdate", steps + 1),
        "/mission/metrics": ("mission_runner.MissionMetrics", steps + 1),
    }
    for i in IDS:
        expected[f"/vehicles/{i}/pose"] = ("foxglove.PoseInFrame", steps + 1)
        expected[f"/vehicles/{i}/slot"] = ("foxglove.PoseInFrame", steps + 1)
        # A state per step that computed a command: k = 0..K-1.
        expected[f"/vehicles/{i}/state"] = ("mission_runner.VehicleState", steps)
        expected[f"/vehicles/{i}/scene"] = ("foxglove.SceneUpdate", steps)
    assert {topic: channels[topic] for topic in expected} == expected
    assert channels["/mission/events"][0] == "foxglove.Log"
    assert not list(simulated.glob(".*.partial"))


def test_a_recorded_pose_is_the_timeseries(simulated):
    rows = list(csv.DictReader((simulated / "timeseries.csv").read_text().splitlines()))
    k = 123
    poses = [m for m in read_recording(simulated / RECORDING, ["/vehicles/2/pose"])]
    pose = poses[k]
    assert pose.time_s == pytest.approx(float(rows[k]["time_s"]))
    assert pose.message.frame_id == "world"
    # world is east-north-up: x east, y north.
    assert pose.message.pose.position.x == pytest.approx(float(rows[k]["v2_east_m"]), abs=1e-6)
    assert pose.message.pose.position.y == pytest.approx(float(rows[k]["v2_north_m"]), abs=1e-6)
    assert pose.message.pose.position.z == 0.0
    target = list(read_recording(simulated / RECORDING, ["/target/pose"]))[k].message
    assert target.pose.position.y == pytest.approx(float(rows[k]["target_north_m"]), abs=1e-6)


def test_one_message_per_topic_per_step_in_mission_time(simulated):
    per_step = Counter()
    for message in read_recording(simulated / RECORDING, ["/tf", "/vehicles/3/state"]):
        per_step[(message.topic, round(message.time_s / 0.125))] += 1
    assert set(per_step.values()) == {1}
    state = next(read_recording(simulated / RECORDING, ["/vehicles/3/state"])).message
    assert state["step"] == 0
    assert state["time_s"] == 0.0
    assert state["state"] == "following"
    assert state["setpoint_lateness_s"] is None  # not measured in a simulation


def test_simulated_estimates_and_slots_are_recorded(simulated):
    scenario = load_scenario(CONFIGS / "paper_tracking.yaml")
    result = simulate(scenario)
    k = 300
    state = list(read_recording(simulated / RECORDING, ["/vehicles/1/state"]))[k].message
    estimates = {e["peer"]: (e["north_m"], e["east_m"]) for e in state["estimates"]}
    assert set(estimates) == {0, 2, 3, 4}  # vehicle 1 senses the target; never itself
    truth = result.positions_m[0, k, 0] - result.positions_m[0, k, 2]  # p_1 - p_3
    assert np.allclose(estimates[3], truth, atol=1e-6)
    slot = np.array([state["slot_north_m"], state["slot_east_m"]])
    assert np.hypot(*(slot - result.target_m[k])) > 0.5 * scenario.algorithm.radius_m
    scene = list(read_recording(simulated / RECORDING, ["/formation/scene"]))[k].message
    ids = {entity.id for entity in scene.entities}
    assert ids >= {"circle", "target", "slot_1", "slot_4"}
    circle = next(e for e in scene.entities if e.id == "circle").lines[0].points
    radii = [math.hypot(p.x - result.target_m[k, 1], p.y - result.target_m[k, 0]) for p in circle]
    assert min(radii) > 0  # the shaped circle around the target


def flight_records(result, *, start_s, holding=None):
    """Controller records that a flight of ``result`` would have produced (vehicle ``holding``
    = (id, step) holds from that step on)."""
    ids = [v.id for v in result.scenario.vehicles]
    step_s = result.scenario.timing.step_s
    records = {}
    for index, vehicle_id in enumerate(ids):
        records[vehicle_id] = []
        for k in range(result.commands_m_s.shape[1]):
            time_s = start_s + k * step_s
            held = holding is not None and vehicle_id == holding[0] and k >= holding[1]
            row = result.estimates_m[k, index]
            estimates = {peer: row[slot] for slot, peer in enumerate([0, *ids])}
            records[vehicle_id].append(
                StepRecord(
                    step=k,
                    time_s=time_s,
                    state=ControllerState.HOLDING if held else ControllerState.FOLLOWING,
                    velocity_ned_m_s=(*map(float, result.commands_m_s[0, k, index]), 0.0),
                    consensus_m_s=(0.1, -0.1),
                    phase_rad=float(result.phases_rad[0, k, index]),
                    neighbours_used=tuple(i for i in ids if i != vehicle_id),
                    estimates_m={p: e for p, e in estimates.items() if np.all(np.isfinite(e))},
                    setpoint_sent_s=time_s + 0.001 * (k % 7),
                    odometry_m=(0.0, 0.0, -5.0),
                    gated=(1,) if k == 3 else (),
                    ranges_m={
                        p: float(np.hypot(*e))
                        for p, e in estimates.items()
                        if np.all(np.isfinite(e))
                    },
                )
            )
    return records


def test_a_flight_records_its_controllers_on_the_mission_clock(tmp_path):
    scenario = short_scenario()
    result = simulate(scenario)
    start_s = 1000.0
    records = flight_records(result, start_s=start_s, holding=(2, 25))
    capture = LogCapture()
    with capture.attached():
        logging.getLogger("mission_runner.test").warning("before k = 0")
        capture.stamp(start_s + 10 * 0.125)
        logging.getLogger("mission_runner.test").warning("at step 10")
    write_results(
        result, tmp_path, figures=False, records=records, start_s=start_s, logs=capture.lines
    )
    states = [m.message for m in read_recording(tmp_path / RECORDING, ["/vehicles/2/state"])]
    assert [s["step"] for s in states] == list(range(40))
    assert states[0]["time_s"] == start_s
    assert states[5]["setpoint_lateness_s"] == pytest.approx(0.005)
    assert states[30]["state"] == "holding"
    assert states[3]["consensus_north_m_s"] == 0.1
    assert states[3]["neighbours_used"] == [1, 3, 4]
    ranges = {r["peer"]: (r["range_m"], r["gated"]) for r in states[3]["ranges"]}
    assert set(ranges) == {1, 3, 4} and ranges[1][1] and not ranges[3][1]
    assert ranges[3][0] == pytest.approx(np.hypot(*records[2][3].estimates_m[3]))
    events = [m for m in read_recording(tmp_path / RECORDING, ["/mission/events"])]
    changed = next(m for m in events if "following -> holding" in m.message.message)
    assert changed.time_s == pytest.approx(start_s + 25 * 0.125)
    assert events[-1].message.message.startswith("expectations:")
    logs = [(m.time_s, m.message.message) for m in read_recording(tmp_path / RECORDING, ["/log"])]
    assert logs == [(start_s, "before k = 0"), (pytest.approx(start_s + 1.25), "at step 10")]
    times = [m.time_s for m in read_recording(tmp_path / RECORDING)]
    assert times == sorted(times)
    assert min(times) == start_s


def test_scheduled_events_are_recorded_at_their_step(tmp_path):
    scenario = short_scenario(events=[{"kind": "vehicle_lost", "vehicle": 4, "at_step": 20}])
    result = simulate(scenario)
    write_results(result, tmp_path, figures=False)
    recorded = read_recording(tmp_path / RECORDING, ["/mission/events"])
    events = [(m.time_s, m.message.message) for m in recorded]
    assert (2.5, "event: vehicle_lost of vehicle 4 at step 20") in events
    assert (2.5, "vehicle 4: following -> absent at step 20") in events
    poses = list(read_recording(tmp_path / RECORDING, ["/vehicles/4/pose"]))
    assert len(poses) == 41  # the simulator knows where a lost vehicle stays


def test_a_vehicle_process_records_itself_in_its_odometry_frame(tmp_path):
    scenario = short_scenario(steps=20)
    result = simulate(scenario)
    records = flight_records(result, start_s=1.7e9, holding=(3, 12))[3]
    run = VehicleRun(3, mission_id="m1", state="done", records=records)
    write_vehicle_run(run, tmp_path, scenario=scenario)
    channels = summary_of(tmp_path / RECORDING)
    assert channels["/vehicles/3/state"] == ("mission_runner.VehicleState", 20)
    assert channels["/tf"] == ("foxglove.FrameTransforms", 20)
    assert "/vehicles/3/pose" not in channels  # no truth in a vehicle process
    tf = next(read_recording(tmp_path / RECORDING, ["/tf"])).message.transforms[0]
    assert (tf.parent_frame_id, tf.child_frame_id) == ("odom_3", "vehicle_3")
    assert tf.translation.z == 5.0  # NED down -5 m is 5 m up
    scene = next(read_recording(tmp_path / RECORDING, ["/vehicles/3/scene"])).message
    entity = scene.entities[0]
    assert entity.frame_id == "vehicle_3"
    assert len(entity.spheres) == 3  # vehicles 1, 2, 4 (3 does not sense the target)
    first = records[0]
    phat = first.estimates_m[1]
    assert (entity.spheres[0].pose.position.x, entity.spheres[0].pose.position.y) == (
        pytest.approx(-phat[1]),
        pytest.approx(-phat[0]),
    )
    events = [m.message.message for m in read_recording(tmp_path / RECORDING, ["/mission/events"])]
    assert events == ["vehicle 3: following -> holding at step 12"]

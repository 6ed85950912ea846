"""The real-PX4 path, flown against emulated vehicles that behave like PX4 SITL (SIH): boot clocks
at 0.986x the host's with SYSTEM_TIME on the host clock and offsets between vehicles, GPS/EKF
position error, a velocity loop that lags and loses to drag, a ground-truth stream, an arming
refusal.

The same processes a user starts against real PX4: ``mission-runner ranges --source sih``, one
``mission-runner vehicle`` per drone, ``mission-runner ground``, over a real mosquitto, each on its
own clock. What broke on real PX4 (a drifting clock mapping, late ranges, a stalled target-sensing
vehicle, a refused arm leaving the others hovering) fails here.
"""

import json
import re
import signal

import pytest
import yaml

from mission_runner.recording import RECORDING
from tests.sitl.helpers import free_port_config, free_truth_stream
from tests.test_recording import summary_of

from .flying import CONFIGS, start

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.slow]

STEPS = 600  # the whole 75 s mission at PX4 SIH's omega = pi/8
#: EKF2's odometry is ~1.2 cm per step off the truth. The vehicles keep the emulator's own velocity
#: response: with PX4 SIH's (physics airspeed_drag_1_s 1.0, velocity_integral_gain_1_s2 0.4,
#: velocity_time_constant_s 0.55, tilt_time_constant_s 0.25) the formation does not converge
#: reliably in real time - half the runs end metres off, as on real SIH - which is the open part
#: of flying real PX4 (docs/real-px4.md), not what this test guards: clocks, data in time, the
#: handshake, the outputs.
SIH_EMULATOR = {"odometry": {"position_noise_std_m": 0.009}}


def scenario_file(tmp_path, broker, **flight):
    data = yaml.safe_load((CONFIGS / "px4_sih_tracking.yaml").read_text())
    data["name"] = "px4_like"
    data["timing"]["steps"] = STEPS
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    data["flight"].update(flight)
    data["expect"] = {
        "tail_tracking_error_rms_m": {"max": 0.2},
        "vehicles_disarmed_at_end": {"min": 4},
    }
    path = tmp_path / "swarm.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, data


def emulator_file(tmp_path, data, **sections):
    positions = [
        {"north_m": v["initial_position_m"][0], "east_m": v["initial_position_m"][1]}
        for v in data["vehicles"]
    ]
    path = tmp_path / "emulator.yaml"
    emulator = {"placement": {"positions": positions}, **SIH_EMULATOR, **sections}
    path.write_text(yaml.safe_dump(emulator))
    return path


class Swarm:
    """sitl (SIH-like) + range aid + one process per vehicle + ground station; everything
    stopped on exit, whatever happened."""

    def __init__(self, tmp_path, scenario, data, *sitl_arguments, emulator=None):
        self.tmp_path, self.scenario, self.data = tmp_path, str(scenario), data
        self.emulator = emulator or {}
        n = len(data["vehicles"])
        self.ports = free_port_config(n, gcs=False)
        self.truth = free_truth_stream(n, self.ports)
        self.sitl_arguments = sitl_arguments
        self.processes = []

    def __enter__(self):
        self.sitl = start(
            "sitl",
            "--vehicles",
            str(len(self.data["vehicles"])),
            "--config",
            str(emulator_file(self.tmp_path, self.data, **self.emulator)),
            "--sih-like",
            "--no-gcs",
            "--api-port-base",
            str(self.ports.api_remote_base),
            "--api-local-port-base",
            str(self.ports.api_local_base),
            "--truth-port-base",
            str(self.truth.local_base),
            "--truth-remote-port-base",
            str(self.truth.remote_base),
            *self.sitl_arguments,
        )
        for line in self.sitl.stdout:  # the vehicles are up once sitl lists their links
            if "udpin://" in line:
                break
        return self

    def fly(self, timeout_s=200):
        mission = self.tmp_path / "mission"
        ranges = start(
            "mission_runner.cli",
            "ranges",
            self.scenario,
            "--source",
            "sih",
            "--truth-port-base",
            str(self.truth.remote_base),
            "--vision",  # as docs/real-px4.md's block: the file's EKF2 fuses it on SIH
            "50",
            "--out",
            str(mission / "truth"),
        )
        vehicles = [
            start(
                "mission_runner.cli",
                "vehicle",
                self.scenario,
                "--id",
                str(vehicle["id"]),
                "--url",
                f"udpin://0.0.0.0:{self.ports.api_remote_base + i}",
                "--out",
                str(mission / f"vehicle_{vehicle['id']}"),
            )
            for i, vehicle in enumerate(self.data["vehicles"])
        ]
        ground = start(
            "mission_runner.cli",
            "ground",
            self.scenario,
            "--out",
            str(mission),
            "--no-figures",
            "--live",  # the live view of the bus runs alongside, on a free port
            "--live-port",
            "0",
        )
        self.processes = [ranges, *vehicles, ground]
        ground_out, _ = ground.communicate(timeout=timeout_s)
        vehicle_outs = [vehicle.communicate(timeout=90)[0] for vehicle in vehicles]
        if ranges.poll() is None:
            ranges.send_signal(signal.SIGINT)
        ranges_out, _ = ranges.communicate(timeout=30)
        return mission, ground, ground_out, vehicles, vehicle_outs, ranges_out

    def __exit__(self, *exc_info):
        for process in self.processes:
            if process.poll() is None:
                process.kill()
                process.communicate(timeout=10)
        self.sitl.send_signal(signal.SIGINT)
        self.sitl.communicate(timeout=30)


@pytest.mark.timeout(330)
def test_the_mission_flies_on_px4_like_vehicles_as_separate_processes(tmp_path, mosquitto):
    scenario, data = scenario_file(tmp_path, mosquitto)
    with Swarm(tmp_path, scenario, data) as swarm:
        mission, ground, ground_out, vehicles, outputs, ranges_out = swarm.fly()

    assert re.search(r"mission \w+ over; 4 vehicle\(s\) done, lost: none", ground_out), ground_out
    assert "expectations: PASS" in ground_out, ground_out
    assert ground.returncode == 0, ground_out
    for vehicle, output in zip(vehicles, outputs, strict=True):
        assert vehicle.returncode == 0, output
    assert re.search(
        rf"ranges: {STEPS} steps \(\d+ skipped[^)]*\), \d+ ranges published", ranges_out
    ), ranges_out
    assert re.search(r"vision odometry per second: 1: [1-9]", ranges_out), ranges_out
    # The vision went on while the vehicles landed, until each said it was done.
    assert re.search(r"while the vehicles landed \(4 of 4 done\)", ranges_out), ranges_out
    for number in range(1, 5):
        summary = json.loads((mission / f"vehicle_{number}" / "summary.json").read_text())
        assert summary["state"] == "done"
        # Every step flown on fresh data: none skipped, none holding.
        assert summary["steps_by_state"] == {"following": STEPS}, summary
        # The autopilot's boot clock runs at the emulated SIH's 0.986x, and was measured so.
        assert summary["autopilot_clock_rate"] == pytest.approx(0.986, abs=0.003)
        assert summary["mission_clock_rate"] == pytest.approx(0.986, abs=0.003)
        assert summary["autopilot_params"]["COM_OBL_RC_ACT"] == 4  # on_lost: land
        # Where each step's time went, in the order a step goes; the setpoint last.
        timing = summary["step_timing_after_t_k_s"]
        order = [timing[part]["p50"] for part in ("odometry", "message_sent", "inputs")]
        assert 0 <= order[0] <= order[1] <= order[2] <= summary["setpoint_lateness_s"]["p50"]
    merged = json.loads((mission / "summary.json").read_text())
    assert merged["metrics"]["tail_tracking_error_rms_m"] < 0.2
    assert "live: ws://127.0.0.1:" in ground_out
    # Every process recorded its part: the ground the truth and all records, each vehicle itself.
    recorded = summary_of(mission / RECORDING)
    samples = len((mission / "timeseries.csv").read_text().splitlines()) - 1  # the truth's
    assert recorded["/vehicles/3/pose"] == ("foxglove.PoseInFrame", samples)
    assert recorded["/vehicles/3/state"] == ("mission_runner.VehicleState", STEPS)
    for number in range(1, 5):
        own = summary_of(mission / f"vehicle_{number}" / RECORDING)
        assert own[f"/vehicles/{number}/state"] == ("mission_runner.VehicleState", STEPS)


@pytest.mark.timeout(420)
def test_the_mission_clock_follows_autopilots_that_change_pace(tmp_path, mosquitto):
    """PX4 SIH sharing two cores with the mission ran its clock at 0.63-0.7x while everything
    started and at 1x later: the mission clock, set at the start, stayed at 0.7x, the vehicles
    had to fly 1.4x faster than the law on their autopilots' clocks, which velocity setpoints
    are not allowed to (bounded at 1.25x), and the formation ended 0.3-0.6 m off. Here the
    emulated autopilots run at 0.7x until well into the mission, then at SIH's 0.986x."""
    scenario, data = scenario_file(tmp_path, mosquitto)
    slow_start = {"clock": {"speed": 0.7, "pace": [{"after_s": 70.0, "speed": 0.986}]}}
    with Swarm(tmp_path, scenario, data, emulator=slow_start) as swarm:
        mission, ground, ground_out, _, outputs, _ = swarm.fly(timeout_s=380)

    assert re.search(r"mission \w+ starts at [0-9.]+ \(clock rate 0\.7", ground_out), ground_out
    followed = re.findall(r"clocks run at ([0-9.]+)x now: so does the mission clock", ground_out)
    # Within 1.5 %: on a loaded machine the rates the vehicles fit came out 1.2-1.6 % high
    # (1.0000x followed twice, 2026-12-04), an estimate to look into, not the clock left at 0.7x.
    assert followed and float(followed[-1]) == pytest.approx(0.986, abs=0.015), ground_out
    assert "expectations: PASS" in ground_out, ground_out
    assert ground.returncode == 0, ground_out
    for number, output in enumerate(outputs, start=1):
        summary = json.loads((mission / f"vehicle_{number}" / "summary.json").read_text())
        assert summary["steps_by_state"] == {"following": STEPS}, output
        # Asked to fly faster than its autopilot's clock allows (the setpoint scale bounded) only
        # while the ground made sure the change lasted: seconds, not the rest of the mission.
        assert summary["setpoints_scale_bounded"] <= 80, output


@pytest.mark.timeout(240)
def test_a_refused_arm_aborts_the_mission_for_everyone_with_px4s_reason(tmp_path, mosquitto):
    scenario, data = scenario_file(tmp_path, mosquitto)
    # Refused for good (PX4 asked again and again): the vehicle gives up after ARM_RETRY_S.
    with Swarm(tmp_path, scenario, data, "--deny-arming", "1:1000") as swarm:
        mission, ground, ground_out, vehicles, outputs, _ = swarm.fly(timeout_s=180)

    assert ground.returncode == 3, ground_out
    assert "Arming denied: Resolve system health failures first" in ground_out, ground_out
    assert "mission aborted, every vehicle told to land" in ground_out, ground_out
    refused = outputs[1]
    assert vehicles[1].returncode == 3, refused
    assert "arm refused" in refused, refused
    for vehicle, output in zip(vehicles, outputs, strict=True):
        assert vehicle.returncode == 3, output  # nobody flies the mission
    for number in (1, 3, 4):
        summary = json.loads((mission / f"vehicle_{number}" / "summary.json").read_text())
        assert summary["state"] == "aborted", summary

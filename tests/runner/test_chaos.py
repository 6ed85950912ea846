"""One flown mission of vehicle processes over a real mosquitto with everything going wrong that
the runner has to survive (bounded and seeded): the broker restarted, a vehicle's MAVLink link
dropped, forged and unsigned bus messages, a vehicle process killed, a foreign ground station
disarming a vehicle in flight. At the end every vehicle is accounted for, nobody was driven on
stale data, the outputs are complete and the exit codes say what happened."""

import csv
import json
import re
import signal
import time

import paho.mqtt.publish as mqtt_publish
import pytest
import yaml
from pymavlink import mavutil

from mission_runner.bus import ControlCommand, MissionControl, RangeSet, Sender
from mission_runner.bus.auth import BusKey, MessageAuth
from mission_runner.checks import load_scenario

from .flying import CONFIGS, swarm, wait_for

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.slow]

STEPS = 480


def chaos_scenario(tmp_path, broker):
    data = yaml.safe_load((CONFIGS / "paper_tracking_flyable.yaml").read_text())
    data["name"] = "chaos"
    data["timing"]["steps"] = STEPS
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    # Vehicle 2's MAVLink link drops for 0.5 s (shorter than PX4's offboard-loss timeout).
    data["events"] = [{"kind": "link_lost", "vehicle": 2, "at_step": 120, "duration_s": 0.5}]
    # Two of four are expected to finish in formation: 3 is disarmed, 4's process killed.
    data["expect"] = {"vehicles_in_formation_at_end": {"min": 2, "max": 2}}
    path = tmp_path / "chaos.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def forge(broker, topics):
    """What an intruder on the broker sends: unsigned messages, and messages signed with a key
    that is not the mission's (a land for everyone, a start an hour late, 40 m ranges)."""
    wrong = MessageAuth(BusKey.from_text("not the mission key " * 3, "the intruder"))
    now = time.time()
    bodies = [
        (topics.control(), MissionControl(ControlCommand.LAND, now, reason="forged")),
        (topics.control(), MissionControl(ControlCommand.START, now + 1000.0)),
        *(
            (topics.ranges(vehicle), RangeSet(vehicle, now, ((peer, 40.0), (4, 40.0))))
            for vehicle, peer in ((1, 2), (2, 3))
        ),
    ]
    messages = []
    for topic, message in bodies:
        body = message.to_payload()
        messages.append({"topic": topic, "payload": body})
        messages.append({"topic": topic, "payload": wrong.seal(Sender.ground(), topic, body)})
    mqtt_publish.multiple(messages, hostname=broker.host, port=broker.port)


def disarm_from_a_foreign_gcs(gcs_port, system_id):
    """Force disarm (21196) from system 200, as another ground station would."""
    link = mavutil.mavlink_connection(f"udpout:127.0.0.1:{gcs_port}", source_system=200)
    try:
        link.mav.command_long_send(
            system_id, 1, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0
        )
        ack = link.recv_match(type="COMMAND_ACK", blocking=True, timeout=10)
    finally:
        link.close()
    assert ack is not None and ack.result == mavutil.mavlink.MAV_RESULT_ACCEPTED


def steps_of(path):
    with open(path, newline="") as file:
        return list(csv.DictReader(file))


@pytest.mark.timeout(400)
def test_a_mission_through_chaos_accounts_for_every_vehicle(tmp_path, mosquitto):
    path = chaos_scenario(tmp_path, mosquitto)
    scenario = load_scenario(path)
    topics = scenario.bus.topics(scenario.name)
    mission_dir = tmp_path / "ground"
    seen = []
    with swarm(
        str(path), tmp_path, gcs=True, ground_arguments=["--no-figures", "--out", str(mission_dir)]
    ) as flying:
        ground, vehicles = flying.ground, flying.vehicles
        wait_for(ground, r"vehicle 1: following \(step 80\)", seen)
        mosquitto.kill()
        time.sleep(2.0)  # the outage itself (wall time), not a wait for anything
        mosquitto.start()
        wait_for(ground, r"vehicle 1: following \(step 1[6-9]0\)", seen)
        forge(mosquitto, topics)
        wait_for(ground, r"vehicle 1: following \(step 2[0-4]0\)", seen)
        vehicles[3].send_signal(signal.SIGKILL)
        wait_for(ground, r"vehicle 4: lost", seen)
        disarm_from_a_foreign_gcs(flying.ports.gcs_local_port(2), system_id=3)
        wait_for(ground, r"vehicle 3: taken_over", seen)
        rest, _ = ground.communicate(timeout=200)
        ground_out = "".join(seen) + rest
        outputs = [vehicle.communicate(timeout=60)[0] for vehicle in vehicles]

    # Every vehicle accounted for, by the ground station and by its own process.
    assert ground.returncode == 0, ground_out
    summary = json.loads((mission_dir / "summary.json").read_text())
    states = {vehicle: end["state"] for vehicle, end in summary["vehicles"].items()}
    assert states == {"1": "done", "2": "done", "3": "taken_over", "4": "lost"}, ground_out
    assert summary["metrics"]["vehicles_in_formation_at_end"] == 2
    assert [v.returncode for v in vehicles[:2]] == [0, 0], outputs
    assert vehicles[2].returncode != 0  # its mission did not finish: someone else has it
    assert vehicles[3].returncode == -signal.SIGKILL
    assert re.search(r"vehicle 3: taken_over", outputs[2]), outputs[2]
    # Complete outputs of every process that could write them.
    for number in (1, 2, 3):
        folder = tmp_path / f"vehicle_{number}"
        assert {"summary.json", "steps.csv", "recording.mcap"} <= {p.name for p in folder.iterdir()}
    for number in (1, 2):
        rows = steps_of(tmp_path / f"vehicle_{number}" / "steps.csv")
        assert len(rows) == STEPS
        # Held while the broker was down (no fresh data), never driven on stale data, and
        # following again after it.
        held = [int(r["step"]) for r in rows if r["state"] == "holding"]
        assert held and min(held) > 80 and max(held) < 200, held
        assert rows[-1]["state"] == "following"
        # The forgeries were dropped and counted, never acted on.
        security = json.loads((tmp_path / f"vehicle_{number}" / "summary.json").read_text())[
            "bus_security"
        ]
        assert security["messages"].get("forged", 0) >= 1, security
        assert security["messages"].get("malformed", 0) >= 1, security

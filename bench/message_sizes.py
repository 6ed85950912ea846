"""The largest messages a mission sends, sealed as they go on the bus, against the limit the
receivers and ``broker-config``'s broker enforce (``bus.auth.max_message_bytes``). Prints
figures; asserts nothing.

    python bench/message_sizes.py                  # 4, 16 and 64 vehicles
    python bench/message_sizes.py --vehicles 4 128

Every field is filled, every float at full precision (17 significant digits, negative, with an
exponent where JSON needs one), ids as long as the swarm makes them; a step message carries the
target relay, the command in force and, with ``algorithm.shared_ranges``, a range to every other
vehicle. The status detail is PX4's longest refusal seen in this project's logs, doubled.
"""

from __future__ import annotations

import argparse
import time

from mission_runner.bus import (
    AuthPolicy,
    BusKey,
    ControlCommand,
    MessageAuth,
    MissionControl,
    Sender,
    StepMessage,
    Topics,
    VehicleStatus,
    shared_range,
)
from mission_runner.bus.paho_reader import max_packet_bytes

FLOAT = -1234.5678901234567
DETAIL = (
    "arm refused (COMMAND_DENIED): Arming denied: Resolve system health failures first; "
    "mission ended: RunnerTimeoutError('every vehicle ready', 180.0)"
) * 2


def largest_step(vehicles: int) -> StepMessage:
    return StepMessage(
        vehicles,
        10**9,
        1.8e9 + 0.123456789,
        FLOAT,
        FLOAT,
        FLOAT,
        target_odometry_north_m=FLOAT,
        target_odometry_east_m=FLOAT,
        target_velocity_north_m_s=FLOAT,
        target_velocity_east_m_s=FLOAT,
        odometry_down_m=FLOAT,
        ranges_m=tuple((peer, shared_range(123.45678)) for peer in range(1, vehicles)),
        command_north_m_s=FLOAT,
        command_east_m_s=FLOAT,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, nargs="+", default=[4, 16, 64])
    arguments = parser.parse_args()
    auth = MessageAuth(BusKey.generate())
    topics = Topics.for_mission("a-mission-name-of-forty-characters-long-x")
    limit = AuthPolicy().max_message_bytes
    print(
        f"limit: bus.auth.max_message_bytes {limit} B; broker max_packet_size "
        f"{max_packet_bytes(limit)} B, message_size_limit {limit} B"
    )
    for vehicles in arguments.vehicles:
        step = largest_step(vehicles)
        status = VehicleStatus(
            vehicles, time.time(), "lost", 10**9, False, DETAIL, "0123456789ab", -FLOAT, 10**9
        )
        control = MissionControl(
            ControlCommand.START, time.time(), DETAIL, "0123456789ab", 1.0, time.time(), vehicles
        )
        sizes = {
            "step": len(
                auth.seal(Sender.vehicle(vehicles), topics.step(vehicles), step.to_payload())
            ),
            "status": len(
                auth.seal(Sender.vehicle(vehicles), topics.status(vehicles), status.to_payload())
            ),
            "control": len(auth.seal(Sender.ground(), topics.control(), control.to_payload())),
        }
        largest = max(sizes, key=lambda name: sizes[name])
        print(
            f"{vehicles:4d} vehicles: "
            + ", ".join(f"{name} {size} B" for name, size in sizes.items())
            + f"; largest {largest}: {sizes[largest] / limit:.0%} of the limit"
        )


if __name__ == "__main__":
    main()

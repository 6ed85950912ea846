"""CPU of the range aid's ground-truth path: HIL_STATE_QUATERNION datagrams (packed with
pymavlink, one frame each, as PX4's SIH sends them) through ``_TruthProtocol.datagram_received``,
with and without the vision odometry it sends back. Prints microseconds per datagram; asserts
nothing. Runs whatever ``mission_runner`` is on the path, so the same script measures an older
tree:

    nice -n 5 python bench/ranges_bench.py                   # 20000 datagrams, vision 50 Hz
    nice -n 5 python bench/ranges_bench.py --datagrams 5000 --vision-hz 100

The arrival clock is replaced by one advancing 1/truth_rate per datagram (PX4 asked for 100 Hz),
so the vision odometry goes out at its rate of that clock, as in flight (half of the datagrams
at 50 Hz).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from mission_runner.checks import load_scenario
from mission_runner.runner import ranges
from mission_runner.runner.ranges import (
    TRUTH_RATE_HZ,
    VisionOdometry,
    VisionSettings,
    _Positions,
    _TruthProtocol,
)

SCENARIO = Path(__file__).resolve().parent.parent / "configs" / "paper_tracking_flyable.yaml"
ADDRESS = ("127.0.0.1", 19450)


class SteppedClock:
    """Stands in for the ``time`` module in the aid: each ``time()`` is ``period_s`` later."""

    def __init__(self, period_s: float) -> None:
        self.now_s = 1.8e9
        self.period_s = period_s

    def time(self) -> float:
        self.now_s += self.period_s
        return self.now_s


class CountingTransport:
    """Counts what the aid sends back (the rate request, the odometry)."""

    def __init__(self) -> None:
        self.sent = 0
        self.sent_bytes = 0

    def sendto(self, data: bytes, addr: Any = None) -> None:
        self.sent += 1
        self.sent_bytes += len(data)


def recorded_like(count: int, vehicle_id: int, seed: int) -> list[bytes]:
    """``count`` datagrams of a vehicle flying a slow circle near Zurich with some jitter."""
    rng = np.random.default_rng(seed)
    packer = mavlink.MAVLink(None, srcSystem=vehicle_id, srcComponent=1)
    datagrams = []
    for index in range(count):
        angle = index / TRUTH_RATE_HZ * 0.5
        jitter = rng.normal(0.0, 1.0, 6)
        message = mavlink.MAVLink_hil_state_quaternion_message(
            0,
            [math.cos(angle / 2), 0.01 * jitter[0], 0.01 * jitter[1], math.sin(angle / 2)],
            *(0.1 * jitter[:3]),
            473977420 + round(200 * math.sin(angle)),
            85455940 + round(300 * math.cos(angle)),
            488000 + round(100 * jitter[3]),
            round(150 * math.cos(angle)),
            round(-150 * math.sin(angle)),
            round(10 * jitter[4]),
            0,
            0,
            0,
            0,
            -981,
        )
        datagrams.append(message.pack(packer))
        packer.seq = (packer.seq + 1) % 256
    return datagrams


def per_datagram_us(datagrams: list[bytes], vision_hz: float | None, repeats: int) -> float:
    """Best of ``repeats`` runs: microseconds of CPU per datagram (process time)."""
    scenario = load_scenario(SCENARIO)
    best = math.inf
    for repeat in range(repeats):
        ranges.time = SteppedClock(1.0 / TRUTH_RATE_HZ)  # type: ignore[assignment]
        vision = None
        if vision_hz is not None:
            vision = VisionOdometry(1, VisionSettings(vision_hz), np.random.default_rng(repeat))
        protocol = _TruthProtocol(_Positions(scenario), 1, TRUTH_RATE_HZ, vision)
        transport = CountingTransport()
        protocol.connection_made(transport)  # type: ignore[arg-type]
        started = time.process_time()
        for datagram in datagrams:
            protocol.datagram_received(datagram, ADDRESS)
        best = min(best, time.process_time() - started)
        assert protocol.positions.vehicles[1].received == len(datagrams), "datagrams were lost"
    ranges.time = time
    return best / len(datagrams) * 1e6


def decode_us(datagrams: list[bytes], repeats: int) -> dict[str, float]:
    """Decoding alone, microseconds per datagram: pymavlink's parser (the aid's before) and the
    aid's own decoder when this tree has it."""
    readers: dict[str, Any] = {}
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    readers["pymavlink parse_buffer"] = parser.parse_buffer
    try:
        from mission_runner.runner.mavlink_frames import TruthDecoder  # noqa: PLC0415
    except ImportError:  # a tree from before it
        pass
    else:
        readers["TruthDecoder.states"] = TruthDecoder(1).states
    figures = {}
    for name, read in readers.items():
        best = math.inf
        for _ in range(repeats):
            started = time.process_time()
            for datagram in datagrams:
                read(datagram)
            best = min(best, time.process_time() - started)
        figures[name] = best / len(datagrams) * 1e6
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--datagrams", type=int, default=20_000)
    parser.add_argument("--vision-hz", type=float, default=50.0)
    parser.add_argument("--repeats", type=int, default=5)
    arguments = parser.parse_args()
    datagrams = recorded_like(arguments.datagrams, 1, seed=0)
    print(f"mission_runner from {Path(ranges.__file__).parent.parent}")
    print(
        f"{arguments.datagrams} datagrams of {len(datagrams[0])} bytes, best of {arguments.repeats}"
    )
    truth_us = per_datagram_us(datagrams, None, arguments.repeats)
    both_us = per_datagram_us(datagrams, arguments.vision_hz, arguments.repeats)
    print(f"datagram_received, truth only:             {truth_us:6.1f} us/datagram")
    print(
        f"datagram_received, truth + vision {arguments.vision_hz:g} Hz: {both_us:6.1f} us/datagram"
    )
    for name, micros in decode_us(datagrams, arguments.repeats).items():
        print(f"decode only, {name + ':':30} {micros:6.1f} us/datagram")
    rate = 4 * TRUTH_RATE_HZ
    print(f"with vision at 4 x {TRUTH_RATE_HZ:g} Hz: {both_us * rate / 1e4:.2f} % of a core")


if __name__ == "__main__":
    main()

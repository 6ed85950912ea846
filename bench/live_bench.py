"""What ``run --live`` costs the controllers: the paper mission at 1x real time, flown without and
with the live view (the Foxglove WebSocket server, fed as ``run --live`` feeds it, and a client
subscribed to every channel and reading everything). Prints figures; asserts nothing about time.

    python bench/live_bench.py                 # 2 pairs of 240 steps (30 s each), interleaved
    python bench/live_bench.py --pairs 1 --steps 80

Lateness as in bench/flight_bench.py: the mission-clock time at which a step's setpoint had been
sent minus t_k, over every vehicle-step; a step misses its deadline past T/2.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import sys
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from flight_bench import (  # noqa: E402
    Flight,
    _cores,
    _load,
    _MissionMeter,
    paper_data,
    timing,
)

from mission_runner.checks import validate_scenario  # noqa: E402
from mission_runner.live import FlightFeed, LiveLog, LiveServer  # noqa: E402
from mission_runner.metrics import run_metrics  # noqa: E402
from mission_runner.runner.mission import fly  # noqa: E402
from tests.runner.flying import free_ports  # noqa: E402
from tests.test_live import foxglove_client  # noqa: E402


def _reader(url: str, ready: threading.Event, counts: list[int]) -> None:
    """A Foxglove client subscribed to every channel, reading until the server goes."""
    from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

    with foxglove_client(url) as client:
        client.wait_for_topics(["/tf", "/vehicles/1/state"])
        client.subscribe([channel["topic"] for channel in client.channels.values()])
        ready.set()
        with contextlib.suppress(ConnectionClosed, TimeoutError):
            while True:
                client.receive()
                counts[0] += 1


def flown(data: dict, *, live: bool) -> tuple[Flight, int]:
    """One flight (and how many messages the live client read)."""
    scenario = validate_scenario(data)
    meter = _MissionMeter()
    on_step = [meter]
    on_progress = []
    counts = [0]
    with contextlib.ExitStack() as stack:
        if live:
            server = stack.enter_context(LiveServer(scenario, port=0))
            feed = FlightFeed(scenario, server.channels)
            live_log = stack.enter_context(LiveLog(server.channels).attached())
            on_step += [feed.on_step, lambda _, record: live_log.stamp(record.time_s)]
            on_progress.append(feed.on_progress)
            ready = threading.Event()
            reader = threading.Thread(
                target=_reader, args=(server.url, ready, counts), name="foxglove-client"
            )
            reader.start()
            ready.wait(30)
            stack.callback(reader.join, 30)

        def each_step(vehicle_id: int, record: object) -> None:
            for callback in on_step:
                callback(vehicle_id, record)

        def each_progress(progress: object) -> None:
            for callback in on_progress:
                callback(progress)

        outcome = asyncio.run(
            fly(
                scenario,
                emulator_overrides=free_ports(scenario),
                on_step=each_step,
                on_progress=each_progress,
            )
        )
    metrics = {name: float(value[0]) for name, value in run_metrics(outcome.result).items()}
    flight = Flight(scenario, outcome, metrics, *meter.shares(), meter.before_start_s(), 0)
    return flight, counts[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=2, help="flights without/with (default 2)")
    parser.add_argument("--steps", type=int, default=240, help="steps per flight (default 240)")
    arguments = parser.parse_args()
    logging.getLogger().setLevel(logging.WARNING)
    logging.getLogger().addHandler(logging.NullHandler())
    data = paper_data(steps=arguments.steps, clock="realtime")
    step_s = data["timing"]["step_s"]
    print(
        f"{data['name']} at 1x real time, {arguments.steps} steps of {step_s * 1000:g} ms, "
        f"4 vehicles; without / with --live, interleaved ({_load()})"
    )
    for pair in range(arguments.pairs):
        for live in (False, True):
            flight, messages = flown(data, live=live)
            t = timing(flight)
            label = "with --live" if live else "without    "
            extra = f"; client read {messages} messages" if live else ""
            print(
                f"  {pair + 1} {label}: setpoint - t_k p50 {t.percentile_ms(50):5.1f} ms, "
                f"p99 {t.percentile_ms(99):5.1f} ms, max {t.percentile_ms(100):5.1f} ms; "
                f"{t.late} of {t.vehicle_steps} past T/2; CPU own/others {_cores(flight)} "
                f"cores; final tracking error "
                f"{flight.metrics['final_tracking_error_m']:.4f} m{extra}"
            )


if __name__ == "__main__":
    main()

"""A sparse graph in flight: fly a scenario (default ``configs/ring_enclosing_flyable.yaml``) in
lockstep on the bundled emulator, optionally with another ``algorithm.graph`` or ``beta``, and
print its metrics, how many steps each pair of vehicles ranged and coupled (from the
controllers' records), and the step at which each vehicle first coupled with a vehicle that was
not its neighbour at the start (a ring closing over a loss). Asserts nothing:

    python bench/sparse_flight.py
    python bench/sparse_flight.py --graph complete --beta 7
"""

from __future__ import annotations

import argparse
import asyncio
from collections import Counter
from pathlib import Path

import yaml

from mission_runner.checks import parse_scenario
from mission_runner.metrics import check_expectations, run_metrics
from mission_runner.runner.mission import fly
from mission_runner.wiring import neighbour_graph

SCENARIO = Path(__file__).resolve().parent.parent / "configs" / "ring_enclosing_flyable.yaml"
SHOWN = (
    "tail_tracking_error_rms_m",
    "final_localization_error_m",
    "final_phase_spacing_error_rad",
    "tracking_converged_step",
    "phase_converged_step",
    "vehicles_in_formation_at_end",
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario", nargs="?", default=str(SCENARIO))
    parser.add_argument("--graph", help="another algorithm.graph kind (complete, ring)")
    parser.add_argument("--beta", type=float, help="another algorithm.beta")
    arguments = parser.parse_args()
    data = yaml.safe_load(Path(arguments.scenario).read_text())
    if arguments.graph:
        data["algorithm"]["graph"] = {"kind": arguments.graph}
    if arguments.beta:
        data["algorithm"]["beta"] = arguments.beta
    scenario = parse_scenario(yaml.safe_dump(data), source=arguments.scenario)
    outcome = asyncio.run(fly(scenario))
    metrics = {key: value[0] for key, value in run_metrics(outcome.result).items()}
    for name in SHOWN:
        print(f"{name:32s} {metrics[name]:.4g}")
    failures = check_expectations(scenario.expect, metrics)
    print("expectations:", "PASS" if not failures else f"FAIL {failures}")
    ids = [vehicle.id for vehicle in scenario.vehicles]
    graph = neighbour_graph(scenario)
    at_start = {(ids[i], ids[j]) for i in range(len(ids)) for j in range(len(ids)) if graph[i, j]}
    ranged: Counter[tuple[int, int]] = Counter()
    coupled: Counter[tuple[int, int]] = Counter()
    first_new: dict[tuple[int, int], int] = {}
    for vehicle_id, records in outcome.records.items():
        for record in records:
            ranged.update((vehicle_id, peer) for peer in record.ranges_m if peer)
            for peer in record.neighbours_used:
                if peer:
                    coupled[vehicle_id, peer] += 1
                    if (vehicle_id, peer) not in at_start:
                        first_new.setdefault((vehicle_id, peer), record.step)
    print("steps ranged, by (vehicle, peer):", dict(sorted(ranged.items())))
    print("steps coupled, by (vehicle, peer):", dict(sorted(coupled.items())))
    print("pairs ranged that were never graph edges at the start:", sorted(set(ranged) - at_start))
    print("first step coupled with a new neighbour:", first_new)


if __name__ == "__main__":
    main()

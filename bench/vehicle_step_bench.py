"""What one flying vehicle's step of the algorithm costs: ``VehicleEnclosing.step`` of vehicle 1
of the paper's tracking scenario (4 vehicles; it ranges to the three others and to the target),
fed the trajectory the numeric simulator flies. Prints figures; asserts nothing.

    python bench/vehicle_step_bench.py [--repeat 5] [--root DIR]

The algorithm is the same code in the simulator and in flight, so a change made for the
simulator's large swarms must not slow this down. ``--root`` measures another checkout's package
with this script, so that two trees are compared in one sitting (alternate the runs).
"""

import argparse
import os
import statistics
import sys
import time
from pathlib import Path


def feeds(scenario, result):
    """The step-k arguments of vehicle 1's ``step`` for every k, from a simulated run."""
    from mission_runner.enclosing.vehicle import NeighbourReport, TargetReport  # noqa: PLC0415

    ids = [v.id for v in scenario.vehicles]
    positions, phases = result.positions_m[0], result.phases_rad[0]
    target = result.target_m
    step_s = scenario.timing.step_s
    for k in range(positions.shape[0] - 1):
        odometry = positions[k] - positions[0]
        own = positions[k, 0]
        yield {
            "own_odometry_m": odometry[0],
            "neighbours": {
                peer: NeighbourReport(float(phases[k, j]), tuple(odometry[j]))
                for j, peer in enumerate(ids)
                if j > 0
            },
            "ranges_m": {
                0: float(((own - target[k]) ** 2).sum() ** 0.5),
                **{
                    peer: float(((own - positions[k, j]) ** 2).sum() ** 0.5)
                    for j, peer in enumerate(ids)
                    if j > 0
                },
            },
            "target": TargetReport(
                tuple(target[k] - target[0]), tuple((target[k + 1] - target[k]) / step_s)
            ),
            "members": ids,
        }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="runs of every step (median)")
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    arguments = parser.parse_args()
    root = arguments.root.resolve()
    sys.path[:0] = [str(root)]
    from mission_runner.checks import load_scenario  # noqa: PLC0415 - from the checkout under --root
    from mission_runner.enclosing.vehicle import VehicleEnclosing  # noqa: PLC0415 - idem
    from mission_runner.scenario import omega_of  # noqa: PLC0415 - idem
    from mission_runner.sim.simulator import simulate  # noqa: PLC0415 - idem
    from mission_runner.wiring import algorithm_params  # noqa: PLC0415 - idem

    scenario = load_scenario(root / "configs" / "paper_tracking.yaml")
    steps = list(feeds(scenario, simulate(scenario)))
    vehicle = scenario.vehicles[0]
    ids = [v.id for v in scenario.vehicles]
    per_step = []
    for _ in range(arguments.repeat):
        law = VehicleEnclosing(
            algorithm_params(scenario),
            vehicle.id,
            ids,
            vehicle.initial_phase_rad,
            omega_of(scenario, vehicle),
        )
        started = time.perf_counter()
        for arguments_k in steps:
            law.step(**arguments_k)
        per_step.append((time.perf_counter() - started) / len(steps))
    print(
        f"{root}: vehicle {vehicle.id} of {len(ids)}, {len(steps)} steps, load "
        f"{os.getloadavg()[0]:.2f}: {statistics.median(per_step) * 1e6:.0f} us a step "
        f"(median of {arguments.repeat}; best {min(per_step) * 1e6:.0f} us)"
    )


if __name__ == "__main__":
    main()

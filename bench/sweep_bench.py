"""Runs per second of one fixed sweep here (one process, one combination after another) and on a
Dask LocalCluster of 2 worker processes. Prints figures; asserts nothing about time.

    python bench/sweep_bench.py              # 8 combinations x 10 runs x 300 steps, 3 repeats
    python bench/sweep_bench.py --repeat 1   # quicker

The sweep: the paper's tracking scenario cut to ``--steps``, ``algorithm.forgetting_factor`` x
``seed`` (4 x 2 combinations), each a batch of ``--runs``. A cluster shares out combinations (a
combination's runs are one vectorised batch on one worker), so 2 workers can at best halve the
wall time. The cluster's start and its first sweep (the workers import the package) are timed apart;
then sweeps here and on the cluster alternate, and each side's median is printed. The tables of
both are compared byte for byte.
"""

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from distributed import LocalCluster  # noqa: E402

from mission_runner.checks import load_scenario, validate_scenario  # noqa: E402
from mission_runner.sim.executors import DaskExecutor, InProcess  # noqa: E402
from mission_runner.sim.sweep import Axis, combinations, run_sweep, sweep_csv  # noqa: E402

AXES = [Axis("algorithm.forgetting_factor", (0.6, 0.7, 0.8, 0.9)), Axis("seed", (1, 2))]


def timed_sweep(found, executor):
    """Wall seconds of one sweep of ``found`` on ``executor``, and its table."""
    started = time.perf_counter()
    table = sweep_csv(run_sweep(found, executor))
    return time.perf_counter() - started, table


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--runs", type=int, default=10, help="runs per combination")
    parser.add_argument("--repeat", type=int, default=3)
    arguments = parser.parse_args()
    data = load_scenario(ROOT / "configs" / "paper_tracking.yaml").model_dump(mode="json")
    data["timing"]["steps"] = arguments.steps
    found = combinations(validate_scenario(data), AXES, arguments.runs)
    runs = len(found) * arguments.runs
    print(f"sweep: {len(found)} combinations x {arguments.runs} runs x {arguments.steps} steps")
    print(f"load average before: {os.getloadavg()[0]:.1f}")
    started = time.perf_counter()
    with (
        LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        DaskExecutor(cluster.scheduler_address) as executor,
    ):
        start_s = time.perf_counter() - started
        first_s, there_table = timed_sweep(found, executor)
        here, there = [], []
        for _ in range(arguments.repeat):  # interleaved: a shared machine's load hits both alike
            seconds, here_table = timed_sweep(found, InProcess())
            here.append(seconds)
            there.append(timed_sweep(found, executor)[0])
    here_s, there_s = statistics.median(here), statistics.median(there)
    print(f"here, one process:       {runs / here_s:6.1f} runs/s  (median {here_s:.2f} s)")
    print(f"LocalCluster, 2 workers: {runs / there_s:6.1f} runs/s  (median {there_s:.2f} s)")
    print(f"  speed-up: {here_s / there_s:.2f}x")
    print(
        f"  cluster start {start_s:.2f} s, first sweep {first_s:.2f} s (workers import the "
        f"package): {runs / (start_s + first_s):.1f} runs/s with both"
    )
    print(f"tables identical: {'yes' if here_table == there_table else 'NO'}")
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()

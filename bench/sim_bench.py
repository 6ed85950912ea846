"""Benchmarks of the numeric simulator. Prints figures; asserts nothing about time.

    python bench/sim_bench.py            # all three
    python bench/sim_bench.py --quick    # fewer repetitions

1. The paper's tracking scenario (4 vehicles, 600 steps): the vectorised simulator against a
   straightforward per-vehicle Python loop of the same equations (bench/baseline_loop.py), after
   checking both fly the same trajectory.
2. A complete graph of 256 vehicles: steps per second and memory.
3. A 1000-run batch of the paper's scenario (vectorised over runs), wall time.
4. A k-nearest graph (k = 6) of 1000 vehicles: steps per second and memory
   (``--graph`` runs this part alone).
"""

import argparse
import os
import resource
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from baseline_loop import simulate_loop  # noqa: E402

from mission_runner.checks import load_scenario, validate_scenario  # noqa: E402
from mission_runner.sim.simulator import simulate  # noqa: E402
from mission_runner.wiring import neighbour_graph  # noqa: E402


def timings(function, repeat):
    """Wall seconds of ``repeat`` calls of ``function``."""
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        function()
        times.append(time.perf_counter() - started)
    return times


def median_of(function, repeat):
    """The median wall time of ``repeat`` calls: a shared machine's slow moments count less
    than in a mean, and its one lucky run less than in a best-of."""
    return statistics.median(timings(function, repeat))


def best_of(function, repeat):
    return min(timings(function, repeat))


def ring_scenario(n, steps, radius_m=4.0, omega_rad_s=np.pi / 2, graph=None):
    """The paper's tracking scenario with n vehicles on a ring (vehicle 1 senses the target)."""
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    data = load_scenario(ROOT / "configs" / "paper_tracking.yaml").model_dump(mode="json")
    data["name"] = f"complete_graph_{n}"
    data["timing"]["steps"] = steps
    data["algorithm"]["radius_m"] = radius_m
    data["algorithm"]["omega_rad_s"] = omega_rad_s
    data["vehicles"] = [
        {
            "id": i + 1,
            "initial_position_m": [0.8 * radius_m * np.cos(a), 0.8 * radius_m * np.sin(a)],
            "initial_phase_rad": float(a * 0.9),
            "senses_target": i == 0,
        }
        for i, a in enumerate(angles)
    ]
    data["expect"] = {}
    if graph is not None:
        data["algorithm"]["graph"] = graph
    return validate_scenario(data)


def compare_with_loop(scenario, repeat):
    vectorised = simulate(scenario).positions_m[0]
    difference = np.abs(vectorised - simulate_loop(scenario)).max()
    fast = best_of(lambda: simulate(scenario), repeat)
    slow = best_of(lambda: simulate_loop(scenario), max(1, repeat // 3))
    return fast, slow, difference


def paper_speedup(repeat):
    scenario = load_scenario(ROOT / "configs" / "paper_tracking.yaml")
    fast, slow, difference = compare_with_loop(scenario, repeat)
    print("1. paper tracking scenario, 4 vehicles x 600 steps, against a per-vehicle Python loop")
    print(f"   same trajectory: max |difference| = {difference:.1e} m")
    print(
        f"   one run:  vectorised {fast * 1e3:7.1f} ms   loop {slow * 1e3:7.1f} ms   "
        f"speed-up {slow / fast:5.1f}x"
    )
    runs = 1000
    batch = best_of(lambda: simulate(scenario, runs=runs), 1)
    print(
        f"   per run in a {runs}-run batch: {batch / runs * 1e3:.2f} ms   "
        f"speed-up {slow / (batch / runs):5.1f}x   (target >= 20x)"
    )
    for n, steps in ((16, 600), (32, 300)):
        fast, slow, difference = compare_with_loop(ring_scenario(n, steps), max(1, repeat // 3))
        print(
            f"   {n} vehicles x {steps} steps, one run: vectorised {fast * 1e3:7.1f} ms   "
            f"loop {slow * 1e3:8.1f} ms   speed-up {slow / fast:5.1f}x   "
            f"(|diff| {difference:.0e} m)"
        )


def large_swarm(n, steps):
    scenario = ring_scenario(n, steps, radius_m=40.0, omega_rad_s=0.05)
    simulate(ring_scenario(n, 2, radius_m=40.0, omega_rad_s=0.05))  # warm-up
    elapsed = median_of(lambda: simulate(scenario), 5)
    tracemalloc.start()
    simulate(ring_scenario(n, 5, radius_m=40.0, omega_rad_s=0.05))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    print(f"2. complete graph, {n} vehicles ({n * (n - 1) + 1} estimated edges), {steps} steps")
    print(
        f"   {steps / elapsed:.0f} steps/s, {elapsed / steps * 1e3:.1f} ms/step, median of 5 "
        "(target >= 150 steps/s)"
    )
    print(
        f"   memory: peak traced {peak / 2**20:.0f} MiB over a 5-step run (estimator state + "
        f"temporaries); process max RSS {max_rss_mib():.0f} MiB"
    )
    return {"vehicles": n, "steps_per_s": steps / elapsed, "peak_traced_mib": peak / 2**20}


def sparse_swarm(n, k, steps):
    """Steps/s and memory of ``n`` vehicles on a k-nearest graph (on the start ring: k / 2 each
    side). The simulator keeps such a swarm per directed edge (7000 here, with the target's),
    not on ``(N, N+1)`` planes. Steps/s is of the whole run (the graph is built at its start),
    as for part 2; the marginal figure leaves out what a run costs whatever its length."""
    graph = {"kind": "k_nearest", "k": k}

    def scenario(count):
        return ring_scenario(n, count, radius_m=400.0, omega_rad_s=0.005, graph=graph)

    simulate(scenario(2))  # warm-up
    timed, short = scenario(steps), scenario(2)
    elapsed = median_of(lambda: simulate(timed), 3)
    setup = median_of(lambda: simulate(short), 3)
    tracemalloc.start()
    simulate(scenario(5))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    edges = int(np.sum(simulate_graph_degree(timed)))
    print(f"4. k-nearest graph (k = {k}), {n} vehicles ({edges} estimated edges), {steps} steps")
    print(
        f"   {steps / elapsed:.1f} steps/s, {elapsed / steps * 1e3:.1f} ms/step, median of 3 "
        "(target >= 50 steps/s)"
    )
    marginal = (elapsed - setup) / (steps - 2)
    print(
        f"   marginal: {1 / marginal:.0f} steps/s, {marginal * 1e3:.1f} ms/step (a 2-step run: "
        f"{setup * 1e3:.0f} ms)"
    )
    print(
        f"   memory: peak traced {peak / 2**20:.0f} MiB over a 5-step run; process max RSS "
        f"{max_rss_mib():.0f} MiB"
    )
    return {"vehicles": n, "steps_per_s": steps / elapsed, "peak_traced_mib": peak / 2**20}


def simulate_graph_degree(scenario):
    """Each vehicle's number of graph neighbours ``(N,)``."""
    return neighbour_graph(scenario).sum(axis=1)


def max_rss_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def big_batch(runs):
    scenario = load_scenario(ROOT / "configs" / "paper_tracking.yaml")
    started = time.perf_counter()
    result = simulate(scenario, runs=runs)
    elapsed = time.perf_counter() - started
    final = result.tracking_error_m[:, -1]
    print(f"3. batch of {runs} runs of the paper scenario (vectorised over runs, one process)")
    print(f"   {elapsed:.2f} s wall on a {os.cpu_count()}-core machine   (target < 60 s)")
    print(
        f"   final tracking error: median {np.median(final):.1e} m, p95 "
        f"{np.percentile(final, 95):.1e} m, worst {final.max():.1e} m"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    parser.add_argument("--graph", action="store_true", help="only the sparse graph (part 4)")
    arguments = parser.parse_args()
    if arguments.graph:
        sparse_swarm(1000, 6, 10 if arguments.quick else 30)
        return
    repeat = 3 if arguments.quick else 9
    paper_speedup(repeat)
    large_swarm(256, 50 if arguments.quick else 200)
    big_batch(1000)
    sparse_swarm(1000, 6, 10 if arguments.quick else 30)


if __name__ == "__main__":
    main()

"""Where a simulator step's time goes: 1000 vehicles on a k-nearest graph (k = 6), or with
``--graph complete`` 256 vehicles on the complete graph (sim_bench.py's part 2), one run under
cProfile, the cumulative time of each stage per step. Prints figures; asserts nothing.

    python bench/sim_profile.py [--steps 20] [--vehicles 1000] [--graph complete] [--root DIR]

``--root`` profiles another checkout's package (its bench/sim_bench.py builds the scenario), so
that two trees are compared with the same script in one sitting.
"""

import argparse
import cProfile
import pstats
import sys
import time
from pathlib import Path

STAGES = [
    ("sim/simulator.py", "simulate", "the whole run"),
    ("sim/simulator.py", "_step", "the steps"),
    ("sim/simulator.py", "_measure", "measurement (planes)"),
    ("sim/simulator.py", "_measure_edges", "measurement (per edge)"),
    ("enclosing/step.py", "enclosing_step", "the algorithm's step"),
    ("enclosing/step.py", "_localize", "  localization"),
    ("enclosing/step.py", "_advance_oscillators", "  oscillators"),
    ("enclosing/step.py", "_formation_errors", "  formation errors"),
    ("enclosing/step.py", "_command", "  consensus and command"),
    ("sim/simulator.py", "_record_estimation", "scoring"),
    ("wiring.py", "neighbour_graph", "the graph (once a run)"),
]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--vehicles", type=int, help="default 1000 (k-nearest), 256 (complete)")
    parser.add_argument("--graph", choices=["k_nearest", "complete"], default="k_nearest")
    parser.add_argument("--top", type=int, default=0, help="also the N costliest functions")
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    arguments = parser.parse_args()
    root = arguments.root.resolve()
    sys.path[:0] = [str(root), str(root / "bench")]
    from sim_bench import ring_scenario  # noqa: PLC0415 - from the checkout under --root

    from mission_runner.sim.simulator import simulate  # noqa: PLC0415 - idem

    complete = arguments.graph == "complete"
    n = arguments.vehicles or (256 if complete else 1000)

    def scenario(steps):
        if complete:  # as sim_bench.py's large_swarm
            return ring_scenario(n, steps, radius_m=40.0, omega_rad_s=0.05)
        graph = {"kind": "k_nearest", "k": 6}
        return ring_scenario(n, steps, radius_m=400.0, omega_rad_s=0.005, graph=graph)

    simulate(scenario(2))  # warm-up
    timed, steps = scenario(arguments.steps), arguments.steps
    started = time.perf_counter()
    simulate(timed)
    wall = time.perf_counter() - started
    profile = cProfile.Profile()
    profile.runcall(simulate, timed)
    stats = pstats.Stats(profile).stats  # type: ignore[attr-defined]
    cumulative = {
        (path, name): (calls, cum) for (path, _, name), (_, calls, _, cum, _) in stats.items()
    }
    print(f"{root}: {n} vehicles ({arguments.graph}), {steps} steps, {wall * 1e3:.0f} ms bare")
    for suffix, name, what in STAGES:
        found = [v for (path, f), v in cumulative.items() if f == name and path.endswith(suffix)]
        if found:
            calls, cum = found[0]
            per_step = cum / steps * 1e3
            print(f"  {what:28s} {calls:4d} calls  {cum * 1e3:8.1f} ms  {per_step:7.2f} ms/step")
    if arguments.top:
        pstats.Stats(profile).sort_stats("tottime").print_stats(arguments.top)


if __name__ == "__main__":
    main()

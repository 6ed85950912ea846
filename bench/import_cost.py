"""What a vehicle process pays before it flies: the CPU of importing what ``mission-runner
vehicle`` imports, and of loading a scenario. Prints figures; asserts nothing.

    python bench/import_cost.py [--runs 4] [--against DIR]

Each run is a fresh interpreter (an import is paid once a process), with the bytecode compiled
first as an install does. numpy and pydantic, which every command needs, are imported before the
clock starts and reported apart. ``--against`` alternates another checkout's runs with this one's,
so that two trees are compared in one sitting.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from bytecode import compile_packages  # noqa: E402

#: Run in the fresh interpreter: CPU seconds of each stage, as JSON on stdout.
PROBE = """
import json, resource, sys
def cpu():
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime
stages = {}
start = cpu()
import numpy, pydantic
stages["numpy and pydantic"] = cpu() - start
start = cpu()
import mission_runner.cli.vehicle, mission_runner.runner.process, mission_runner.checks
stages["the vehicle command's modules"] = cpu() - start
start = cpu()
from mission_runner.checks import load_scenario
load_scenario(sys.argv[1])
stages["first scenario load"] = cpu() - start
print(json.dumps(stages))
"""


def measure(root: Path) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(root)}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    scenario = root / "configs" / "paper_tracking_flyable.yaml"
    out = subprocess.run(
        [sys.executable, "-c", PROBE, str(scenario)],
        cwd=root, env=env, capture_output=True, text=True, check=True,
    )  # fmt: skip
    return json.loads(out.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=4, help="runs per checkout (median)")
    parser.add_argument("--against", type=Path, help="another checkout, alternated with this one")
    arguments = parser.parse_args()
    roots = [ROOT] + ([arguments.against.resolve()] if arguments.against else [])
    for root in roots:
        compile_packages(root)
    runs: dict[Path, list[dict[str, float]]] = {root: [] for root in roots}
    for _ in range(arguments.runs):
        for root in roots:
            runs[root].append(measure(root))
    print(f"CPU s, median of {arguments.runs} fresh interpreters (load {os.getloadavg()[0]:.2f})")
    for root in roots:
        stages = runs[root][0].keys()
        cells = [
            f"{stage} {statistics.median(run[stage] for run in runs[root]):.3f}" for stage in stages
        ]
        print(f"   {root}: " + ", ".join(cells))


if __name__ == "__main__":
    main()

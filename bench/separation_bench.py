"""The separation guard over random starts (numeric model). Prints figures; asserts nothing.

    python bench/separation_bench.py            # the paper's scenario and the flyable one
    python bench/separation_bench.py --runs 200 # fewer starts, quicker

For each scenario, the batch of runs (initial positions jittered, phases random; the scenario's
``batch:`` settings) without and with a 1 m guard, with exact ranges and with 5 cm (1 sigma)
range noise (what the flight configs model, e.g. sensor_noise_flight.yaml): the smallest
separation, how many runs come closer than 0.9 m, how many converge on the target (within the
scenario's tracking tolerance, 5 cm, to the end) and how fast, and the median RMS tracking error
over the last quarter of the run (a formation that stops shows here, not only in convergence).
The guard's margin is its default: three range-noise stds.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mission_runner.checks import load_scenario, validate_scenario  # noqa: E402
from mission_runner.metrics import run_metrics  # noqa: E402
from mission_runner.sim.simulator import simulate  # noqa: E402

RUNS = 1000
RANGE_NOISE_STD_M = (0.0, 0.05)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=RUNS, help="random starts per batch")
    runs = parser.parse_args().runs
    for name in ("paper_tracking", "separation_guard"):
        base = load_scenario(ROOT / "configs" / f"{name}.yaml").model_dump(mode="json")
        print(f"{name}: {runs} random starts, omega {base['algorithm']['omega_rad_s']:.3f} rad/s")
        for noise in RANGE_NOISE_STD_M:
            for guard in (None, 1.0):
                sensors = dict(base.get("sensors") or {}, range_noise_std_m=noise)
                data = dict(base, safety={"min_separation_m": guard}, sensors=sensors)
                started = time.perf_counter()
                metrics = run_metrics(simulate(validate_scenario(data, name), runs=runs))
                elapsed = time.perf_counter() - started
                print(f"  {_row(noise, guard, metrics, runs)}  ({elapsed:.1f} s)")


def _row(noise: float, guard: float | None, metrics: dict[str, np.ndarray], runs: int) -> str:
    separation = metrics["min_separation_m"]
    step = metrics["tracking_converged_step"]
    converged = step >= 0
    timing = (
        f"{np.median(step[converged]):.0f} / {np.percentile(step[converged], 95):.0f}"
        if converged.any()
        else "- / -"
    )
    return (
        f"noise {noise * 100:g} cm, guard {'off' if guard is None else f'{guard:g} m':>4}: "
        f"min separation {separation.min():.3f} m, runs < 0.9 m {int(np.sum(separation < 0.9))}; "
        f"converged {int(converged.sum())}/{runs}, step median / p95 {timing}; tail tracking "
        f"RMS median {np.median(metrics['tail_tracking_error_rms_m']):.3f} m"
    )


if __name__ == "__main__":
    main()

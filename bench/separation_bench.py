"""The separation guard over 1000 random starts (numeric model). Prints figures; asserts nothing.

    python bench/separation_bench.py            # the paper's scenario and the flyable one

For each scenario, the batch of 1000 runs (initial positions jittered, phases random; the
scenario's ``batch:`` settings) without and with a 1 m guard: the smallest separation, how many
runs come closer than 0.9 m (and 0.1 m), how many converge on the target and how fast.
"""

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mission_runner.config import load_scenario, validate_scenario  # noqa: E402
from mission_runner.sim.metrics import run_metrics  # noqa: E402
from mission_runner.sim.simulator import simulate  # noqa: E402

RUNS = 1000


def main() -> None:
    for name in ("paper_tracking", "separation_guard"):
        base = load_scenario(ROOT / "configs" / f"{name}.yaml").model_dump(mode="json")
        print(f"{name}: {RUNS} random starts, omega {base['algorithm']['omega_rad_s']:.3f} rad/s")
        for guard in (None, 1.0):
            data = dict(base, safety={"min_separation_m": guard})
            started = time.perf_counter()
            metrics = run_metrics(simulate(validate_scenario(data, name), runs=RUNS))
            elapsed = time.perf_counter() - started
            separation = metrics["min_separation_m"]
            step = metrics["tracking_converged_step"]
            converged = step >= 0
            print(
                f"  guard {'off' if guard is None else f'{guard:g} m':>5}: min separation "
                f"{separation.min():.3f} m, runs < 0.9 m {int(np.sum(separation < 0.9))}, "
                f"< 0.1 m {int(np.sum(separation < 0.1))}; tracking converged "
                f"{int(converged.sum())}/{RUNS}, step median "
                f"{np.median(step[converged]):.0f} p95 {np.percentile(step[converged], 95):.0f}"
                f"  ({elapsed:.1f} s)"
            )


if __name__ == "__main__":
    main()

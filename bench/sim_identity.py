"""Whether two checkouts simulate every bundled scenario bit for bit alike: every numeric record
of ``simulate`` (one run and a 3-run batch) of each ``configs/*.yaml`` the numeric model can play,
compared byte for byte, and for the large swarms, which may differ by rounding, the largest
difference. Prints a line per difference and a verdict; exits 1 if a bundled scenario differs.

    python bench/sim_identity.py OTHER_CHECKOUT [--root DIR]

Each checkout runs in its own process (its own package on the path) and writes .npz files to a
temporary folder.
"""

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

#: Large swarms, beyond the bundled scenarios: (vehicles, graph); None is the complete graph.
LARGE = ((100, None), (256, None), (300, {"kind": "k_nearest", "k": 6}))

DUMP = """
import dataclasses, sys, pathlib
import numpy as np
root, out = sys.argv[1], pathlib.Path(sys.argv[2])
sys.path[:0] = [root, root + "/bench"]
from mission_runner.checks import load_scenario
from mission_runner.sim.simulator import flight_only_events, simulate
from sim_bench import ring_scenario
for path in sorted(pathlib.Path(root, "configs").glob("*.yaml")):
    scenario = load_scenario(path)
    if flight_only_events(scenario):
        continue
    for runs in (1, 3):
        result = simulate(scenario, runs=runs)
        arrays = {f.name: getattr(result, f.name) for f in dataclasses.fields(result)}
        extra = arrays.pop("extra_metrics")
        arrays = {k: v for k, v in arrays.items() if isinstance(v, np.ndarray)}
        arrays.update({f"extra_metrics.{k}": np.asarray(v) for k, v in extra.items()})
        np.savez(out / f"{path.stem}_runs{runs}.npz", **arrays)
for n, graph in LARGE:
    result = simulate(ring_scenario(n, 200, radius_m=40.0, omega_rad_s=0.05, graph=graph))
    kind = "complete" if graph is None else graph["kind"]
    np.savez(out / f"large_{n}_{kind}.npz", positions_m=result.positions_m,
             phases_rad=result.phases_rad, commands_m_s=result.commands_m_s)
"""


def dump(root: Path, out: Path) -> None:
    out.mkdir()
    script = f"LARGE = {LARGE!r}\n{DUMP}"
    subprocess.run([sys.executable, "-c", script, str(root), str(out)], check=True)


def compare(first: Path, second: Path) -> int:
    """Prints the differences; returns how many bundled records differ."""
    differing = 0
    for path in sorted(first.glob("*.npz")):
        one, other = np.load(path), np.load(second / path.name)
        for name in sorted(set(one.files) | set(other.files)):
            a, b = one.get(name), other.get(name)
            if a is not None and b is not None and a.dtype == b.dtype and a.shape == b.shape:
                if a.tobytes() == b.tobytes():
                    continue
                gap = f"max |difference| {np.nanmax(np.abs(a.astype(float) - b)):.1e}"
            else:
                gap = "missing or of another shape"
            large = path.name.startswith("large_")
            differing += not large
            print(f"{'rounding' if large else 'DIFFERS '} {path.stem} {name}: {gap}")
    count = len(list(first.glob("*.npz")))
    print(f"{count} files; bundled scenarios: {differing or 'none'} differing")
    return differing


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("other", type=Path, help="the checkout to compare with")
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    arguments = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        first, second = Path(folder) / "root", Path(folder) / "other"
        dump(arguments.root.resolve(), first)
        dump(arguments.other.resolve(), second)
        sys.exit(1 if compare(first, second) else 0)


if __name__ == "__main__":
    main()

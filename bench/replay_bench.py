"""Benchmark of the recording and the replay. Prints figures; asserts nothing about time.

    python bench/replay_bench.py            # 3 repetitions
    python bench/replay_bench.py --quick    # 1

The paper's tracking scenario (4 vehicles, 600 steps) simulated once, then, each repetition:
writing its recording.mcap, and rendering its replay (every step: 601 frames, 800 px wide,
GIF only) from that recording. Target: the replay in under 30 s.
"""

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mission_runner.checks import load_scenario  # noqa: E402
from mission_runner.recording import RECORDING, write_recording  # noqa: E402
from mission_runner.replay import write_replay  # noqa: E402
from mission_runner.sim.simulator import simulate  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one repetition")
    arguments = parser.parse_args()
    repeat = 1 if arguments.quick else 3
    scenario = load_scenario(ROOT / "configs" / "paper_tracking.yaml")
    result = simulate(scenario)
    vehicles, steps = len(scenario.vehicles), scenario.timing.steps
    recording_s, replay_s = [], []
    with tempfile.TemporaryDirectory() as folder:
        for _ in range(repeat):
            started = time.perf_counter()
            write_recording(result, Path(folder) / RECORDING)
            recording_s.append(time.perf_counter() - started)
            cpu = os.times()
            started = time.perf_counter()
            files = write_replay(folder, mp4=False)
            replay_s.append(time.perf_counter() - started)
            used = os.times()
            cpu_s = (used.user - cpu.user) + (used.system - cpu.system)
            size_mb = files.gif.stat().st_size / 2**20
            width, height = files.size_px
        record_mb = (Path(folder) / RECORDING).stat().st_size / 2**20
    print(f"{scenario.name}: {vehicles} vehicles, {steps} steps")
    print(
        f"  recording.mcap: {min(recording_s):.2f} s best of {repeat} "
        f"({max(recording_s):.2f} s worst), {record_mb:.1f} MiB"
    )
    print(
        f"  replay: {files.frames} frames of {width}x{height} px in {min(replay_s):.1f} s best of "
        f"{repeat} ({max(replay_s):.1f} s worst; last run {cpu_s:.1f} s CPU), GIF {size_mb:.1f} MiB"
        f"  [target < 30 s]"
    )


if __name__ == "__main__":
    main()

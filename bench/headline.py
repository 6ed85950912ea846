"""The project's headline figures in one table, printed and written as JSON (``make bench``).

    python bench/headline.py                       # every figure (about 6 minutes on 2 cores)
    python bench/headline.py --quick               # shorter runs (about 3 minutes)
    python bench/headline.py --only demo --runs 3 --against ../other-checkout

1. ``demo``: the command ``make demo`` runs (``mission-runner run
   configs/paper_tracking_flyable.yaml``): wall time of the whole command and of its mission
   phase, CPU of the command and its children. ``--against DIR`` runs the
   same command from another checkout interleaved with this one, so both are measured in the
   same sitting on the same machine.
2. ``processes``: the mission as it flies for real, on emulated vehicles: ``emulate`` +
   ``ground`` + four ``vehicle`` processes over a private mosquitto, in real time. CPU of each
   process over its whole life (start, take-off, mission, landing), MAVSDK's threads included
   (MAVSDK 4 runs in the process), as a share of one core. The project's bytecode is compiled
   first, as after an install or a first run: with PYTHONDONTWRITEBYTECODE set and no cache,
   every process compiled its sources again (0.25-0.4 CPU s of a vehicle's 2-4). Vehicle 1's
   CPU is also printed per 5 s of its life, its Python thread apart from MAVSDK's threads.
3. ``realtime``: the tracking mission at 1x in one process: setpoint time - t_k over every
   vehicle-step (``bench/flight_bench.py``).
4. ``swarm``: the largest swarm one process holds in real time at T = 0.125 s
   (``bench/flight_bench.py``).
5. ``simulator``: the numeric simulator, 256 vehicles on a complete graph, steps per second
   (``bench/sim_bench.py``).

Nothing here asserts a time: the figures are printed and written to ``--json`` (default
``out/bench/headline.json``) with the machine's core count and load.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import yaml  # noqa: E402
from bytecode import compile_packages  # noqa: E402

DEMO_CONFIG = "configs/paper_tracking_flyable.yaml"
FLOWN = re.compile(r"flown: ([0-9.]+) s of mission in ([0-9.]+) s wall")


# --- 1. the demo command ---------------------------------------------------------------------


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def demo_once(checkout: Path, out: Path) -> dict[str, float]:
    """One ``mission-runner run`` of the demo scenario from ``checkout`` (its own packages)."""
    env = {**os.environ, "PYTHONPATH": str(checkout), "MPLBACKEND": "Agg"}
    command = [sys.executable, "-m", "mission_runner.cli", "run", DEMO_CONFIG, "--out", str(out)]
    cpu_before, started = _children_cpu_s(), time.perf_counter()
    done = subprocess.run(
        command, cwd=checkout, env=env, capture_output=True, text=True, check=False
    )
    wall_s, cpu_s = time.perf_counter() - started, _children_cpu_s() - cpu_before
    flown = FLOWN.search(done.stdout + done.stderr)
    if done.returncode != 0 or flown is None:
        raise RuntimeError(f"the demo failed in {checkout} ({done.returncode}):\n{done.stderr}")
    mission_s, phase_wall_s = float(flown.group(1)), float(flown.group(2))
    return {
        "whole_command_s": wall_s,
        "mission_phase_s": phase_wall_s,
        "mission_speedup": mission_s / phase_wall_s,
        "whole_speedup": mission_s / wall_s,
        "cpu_s": cpu_s,
    }


def bench_demo(runs: int, against: Path | None) -> dict[str, object]:
    checkouts = [ROOT] + ([against] if against is not None else [])
    results: dict[Path, list[dict[str, float]]] = {c: [] for c in checkouts}
    print(f"\n1. the demo command, {runs} run(s) per checkout, interleaved")
    print("   checkout                      whole    mission phase  speed-up (mission)   CPU")
    with tempfile.TemporaryDirectory(prefix="bench-demo-") as folder:
        for run in range(runs):
            for checkout in checkouts:
                figures = demo_once(checkout, Path(folder) / f"{run}-{checkout.name}")
                results[checkout].append(figures)
                print(
                    f"   {str(checkout)[-28:]:28s} {figures['whole_command_s']:6.2f} s   "
                    f"{figures['mission_phase_s']:6.2f} s      "
                    f"{figures['mission_speedup']:5.1f}x        {figures['cpu_s']:6.2f} s"
                )
    summary = {str(c): _medians(r) for c, r in results.items()}
    for checkout, medians in summary.items():
        print(
            f"   median {checkout[-21:]:21s} {medians['whole_command_s']:6.2f} s   "
            f"{medians['mission_phase_s']:6.2f} s      {medians['mission_speedup']:5.1f}x"
        )
    return {"this": summary[str(ROOT)], "against": summary.get(str(against)) if against else None}


def _medians(rows: list[dict[str, float]]) -> dict[str, float]:
    return {key: statistics.median(row[key] for row in rows) for key in rows[0]}


# --- 2. one process per vehicle ----------------------------------------------------------------


@contextlib.contextmanager
def _broker(folder: Path) -> Iterator[object]:
    from tests.mosquitto import MosquittoBroker, require_mosquitto  # noqa: PLC0415 - needs pytest

    require_mosquitto()
    broker = MosquittoBroker(folder / "broker")
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()


def _wait_rusage(process: subprocess.Popen[bytes]) -> float:
    """Wait for ``process``; CPU seconds of it and of every child it reaped."""
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    return usage.ru_utime + usage.ru_stime


class _CpuTimeline:
    """A process's CPU, its own thread (the Python one) and the others (MAVSDK's), read from /proc
    once a second while it lives: where in its life a vehicle process spends (start, waiting,
    mission, end). One read a second of three small files: nothing the process notices."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.samples: list[tuple[float, float, float]] = []  # (wall s, main CPU s, others CPU s)
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _read(self) -> tuple[float, float]:
        tick = os.sysconf("SC_CLK_TCK")
        main = others = 0.0
        for tid in os.listdir(f"/proc/{self.pid}/task"):
            with open(f"/proc/{self.pid}/task/{tid}/stat") as stat:
                fields = stat.read().rsplit(")", 1)[1].split()
            cpu_s = (int(fields[11]) + int(fields[12])) / tick  # utime, stime
            if int(tid) == self.pid:
                main += cpu_s
            else:
                others += cpu_s
        return main, others

    def _watch(self) -> None:
        started = time.perf_counter()
        while True:
            try:
                main, others = self._read()
            except (OSError, ValueError, IndexError):  # the process (or a thread) is gone
                return
            self.samples.append((time.perf_counter() - started, main, others))
            time.sleep(1.0)  # a bench sampling /proc, not a test

    def report(self, name: str) -> None:
        """Per 5 s of its life: the CPU of its Python thread and of its other threads."""
        self._thread.join(timeout=2.0)
        print(f"   {name}, CPU s per 5 s of its life, Python thread + other threads:")
        cells, last = [], (0.0, 0.0)
        for when, main, others in self.samples[5::5]:
            cells.append(f"{when:3.0f} s {main - last[0]:.2f}+{others - last[1]:.2f}")
            last = (main, others)
        for row in range(0, len(cells), 6):
            print("     " + "   ".join(cells[row : row + 6]))


def bench_processes(steps: int) -> dict[str, object]:
    from tests.mosquitto import TEST_BUS_KEY  # noqa: PLC0415 - needs pytest
    from tests.sitl.helpers import free_port_config  # noqa: PLC0415

    print(f"\n2. one process per vehicle over mosquitto, real time, {steps} steps")
    compile_packages(ROOT)  # as an install does: the processes read bytecode
    with (
        tempfile.TemporaryDirectory(prefix="bench-processes-") as name,
        _broker(Path(name)) as broker,
    ):
        folder = Path(name)
        data = yaml.safe_load((ROOT / DEMO_CONFIG).read_text())
        data["name"], data["timing"]["steps"] = "bench_processes", steps
        data["flight"]["clock"] = "realtime"
        data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
        scenario = folder / "scenario.yaml"
        scenario.write_text(yaml.safe_dump(data))
        ports = free_port_config(len(data["vehicles"]), gcs=False)
        env = {**os.environ, "MISSION_BUS_KEY": TEST_BUS_KEY, "PYTHONUNBUFFERED": "1"}

        def start(*arguments: str, log: str) -> tuple[subprocess.Popen[bytes], float]:
            with (folder / log).open("wb") as output:
                process = subprocess.Popen(
                    [sys.executable, "-m", "mission_runner.cli", *arguments],
                    stdin=subprocess.DEVNULL, stdout=output, stderr=subprocess.STDOUT, env=env,
                )  # fmt: skip
            return process, time.perf_counter()

        world, world_started = start(
            "emulate", str(scenario), "--no-gcs", "--api-port-base", str(ports.api_remote_base),
            "--api-local-port-base", str(ports.api_local_base), log="world.log",
        )  # fmt: skip
        _wait_for_line(folder / "world.log", "world on the mqtt bus", world)
        ground, ground_started = start(
            "ground", str(scenario), "--out", str(folder / "mission"), log="ground.log"
        )
        vehicles = [
            start(
                "vehicle", str(scenario), "--id", str(i + 1), "--url",
                f"udpin://0.0.0.0:{ports.api_remote_base + i}", "--out",
                str(folder / f"vehicle_{i + 1}"), log=f"vehicle_{i + 1}.log",
            )
            for i in range(len(data["vehicles"]))
        ]  # fmt: skip
        timeline = _CpuTimeline(vehicles[0][0].pid)
        rows = {}
        for i, (process, started) in enumerate(vehicles, start=1):
            cpu_s = _wait_rusage(process)
            rows[f"vehicle {i}"] = (cpu_s, time.perf_counter() - started, process.returncode)
        cpu_s = _wait_rusage(ground)
        rows["ground"] = (cpu_s, time.perf_counter() - ground_started, ground.returncode)
        world.send_signal(2)
        cpu_s = _wait_rusage(world)
        rows["emulate (emulator + world)"] = (cpu_s, time.perf_counter() - world_started, 0)
        failed = [name for name, (_, _, code) in rows.items() if code != 0]
        if failed:
            log = (folder / "ground.log").read_text()[-3000:]
            raise RuntimeError(f"process mission failed ({', '.join(failed)}):\n{log}")
    print("   process                          CPU s   wall s   share of a core")
    shares = {}
    for name, (cpu_s, wall_s, _) in rows.items():
        shares[name] = 100 * cpu_s / wall_s
        print(f"   {name:30s} {cpu_s:7.2f}  {wall_s:7.1f}   {shares[name]:6.2f} %")
    vehicle_shares = [v for k, v in shares.items() if k.startswith("vehicle")]
    timeline.report("vehicle 1")
    print(
        f"   a vehicle process (MAVSDK's threads included): {min(vehicle_shares):.2f}-"
        f"{max(vehicle_shares):.2f} % of a core"
    )
    return {"vehicle_cpu_percent_max": max(vehicle_shares), "processes": shares}


def _wait_for_line(log: Path, text: str, process: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        if text in log.read_text(errors="replace"):
            return
        if process.poll() is not None:
            break
        time.sleep(0.1)  # a bench polling a log file, not a test
    raise RuntimeError(f"no {text!r} in {log}:\n{log.read_text(errors='replace')[-2000:]}")


# --- 3-5. the other benches' headline figures --------------------------------------------------


def bench_realtime(steps: int) -> dict[str, object]:
    import flight_bench  # noqa: PLC0415 - bench/ is on sys.path

    return flight_bench.bench_realtime(steps, reference=False)


def bench_swarm(sizes: list[int], seconds: float) -> dict[str, object]:
    import flight_bench  # noqa: PLC0415

    return flight_bench.bench_swarm(sizes, seconds, budget_s=300.0)


def bench_simulator(steps: int) -> dict[str, object]:
    import sim_bench  # noqa: PLC0415

    return sim_bench.large_swarm(256, steps)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="shorter runs")
    parser.add_argument(
        "--only",
        choices=["demo", "processes", "realtime", "swarm", "simulator"],
        action="append",
        help="one figure (repeatable); default every figure",
    )
    parser.add_argument("--runs", type=int, help="demo runs per checkout (default 3; quick 1)")
    parser.add_argument("--against", type=Path, help="another checkout to run the demo from")
    parser.add_argument("--json", type=Path, default=ROOT / "out" / "bench" / "headline.json")
    args = parser.parse_args(argv)
    only = args.only or ["demo", "processes", "realtime", "swarm", "simulator"]
    quick = args.quick
    started = time.perf_counter()
    print(f"headline figures on {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}")
    figures: dict[str, object] = {"cores": os.cpu_count(), "load_1min": os.getloadavg()[0]}
    if "demo" in only:
        figures["demo"] = bench_demo(args.runs or (1 if quick else 3), args.against)
    if "processes" in only:
        figures["processes"] = bench_processes(160 if quick else 600)
    if "realtime" in only:
        figures["realtime"] = bench_realtime(80 if quick else 240)
    if "swarm" in only:
        sizes = [8, 16] if quick else [8, 12, 16, 24, 32, 48, 64]
        figures["swarm"] = bench_swarm(sizes, 10.0 if quick else 20.0)
    if "simulator" in only:
        figures["simulator"] = bench_simulator(50 if quick else 200)
    figures["wall_s"] = time.perf_counter() - started
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(figures, indent=2) + "\n")
    print(f"\nwritten {args.json} ({figures['wall_s']:.0f} s)")


if __name__ == "__main__":
    main()

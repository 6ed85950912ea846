"""Benchmarks of flown missions (MAVSDK over UDP against the bundled emulator). Prints figures;
asserts nothing about time.

    python bench/flight_bench.py            # all three figures (about 5 minutes on 2 cores)
    python bench/flight_bench.py --quick    # shorter runs, fewer sizes (about 2 minutes)

1. The paper's tracking mission (configs/paper_tracking_flyable.yaml: 4 vehicles + target,
   600 steps = 75 s simulated) in lockstep, several times: wall time of the mission phase
   (k = 0 to the last step) and of the whole run (emulator start, take-off, mission, landing),
   and the speed-up over real time.
2. The same mission at 1x real time, cut to ``--realtime-steps`` steps: the controllers' loop
   timing. A step's lateness is the mission-clock time at which its setpoint had been sent minus
   t_k (``StepRecord.setpoint_sent_s - time_s``); a step misses its deadline when the setpoint
   goes out later than t_k + T/2. A vehicle-step is short-handed when the law ran without some
   neighbour that was flying that step (its ``neighbours_used`` lacks a vehicle whose controller
   also ran step k and that is its neighbour in the scenario's graph). The same truncated mission
   in lockstep is flown as the reference for the tracking error.
3. Swarm size at T = 0.125 s in real time: N vehicles on a ring (vehicle 1 senses the target,
   each at its own altitude 4 + 0.5 i m), ``--swarm-seconds`` simulated each; N = 4, 8, 12, ...
   until it clearly fails. The largest N with >= 99 % of vehicle-steps on time holds real time.
   These runs end in ``hold`` instead of landing, to spend the wall time on the mission.
   ``--swarm-graph ring``: each vehicle hears, couples with and ranges to its two ring neighbours
   only (``algorithm.graph``), instead of all N - 1.

Every run gets free UDP ports. Besides the figures, each run reports the CPU used during the
mission phase, in cores: by this process (emulator, controllers, bus and MAVSDK all run in it)
and by everything else on the machine (from /proc/stat), as other work disturbs real time.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# Run from a checkout without installing: the repository root holds the packages.
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mission_runner.checks import load_scenario, validate_scenario  # noqa: E402
from mission_runner.cli.stopping import run_async  # noqa: E402
from mission_runner.config import Scenario  # noqa: E402
from mission_runner.metrics import run_metrics  # noqa: E402
from mission_runner.runner.mission import FlightOutcome, fly  # noqa: E402
from mission_runner.wiring import neighbour_graph  # noqa: E402
from tests.runner.flying import free_ports  # noqa: E402

CONFIG = ROOT / "configs" / "paper_tracking_flyable.yaml"
EMULATOR_MAX_VEHICLES = 250
ON_TIME_TARGET = 0.99
CLEAR_FAILURE = 0.90


# --- measuring one flight --------------------------------------------------------------------


def _cpu_ticks() -> tuple[int, int]:
    """(busy, total) jiffies of the whole machine since boot."""
    with open("/proc/stat", encoding="ascii") as stat:
        values = [int(v) for v in stat.readline().split()[1:]]
    idle = values[3] + values[4]  # idle + iowait
    return sum(values) - idle, sum(values)


class _MissionMeter:
    """on_step hook: wall and CPU time between the first and the last step of the mission."""

    def __init__(self) -> None:
        self.latest_step = -1
        self.created = time.perf_counter()
        self.first: tuple[float, float, tuple[int, int]] | None = None
        self.last: tuple[float, float, tuple[int, int]] | None = None

    def _now(self) -> tuple[float, float, tuple[int, int]]:
        return time.perf_counter(), time.process_time(), _cpu_ticks()

    def __call__(self, _vehicle_id: int, record: object) -> None:
        # Once per step (the first vehicle to finish it), so a run that breaks off still counts.
        step = record.step  # type: ignore[attr-defined]
        if step == 0 and self.first is None:
            self.first = self._now()
        elif step > self.latest_step:
            self.last = self._now()
        self.latest_step = max(self.latest_step, step)

    def shares(self) -> tuple[float, float]:
        """(Python process CPU, other processes' CPU), in cores, over the mission phase."""
        if self.first is None or self.last is None or self.last[0] <= self.first[0]:
            return math.nan, math.nan
        wall = self.last[0] - self.first[0]
        busy = self.last[2][0] - self.first[2][0]
        total = self.last[2][1] - self.first[2][1]
        own = (self.last[1] - self.first[1]) / wall
        machine = (os.cpu_count() or 1) * busy / total if total else math.nan
        return own, max(machine - own, 0.0)

    def before_start_s(self) -> float:
        """Wall seconds from the call of fly() to step 0 (start, connection, take-off)."""
        return self.first[0] - self.created if self.first is not None else math.nan


class _WarningCounter(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        self.count += 1


@dataclass
class Flight:
    """One flown scenario and what the bench reads from it."""

    scenario: Scenario
    outcome: FlightOutcome
    metrics: dict[str, float]
    process_cpu: float
    others_cpu: float
    before_start_s: float
    warnings: int


def flown(data: dict) -> Flight:
    scenario = validate_scenario(data)
    meter = _MissionMeter()
    counter = _WarningCounter()
    logging.getLogger().addHandler(counter)
    try:
        # run_async keeps the outcome out of asyncio's main task, whose repr (arrays and all)
        # asyncio.run formats at its end: seconds for a large swarm.
        outcome = run_async(fly(scenario, emulator_overrides=free_ports(scenario), on_step=meter))
    finally:
        logging.getLogger().removeHandler(counter)
    metrics = {name: float(value[0]) for name, value in run_metrics(outcome.result).items()}
    return Flight(
        scenario, outcome, metrics, *meter.shares(), meter.before_start_s(), counter.count
    )


@dataclass
class Timing:
    """Loop timing over every vehicle-step of a flight."""

    lateness_s: np.ndarray
    step_s: float
    short_handed: int = 0
    holding: int = 0
    steps_affected: set[int] = field(default_factory=set)
    lost: int = 0  # vehicles whose controller gave up before the last step

    @property
    def vehicle_steps(self) -> int:
        return len(self.lateness_s)

    @property
    def late(self) -> int:
        return int(np.sum(self.lateness_s > self.step_s / 2))

    @property
    def on_time(self) -> float:
        return 1.0 - self.late / self.vehicle_steps if self.vehicle_steps else math.nan

    def percentile_ms(self, q: float) -> float:
        return float(np.percentile(self.lateness_s, q) * 1000.0)


def timing(flight: Flight) -> Timing:
    step_s = flight.scenario.timing.step_s
    records = flight.outcome.records
    flying_at: dict[int, set[int]] = {}
    for vehicle_id, vehicle_records in records.items():
        for record in vehicle_records:
            flying_at.setdefault(record.step, set()).add(vehicle_id)
    lateness: list[float] = []
    short_handed = holding = 0
    affected: set[int] = set()
    graph = neighbour_graph(flight.scenario)  # no losses in the benches: the graph stays put
    ids = [vehicle.id for vehicle in flight.scenario.vehicles]
    graph_neighbours = {i: {ids[j] for j in np.flatnonzero(graph[n])} for n, i in enumerate(ids)}
    for vehicle_id, vehicle_records in records.items():
        for record in vehicle_records:
            late_s = record.setpoint_sent_s - record.time_s
            lateness.append(late_s)
            neighbours = (flying_at[record.step] - {vehicle_id}) & graph_neighbours[vehicle_id]
            missing = not neighbours <= set(record.neighbours_used)
            short_handed += missing
            holding += record.state != "following"
            if missing or late_s > step_s / 2:
                affected.add(record.step)
    steps = flight.scenario.timing.steps
    lost = sum(len(vehicle_records) < steps for vehicle_records in records.values())
    return Timing(np.asarray(lateness, dtype=float), step_s, short_handed, holding, affected, lost)


# --- scenarios ---------------------------------------------------------------------------------


def paper_data(*, steps: int | None = None, clock: str = "lockstep") -> dict:
    data = load_scenario(CONFIG).model_dump(mode="json")
    if steps is not None:
        data["timing"]["steps"] = steps
    data["flight"]["clock"] = clock
    data["flight"]["speed"] = 1.0
    return data


def swarm_data(n: int, seconds: float, graph: str = "complete") -> dict:
    """The paper's mission with ``n`` vehicles on a ring, in real time, ending in hold; ``graph``
    the neighbourhood graph (``complete`` as in the paper, or ``ring``: each vehicle couples
    with, ranges to and hears its two neighbours in ring order, at the ring's beta of
    configs/ring_enclosing_flyable.yaml)."""
    data = paper_data(clock="realtime")
    step_s = data["timing"]["step_s"]
    data["name"] = f"swarm_{n}"
    data["timing"]["steps"] = max(1, round(seconds / step_s))
    template = {k: v for k, v in data["vehicles"][1].items() if k not in {"senses_target"}}
    radius_m = max(data["algorithm"]["radius_m"], n / (2 * math.pi))  # >= 1 m apart on the ring
    vehicles = []
    for i in range(n):
        angle = 2 * math.pi * i / n
        vehicles.append(
            {
                **template,
                "id": i + 1,
                "initial_position_m": [radius_m * math.cos(angle), radius_m * math.sin(angle)],
                "initial_phase_rad": 0.9 * angle,  # not evenly spaced: the oscillators must work
                "senses_target": i == 0,
                "altitude_m": 4.0 + 0.5 * i,  # never two at one height
            }
        )
    data["vehicles"] = vehicles
    data["flight"]["end_action"] = "hold"
    data["flight"]["autopilot_params"] = {
        **data["flight"].get("autopilot_params", {}),
        "MPC_ACC_HOR": 5.0,
    }
    data["expect"] = {}
    if graph != "complete":
        data["algorithm"]["graph"] = {"kind": graph}
        data["algorithm"]["beta"] = 4.0
    return data


# --- the three benchmarks ----------------------------------------------------------------------


def _load() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min) {five:.2f} (5 min)"


def _cores(flight: Flight) -> str:
    """'own/others' CPU in cores over the mission phase."""
    if not math.isfinite(flight.process_cpu):
        return "   -/-   "
    return f"{flight.process_cpu:4.2f}/{flight.others_cpu:4.2f}"


def bench_lockstep(runs: int, steps: int | None) -> None:
    data = paper_data(steps=steps, clock="lockstep")
    step_s, count = data["timing"]["step_s"], data["timing"]["steps"]
    mission_s = step_s * count
    print(
        f"\n1. {data['name']} in lockstep: {len(data['vehicles'])} vehicles, {count} steps "
        f"= {mission_s:g} s simulated, {runs} runs ({_load()})"
    )
    print(
        "   run   mission phase  speed-up   whole run  (before k=0)  mission/whole  "
        "CPU own/others  final tracking error"
    )
    missions, wholes = [], []
    for run in range(1, runs + 1):
        flight = flown(data)
        outcome = flight.outcome
        mission_wall, whole_wall = outcome.mission_wall_time_s, outcome.wall_time_s
        missions.append(mission_wall)
        wholes.append(whole_wall)
        print(
            f"   {run:3d}   {mission_wall:10.2f} s  {mission_s / mission_wall:6.1f}x"
            f"   {whole_wall:7.2f} s  {flight.before_start_s:9.2f} s  "
            f"{mission_s / whole_wall:11.1f}x      {_cores(flight)}  "
            f"{flight.metrics['final_tracking_error_m']:.4f} m"
        )
    mission, whole = statistics.median(missions), statistics.median(wholes)
    print(
        f"   median mission phase {mission:.2f} s = {mission_s / mission:.1f}x real time "
        f"(target >= 10x); median whole run {whole:.2f} s = {mission_s / whole:.1f}x "
        f"(start, MAVSDK connection, take-off and landing included)"
    )


def bench_realtime(steps: int, reference: bool) -> dict[str, float]:
    data = paper_data(steps=steps, clock="realtime")
    step_s = data["timing"]["step_s"]
    print(
        f"\n2. {data['name']} at 1x real time, cut to {steps} steps = {steps * step_s:g} s "
        f"(the full mission is 600 steps); T = {step_s * 1000:g} ms, deadline T/2 = "
        f"{step_s * 500:g} ms ({_load()})"
    )
    flight = flown(data)
    t = timing(flight)
    outcome = flight.outcome
    print(
        f"   whole run {outcome.wall_time_s:.1f} s wall, mission phase "
        f"{outcome.mission_wall_time_s:.2f} s wall for {steps * step_s:g} s simulated; "
        f"CPU own/others {_cores(flight)} cores; emulator max lag "
        f"{outcome.emulator_stats.max_lag_s * 1000:.0f} ms, {flight.warnings} warnings logged"
    )
    print("   setpoint time - t_k over all vehicle-steps:")
    print(
        f"     p50 {t.percentile_ms(50):6.1f} ms   p99 {t.percentile_ms(99):6.1f} ms   "
        f"max {t.percentile_ms(100):6.1f} ms"
    )
    print(
        f"   missed deadline (> T/2): {t.late} of {t.vehicle_steps} vehicle-steps "
        f"({100 * (1 - t.on_time):.2f} %)"
    )
    print(
        f"   ran without some flying neighbour's message: {t.short_handed} of "
        f"{t.vehicle_steps} vehicle-steps; steps with any miss or late setpoint: "
        f"{len(t.steps_affected)} of {steps}; vehicle-steps holding: {t.holding}"
    )
    figures = {
        "setpoint_late_p50_ms": t.percentile_ms(50),
        "setpoint_late_p99_ms": t.percentile_ms(99),
        "missed_deadlines": t.late,
        "vehicle_steps": t.vehicle_steps,
        "short_handed": t.short_handed,
    }
    line = (
        f"   final tracking error {flight.metrics['final_tracking_error_m']:.4f} m "
        f"(tail RMS {flight.metrics['tail_tracking_error_rms_m']:.4f} m)"
    )
    if reference:
        ref = flown(paper_data(steps=steps, clock="lockstep"))
        line += (
            f"; same {steps} steps in lockstep: {ref.metrics['final_tracking_error_m']:.4f} m "
            f"(tail RMS {ref.metrics['tail_tracking_error_rms_m']:.4f} m)"
        )
    print(line)
    return figures


def bench_swarm(
    sizes: list[int], seconds: float, budget_s: float, graph: str = "complete"
) -> dict[str, object]:
    step_s = paper_data()["timing"]["step_s"]
    print(
        f"\n3. Swarm size in real time at T = {step_s:g} s, {graph} graph, "
        f"{seconds:g} s simulated per size, "
        f"on time = setpoint within T/2 of t_k ({_load()})"
    )
    print(
        "     N  vehicle-steps  on time   late  median late   p99 late   short-handed  "
        "lost  CPU own/others  emu lag  run wall"
    )
    started = time.perf_counter()
    holds, below = None, 0
    on_time: dict[int, float] = {}
    for n in sizes:
        if n > EMULATOR_MAX_VEHICLES:
            print(f"   {n}: above the emulator's {EMULATOR_MAX_VEHICLES} vehicles; stopping")
            break
        try:
            flight = flown(swarm_data(n, seconds, graph))
        except Exception as error:  # a size that cannot even be flown has clearly failed
            print(f"   {n:3d}  failed: {type(error).__name__}: {error}")
            break
        t = timing(flight)
        outcome = flight.outcome
        print(
            f"   {n:3d}  {t.vehicle_steps:13d}  {100 * t.on_time:6.2f} %  {t.late:5d}  "
            f"{t.percentile_ms(50):8.1f} ms  {t.percentile_ms(99):6.1f} ms  {t.short_handed:12d}  "
            f"{t.lost:4d}       {_cores(flight)}  "
            f"{outcome.emulator_stats.max_lag_s * 1000:4.0f} ms  {outcome.wall_time_s:6.1f} s"
        )
        on_time[n] = t.on_time
        if t.on_time >= ON_TIME_TARGET:
            holds, below = n, 0
        else:
            below += 1
        if t.on_time < CLEAR_FAILURE or below >= 2:
            break
        if time.perf_counter() - started > budget_s:
            print(f"   (time budget of {budget_s:g} s spent; stopping)")
            break
    if holds is None:
        print("   no size held real time (>= 99 % on time)")
    else:
        print(f"   largest swarm holding real time (>= 99 % on time): N = {holds}")
    return {"largest_real_time_swarm": holds, "on_time_by_size": on_time, "graph": graph}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="shorter runs, fewer sizes")
    parser.add_argument("--only", choices=["lockstep", "realtime", "swarm"], action="append")
    parser.add_argument("--lockstep-runs", type=int, help="default 3 (quick: 1)")
    parser.add_argument("--lockstep-steps", type=int, help="default: the config's 600")
    parser.add_argument("--realtime-steps", type=int, help="default 240 = 30 s (quick: 80)")
    parser.add_argument("--swarm-seconds", type=float, help="default 20 (quick: 10)")
    parser.add_argument(
        "--swarm-sizes", help="comma-separated N (default 4,8,12,...,64; quick: 4,8,16,32)"
    )
    parser.add_argument(
        "--swarm-budget", type=float, default=360.0, help="wall seconds before no larger N starts"
    )
    parser.add_argument(
        "--swarm-graph", choices=["complete", "ring"], default="complete", help="default complete"
    )
    parser.add_argument("--verbose", action="store_true", help="show the runs' log warnings")
    args = parser.parse_args(argv)
    # Warnings are counted per run (and shown with --verbose), not interleaved with the tables.
    root = logging.getLogger()
    root.setLevel(logging.WARNING)
    handler = logging.StreamHandler() if args.verbose else logging.NullHandler()
    handler.setFormatter(logging.Formatter("   [%(levelname)s %(name)s] %(message)s"))
    root.addHandler(handler)
    quick = args.quick
    runs = args.lockstep_runs or (1 if quick else 3)
    realtime_steps = args.realtime_steps or (80 if quick else 240)
    swarm_seconds = args.swarm_seconds or (10.0 if quick else 20.0)
    if args.swarm_sizes:
        sizes = [int(n) for n in args.swarm_sizes.split(",")]
    else:
        sizes = [4, 8, 16, 32] if quick else list(range(4, 65, 4))
    only = set(args.only or ["lockstep", "realtime", "swarm"])
    started = time.perf_counter()
    print(f"flight bench on {os.cpu_count()} cores, Python {sys.version.split()[0]}")
    if "lockstep" in only:
        bench_lockstep(runs, args.lockstep_steps)
    if "realtime" in only:
        bench_realtime(realtime_steps, reference=True)
    if "swarm" in only:
        bench_swarm(sizes, swarm_seconds, args.swarm_budget, args.swarm_graph)
    print(f"\ntotal wall time {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()

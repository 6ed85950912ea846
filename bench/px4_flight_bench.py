"""The mission on real PX4 SITL (SIH): the block of docs/real-px4.md ("Real PX4 SITL, step by
step") run as it stands, with ``configs/px4_sih_tracking.yaml``, and what each process costs.

    python bench/px4_flight_bench.py --px4-dir ~/PX4-Autopilot                # 1 run at 1x
    python bench/px4_flight_bench.py --px4-dir ~/PX4-Autopilot --speed 2 --runs 5 --json out.json

Needs a PX4-Autopilot checkout built with ``make px4_sitl_default`` (or its
build/px4_sitl_default) and mosquitto on PATH (or /usr/sbin). Each run, in a fresh temporary
folder (the processes' working directory, so the mission's outputs land in its out/):
``broker-config`` into broker/, mosquitto with that configuration, ``px4-sitl --px4-dir DIR
[--speed S]``, ``ranges --source sih --vision 50``, ``vehicle --id i`` for every vehicle (its
PX4 instance's MAVSDK port) and ``ground``, each with its own broker login and the bus key, as
the block starts them. The scenario's broker port (1883) is used when it is free; else a free
one, in a copy of the scenario that differs only there. When ``ground`` ends, every process is
stopped (SIGTERM to its process group, SIGKILL after a grace period), the PX4 instances too (each
runs in a session of its own under ``px4-sitl``).

Printed per run: the ground's verdict (``expectations: PASS``/``FAIL``) and exit code, tail
tracking RMS and the other metrics from the mission's summary.json, the steps each vehicle flew
following the law (of the steps it flew; skipped steps) and when its setpoints left after t_k
on the mission clock (an autopilot at speed factor s sees the mission's wall-clock delays s
times over) from its own summary.json, and how many of its steps awaited their inputs until the
step deadline (ran without one that came too late) from its steps.csv, the range
aid's last line, the load average at the start and the end; and per process (each vehicle
process, MAVSDK's threads included as MAVSDK 4 runs in the process; the range aid; ground;
px4-sitl's own Python; each PX4 instance; mosquitto): CPU seconds over its life (user +
system from /proc, polled every 0.5 s, with its child processes) and that as a share of one
core over its life. Figures only: nothing here asserts a time or a result.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import yaml  # noqa: E402
from bytecode import compile_packages  # noqa: E402

CONFIG = ROOT / "configs" / "px4_sih_tracking.yaml"
TICK_S = os.sysconf("SC_CLK_TCK")
POLL_S = 0.5
GRACE_S = 10.0
#: After ``ground`` ends, how long the vehicles get to land and exit by themselves [s].
VEHICLES_EXIT_S = 60.0


# --- /proc ---------------------------------------------------------------------------------


def _stat(pid: int) -> tuple[str, str, int, float, float] | None:
    """comm, state, parent pid, CPU seconds (user + system) and start (seconds since boot) of
    ``pid``; None once it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    comm = text[text.index("(") + 1 : text.rindex(")")]
    fields = text.rsplit(")", 1)[1].split()
    cpu_s = (int(fields[11]) + int(fields[12])) / TICK_S
    return comm, fields[0], int(fields[1]), cpu_s, int(fields[19]) / TICK_S


def _uptime_s() -> float:
    return float(Path("/proc/uptime").read_text().split()[0])


def _px4_instance(pid: int) -> str | None:
    """``px4 <i>`` for a PX4 SITL process (``px4 -i <i> ...``), else None."""
    with contextlib.suppress(OSError, ValueError, IndexError):
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        if Path(argv[0].decode()).name == "px4" and b"-i" in argv:
            return f"px4 {int(argv[argv.index(b'-i') + 1])}"
    return None


@dataclass
class Usage:
    """One watched process and its descendants: the last CPU seconds seen of each pid."""

    start_s: float
    last_seen_s: float
    cpu_by_pid: dict[int, float] = field(default_factory=dict)

    @property
    def cpu_s(self) -> float:
        return sum(self.cpu_by_pid.values())

    @property
    def life_s(self) -> float:
        return self.last_seen_s - self.start_s


@dataclass
class Watcher:
    """Polls /proc every :data:`POLL_S`: the CPU of each named process with its descendants,
    a PX4 instance anywhere below counted under its own name (``px4 <i>``), not its parent's."""

    roots: dict[str, int] = field(default_factory=dict)
    usage: dict[str, Usage] = field(default_factory=dict)
    #: Every PX4 process seen, and its name.
    px4_pids: dict[int, str] = field(default_factory=dict)
    stop: threading.Event = field(default_factory=threading.Event)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def watch(self, name: str, pid: int) -> None:
        with self.lock:
            self.roots[name] = pid

    def run(self) -> None:
        while not self.stop.is_set():
            self.poll()
            self.stop.wait(POLL_S)
        self.poll()

    def poll(self) -> None:
        now = _uptime_s()
        stats = {pid: s for pid in _pids() if (s := _stat(pid)) is not None}
        children: dict[int, list[int]] = {}
        for pid, stat in stats.items():
            children.setdefault(stat[2], []).append(pid)
        with self.lock:
            roots = dict(self.roots)
        for name, pid in roots.items():
            if pid in stats:
                self._visit(name, pid, stats, children, now, root=True)

    def _visit(
        self, name: str, pid: int, stats: dict, children: dict, now: float, *, root: bool
    ) -> None:
        """Count ``pid`` under ``name`` and its descendants under ``name`` or their own PX4
        instance's; a root's life runs from its start to the last poll that saw it running."""
        _, state, _, cpu_s, start_s = stats[pid]
        usage = self.usage.setdefault(name, Usage(start_s, now))
        usage.cpu_by_pid[pid] = max(cpu_s, usage.cpu_by_pid.get(pid, 0.0))
        if root and state != "Z":
            usage.last_seen_s = now
        for child in children.get(pid, []):
            instance = _px4_instance(child)
            if instance is None:
                self._visit(name, child, stats, children, now, root=False)
            else:
                self.px4_pids[child] = instance
                self._visit(instance, child, stats, children, now, root=True)


def _pids() -> list[int]:
    return [int(entry) for entry in os.listdir("/proc") if entry.isdigit()]


# --- processes -----------------------------------------------------------------------------


@dataclass
class Run:
    """One run's folder, environment and processes."""

    folder: Path
    config: Path
    port: int
    env: dict[str, str]
    processes: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    def start(self, name: str, command: list[str], watcher: Watcher) -> subprocess.Popen[bytes]:
        """``command`` in a process group of its own, output to logs/<name>.log."""
        log = self.folder / "logs" / f"{name.replace(' ', '_')}.log"
        with log.open("wb") as output:
            process = subprocess.Popen(
                command, cwd=self.folder, env=self.env, stdin=subprocess.DEVNULL,
                stdout=output, stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip
        self.processes[name] = process
        watcher.watch(name, process.pid)
        return process

    def mission_runner(self, name: str, watcher: Watcher, *arguments: str) -> None:
        command = [sys.executable, "-m", "mission_runner.cli", *arguments]
        self.start(name, command, watcher)

    def log(self, name: str) -> str:
        path = self.folder / "logs" / f"{name.replace(' ', '_')}.log"
        return path.read_text(errors="replace") if path.exists() else ""


def _port_free(port: int) -> bool:
    with socket.socket() as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _scenario(folder: Path) -> tuple[Path, int]:
    """The scenario file and broker port: the file as it is if its port is free, else a copy
    with a free port."""
    data = yaml.safe_load(CONFIG.read_text())
    port = int(data["bus"]["mqtt"]["port"])
    if _port_free(port):
        return CONFIG, port
    port = _free_port()
    data["bus"]["mqtt"]["port"] = port
    copy = folder / CONFIG.name
    copy.write_text(yaml.safe_dump(data, sort_keys=False))
    return copy, port


def _prepare(folder: Path) -> Run:
    (folder / "logs").mkdir(parents=True)
    config, port = _scenario(folder)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"}
    command = [sys.executable, "-m", "mission_runner.cli", "broker-config", str(config)]
    if config != CONFIG:
        command += ["--port", str(port)]
    subprocess.run(  # the broker's files: logins, ACL, bus key
        [*command, "--out", "broker"], cwd=folder, env=env, check=True, stdout=subprocess.DEVNULL
    )
    env["MISSION_BUS_KEY"] = (folder / "broker" / "bus.key").read_text().strip()
    return Run(folder, config, port, env)


def _wait_port(port: int, process: subprocess.Popen[bytes], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and process.poll() is None:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.5):
            return
        time.sleep(0.1)  # a bench waiting for a broker to listen
    raise RuntimeError(f"mosquitto did not listen on {port} (exit code {process.poll()})")


def _launch(run: Run, watcher: Watcher, px4_dir: str, speed: float) -> None:
    """The block of docs/real-px4.md, in its order."""
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    broker_conf = str(run.folder / "broker" / "mosquitto.conf")
    _wait_port(run.port, run.start("mosquitto", [mosquitto, "-c", broker_conf], watcher))
    config, auth = str(run.config), ["--bus-credentials", "broker/credentials"]
    speed_args = [] if speed == 1 else ["--speed", f"{speed:g}"]
    run.mission_runner("px4-sitl", watcher, "px4-sitl", config, "--px4-dir", px4_dir, *speed_args)
    run.mission_runner(
        "ranges", watcher, "ranges", config, "--source", "sih", "--vision", "50", *auth
    )
    for i in _vehicle_ids():
        url = f"udpin://0.0.0.0:{14539 + i}"
        run.mission_runner(f"vehicle {i}", watcher, "vehicle", config, "--id", str(i), *auth,
                           "--url", url)  # fmt: skip
    run.mission_runner("ground", watcher, "ground", config, *auth)


def _vehicle_ids() -> list[int]:
    return [int(v["id"]) for v in yaml.safe_load(CONFIG.read_text())["vehicles"]]


def _signal(pid: int, number: signal.Signals) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, number)


def _stop(pids: list[int], grace_s: float = GRACE_S) -> None:
    """SIGTERM to each process group of ``pids``, SIGKILL to those still there after
    ``grace_s``."""
    for pid in pids:
        _signal(pid, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and any(_alive(pid) for pid in pids):
        time.sleep(0.1)  # a bench waiting for processes to exit
    for pid in pids:
        _signal(pid, signal.SIGKILL)


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (not a zombie: a child of this process is reaped here)."""
    with contextlib.suppress(ChildProcessError):
        if os.waitpid(pid, os.WNOHANG)[0]:
            return False
    stat = _stat(pid)
    return stat is not None and stat[1] != "Z"


def _shutdown(run: Run, watcher: Watcher) -> None:
    """The vehicles get :data:`VEHICLES_EXIT_S` to end by themselves; then everything stops,
    the broker last, and any PX4 instance that outlived ``px4-sitl`` with it."""
    vehicles = [p for name, p in run.processes.items() if name.startswith("vehicle")]
    deadline = time.monotonic() + VEHICLES_EXIT_S
    while time.monotonic() < deadline and any(p.poll() is None for p in vehicles):
        time.sleep(0.2)  # a bench waiting on processes
    watcher.poll()
    rest = [p.pid for name, p in run.processes.items() if name != "mosquitto"]
    _stop(rest)
    # Each PX4 instance leads a session of its own: stopped above by px4-sitl, else here.
    _stop([pid for pid, name in watcher.px4_pids.items() if _px4_instance(pid) == name], 2.0)
    if "mosquitto" in run.processes:
        _stop([run.processes["mosquitto"].pid])
    for process in run.processes.values():
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=5)
    left = [p for p, name in watcher.px4_pids.items() if _px4_instance(p) == name and _alive(p)]
    if left:
        raise RuntimeError(f"PX4 processes still running after the stop: {left}")


# --- one run -------------------------------------------------------------------------------


def fly(px4_dir: str, speed: float, timeout_s: float, keep: bool) -> dict[str, Any]:
    """One run of the block; its figures."""
    folder = Path(tempfile.mkdtemp(prefix="px4-flight-bench-"))
    watcher = Watcher()
    thread = threading.Thread(target=watcher.run, name="bench-proc-poll", daemon=True)
    load_start = os.getloadavg()
    started = time.monotonic()
    run = _prepare(folder)
    thread.start()
    try:
        _launch(run, watcher, px4_dir, speed)
        ground = run.processes["ground"]
        try:
            code: int | None = ground.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            code = None
        wall_s = time.monotonic() - started
    finally:
        _shutdown(run, watcher)
        watcher.stop.set()
        thread.join()
    result = _result(run, watcher, code, wall_s)
    result.update(speed=speed, load_start=load_start, load_end=os.getloadavg())
    result["folder"] = str(folder) if keep else None
    if not keep:
        shutil.rmtree(folder, ignore_errors=True)
    return result


def _mission_dir(run: Run) -> Path:
    name = yaml.safe_load(run.config.read_text())["name"]
    return run.folder / "out" / f"{name}-mission"


def _read_json(path: Path) -> dict[str, Any]:
    with contextlib.suppress(OSError, ValueError):
        return dict(json.loads(path.read_text()))
    return {}


def _scalar(value: Any) -> Any:
    while isinstance(value, list) and len(value) == 1:
        value = value[0]
    return value


def _result(run: Run, watcher: Watcher, code: int | None, wall_s: float) -> dict[str, Any]:
    mission = _mission_dir(run)
    summary = _read_json(mission / "summary.json")
    ground_log = run.log("ground").splitlines()
    verdict = next((line for line in ground_log if line.startswith("expectations:")), None)
    vehicles = {}
    for i in _vehicle_ids():
        own = _read_json(mission / f"vehicle_{i}" / "summary.json")
        vehicles[i] = {
            "steps": own.get("steps"),
            "following": own.get("steps_by_state", {}).get("following"),
            "skipped": own.get("skipped_steps"),
            "state": own.get("state"),
            # On the mission clock: what an autopilot at speed factor s sees of the mission's
            # wall-clock delays, s times over.
            "setpoint_after_t_k_s": own.get("setpoint_lateness_s", {}),
            "at_deadline": _at_deadline(mission / f"vehicle_{i}" / "steps.csv", run.config),
        }
    ranges_lines = [line for line in run.log("ranges").splitlines() if line.strip()]
    return {
        "ground_exit_code": code,
        "verdict": verdict or f"no verdict (ground exit code {code})",
        "ground_lines": [line for line in ground_log if line.startswith("ground: ")],
        "metrics": {k: _scalar(v) for k, v in summary.get("metrics", {}).items()},
        "vehicles": vehicles,
        "ranges_last_line": ranges_lines[-1] if ranges_lines else None,
        "wall_s": wall_s,
        "processes": {
            name: {"cpu_s": u.cpu_s, "life_s": u.life_s, "core_percent": _share(u)}
            for name, u in sorted(watcher.usage.items(), key=lambda item: _order(item[0]))
        },
    }


def _at_deadline(steps_csv: Path, config: Path) -> tuple[int, int]:
    """(steps whose inputs were awaited until the step deadline, steps with a timing): those
    ran without an input that came too late."""
    deadline_s = float(yaml.safe_load(config.read_text())["flight"]["step_deadline_s"])
    with contextlib.suppress(OSError), steps_csv.open() as rows:
        waits = [row["inputs_lateness_s"] for row in csv.DictReader(rows)]
        timed = [float(w) for w in waits if w not in ("", "nan")]
        return sum(w >= deadline_s - 0.001 for w in timed), len(timed)
    return 0, 0


def _share(usage: Usage) -> float:
    return 100.0 * usage.cpu_s / usage.life_s if usage.life_s > 0 else float("nan")


def _order(name: str) -> tuple[int, str]:
    kinds = ("vehicle", "ranges", "ground", "px4-sitl", "px4 ", "mosquitto")
    return next((i for i, kind in enumerate(kinds) if name.startswith(kind)), len(kinds)), name


# --- output --------------------------------------------------------------------------------


def print_result(number: int, r: dict[str, Any]) -> None:
    m = r["metrics"]
    tail = m.get("tail_tracking_error_rms_m")
    print(
        f"run {number} (speed {r['speed']:g}): {r['verdict']}; ground exit {r['ground_exit_code']}"
        f"; tail_tracking_error_rms_m {_fmt(tail)}; wall {r['wall_s']:.0f} s"
    )
    print("  load average at start {:.2f} {:.2f} {:.2f}".format(*r["load_start"])
          + ", at end {:.2f} {:.2f} {:.2f}".format(*r["load_end"]))  # fmt: skip
    for line in r["ground_lines"]:
        print(f"  {line}")
    shown = ("final_tracking_error_m", "steps_on_stale_data", "min_separation_m")
    extra = ", ".join(f"{k} {_fmt(m[k])}" for k in shown if k in m)
    if extra:
        print(f"  {extra}")
    for i, v in r["vehicles"].items():
        print(
            f"  vehicle {i}: {v['following']} / {v['steps']} steps following, "
            f"{v['skipped']} skipped, ended {v['state']}{_lateness(v['setpoint_after_t_k_s'])}"
            f"; inputs awaited until the deadline: {v['at_deadline'][0]} of {v['at_deadline'][1]}"
        )
    if r["ranges_last_line"]:
        print(f"  range aid: {r['ranges_last_line']}")
    print("  process              CPU s   life s   share of a core")
    for name, p in r["processes"].items():
        print(f"  {name:18s} {p['cpu_s']:7.1f}  {p['life_s']:7.1f}   {p['core_percent']:6.1f} %")
    if r["folder"]:
        print(f"  logs and outputs kept in {r['folder']}")


def _lateness(percentiles: dict[str, float]) -> str:
    if not percentiles:
        return ""
    shown = ", ".join(f"{k} {1000 * v:.0f}" for k, v in percentiles.items())
    return f"; setpoint after t_k (mission ms): {shown}"


def _fmt(value: Any) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--px4-dir", required=True, help="PX4-Autopilot checkout, built")
    parser.add_argument("--speed", type=float, default=1.0, help="PX4 speed factor (default 1)")
    parser.add_argument("--runs", type=int, default=1, help="runs in a row (default 1)")
    parser.add_argument("--json", type=Path, help="write every run's figures here")
    parser.add_argument("--timeout", type=float, default=900.0, help="per run, for ground [s]")
    parser.add_argument("--keep", action="store_true", help="keep each run's folder (logs)")
    arguments = parser.parse_args(argv)
    compile_packages(ROOT)  # as an install does: the processes read bytecode
    results = []
    for number in range(1, arguments.runs + 1):
        result = fly(arguments.px4_dir, arguments.speed, arguments.timeout, arguments.keep)
        print_result(number, result)
        results.append(result)
        if arguments.json:
            arguments.json.parent.mkdir(parents=True, exist_ok=True)
            arguments.json.write_text(json.dumps({"cores": os.cpu_count(), "runs": results}))


if __name__ == "__main__":
    main()

"""One process per vehicle over a real mosquitto, for growing swarms: how many vehicle processes
hold real time on this machine, what each process costs, and what the broker carries.

    python bench/swarm_processes_bench.py                    # N = 4 8 12 16, 20 s of mission each
    python bench/swarm_processes_bench.py --sizes 4 8 --seconds 10

For each N: ``mission-runner emulate`` (the N emulated vehicles and the world) + ``ground`` + N
``vehicle`` processes on a private mosquitto, the paper's mission with N vehicles on a ring
(``flight_bench.swarm_data``: complete graph, real time, ends in hold). Printed per N:

- real time held: every process exited 0, >= 99 % of vehicle-steps sent their setpoint within
  T/2 of t_k (``setpoint_lateness_s`` in each vehicle's steps.csv), >= 95 % of vehicle-steps
  used every other vehicle's step message (``neighbours_used``: complete graph);
- CPU % of one core over the mission window (first to last t_k) of each process (/proc), and
  the largest resident set (``ru_maxrss`` of the reaped process; the broker's VmHWM);
- the broker's messages and bytes per second, in (published) and out (delivered), from
  mosquitto's own ``$SYS/broker/{messages,bytes}/{received,sent}`` counters sampled every
  second and read at the mission window's ends.

Then, from the measured mean size of a message into the broker and T, what a complete graph
needs at N = 100 and 1000: every vehicle publishes one step message per step and each goes
to the N - 1 others, so the broker takes in N / T and hands out N (N - 1) / T step messages
per second (the ground station's and the world's subscriptions add N / T each on top).
Stops at the first N that does not hold real time. Asserts nothing.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import csv
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import paho.mqtt.client as paho  # noqa: E402
import yaml  # noqa: E402
from bytecode import compile_packages  # noqa: E402
from flight_bench import swarm_data  # noqa: E402

ON_TIME_TARGET = 0.99
NEIGHBOURS_TARGET = 0.95
SYS_TOPICS = ("messages/received", "messages/sent", "bytes/received", "bytes/sent")
TICK_S = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of process ``pid`` so far, from /proc; NaN once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return float("nan")
    return (int(fields[11]) + int(fields[12])) / TICK_S


def peak_rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    return 0


@dataclass
class Sampler:
    """Every second: UNIX time, the CPU seconds of each watched pid, the broker's $SYS
    counters (a paho client on the broker, sys_interval 1)."""

    host: str
    port: int
    pids: dict[str, int] = field(default_factory=dict)
    samples: list[tuple[float, dict[str, float], dict[str, float]]] = field(default_factory=list)
    counters: dict[str, float] = field(default_factory=dict)
    stop: threading.Event = field(default_factory=threading.Event)

    def run(self) -> None:
        client = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id="bench-sys")
        client.on_message = lambda _c, _u, message: self.count(message.topic, message.payload)
        client.connect(self.host, self.port)
        for topic in SYS_TOPICS:
            client.subscribe(f"$SYS/broker/{topic}")
        client.subscribe("#")
        client.loop_start()
        try:
            while not self.stop.wait(1.0):
                cpu = {name: cpu_s(pid) for name, pid in list(self.pids.items())}
                self.samples.append((time.time(), cpu, dict(self.counters)))
        finally:
            client.loop_stop()
            client.disconnect()

    def count(self, topic: str, payload: bytes) -> None:
        """A $SYS counter's new value, or one more mission message of its kind (the topic's
        last level: step, ranges, target, status, control) and its size on the wire (payload,
        topic, 4 B of MQTT header: a QoS 0 PUBLISH)."""
        if topic.startswith("$SYS/broker/"):
            self.counters[topic.removeprefix("$SYS/broker/")] = float(payload)
            return
        kind = topic.rsplit("/", 1)[-1]
        for key, value in (
            (f"{kind} messages", 1),
            (f"{kind} bytes", len(payload) + len(topic) + 4),
        ):
            self.counters[key] = self.counters.get(key, 0.0) + value

    def at(self, t: float) -> tuple[float, dict[str, float], dict[str, float]]:
        """The first sample at or after UNIX time ``t`` (the last one if none)."""
        return next((s for s in self.samples if s[0] >= t), self.samples[-1])

    def before(self, t: float) -> tuple[float, dict[str, float], dict[str, float]]:
        """The last sample at or before UNIX time ``t`` (the first one if none)."""
        return next((s for s in reversed(self.samples) if s[0] <= t), self.samples[0])


@dataclass
class Outcome:
    """One swarm's run."""

    n: int
    step_s: float
    codes: dict[str, int]
    maxrss_kib: dict[str, int]
    cpu_percent: dict[str, float]
    on_time: float
    all_neighbours: float
    following: float
    window_s: float
    rates: dict[str, float]
    #: Peer -> how many vehicle-steps went without its step message.
    missed: dict[int, int] = field(default_factory=dict)

    @property
    def held(self) -> bool:
        return (
            not any(self.codes.values())
            and self.on_time >= ON_TIME_TARGET
            and self.all_neighbours >= NEIGHBOURS_TARGET
        )


def _steps(folder: Path, n: int) -> tuple[list[dict[str, str]], float, float]:
    """Every vehicle's steps.csv rows; the mission window (first and last t_k, UNIX time)."""
    rows = []
    for i in range(1, n + 1):
        path = folder / f"vehicle_{i}" / "steps.csv"
        if path.exists():
            with path.open() as file:
                rows += [{**row, "vehicle": str(i)} for row in csv.DictReader(file)]
    times = [float(row["time_s"]) for row in rows] or [0.0]
    return rows, min(times), max(times)


def _start(folder: Path, env: dict[str, str], log: str, *arguments: str) -> subprocess.Popen[bytes]:
    with (folder / log).open("wb") as output:
        return subprocess.Popen(
            [sys.executable, "-m", "mission_runner.cli", *arguments],
            stdin=subprocess.DEVNULL, stdout=output, stderr=subprocess.STDOUT, env=env,
        )  # fmt: skip


def _wait_for_line(log: Path, text: str, process: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + 120.0
    while time.monotonic() < deadline and process.poll() is None:
        if text in log.read_text(errors="replace"):
            return
        time.sleep(0.1)  # a bench polling a log file, not a test
    raise RuntimeError(f"no {text!r} in {log}:\n{log.read_text(errors='replace')[-2000:]}")


def _reap(process: subprocess.Popen[bytes], deadline: float) -> tuple[int, int]:
    """Wait for ``process`` until ``deadline`` (monotonic; then kill it); exit code, max RSS."""
    while True:
        pid, status, usage = os.wait4(process.pid, os.WNOHANG)
        if pid:
            process.returncode = os.waitstatus_to_exitcode(status)
            return process.returncode, usage.ru_maxrss
        if time.monotonic() > deadline:
            process.kill()
            deadline = float("inf")
        time.sleep(0.2)  # a bench waiting on processes, not a test


def _scenario(folder: Path, n: int, seconds: float, host: str, port: int) -> Path:
    data = swarm_data(n, seconds)
    data["name"] = f"procs_{n}"
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": host, "port": port}}
    path = folder / "scenario.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _fly(folder: Path, n: int, scenario: Path, sampler: Sampler) -> dict[str, tuple[int, int]]:
    """emulate + ground + n vehicles; exit code and max RSS of each, once all are done."""
    from tests.mosquitto import TEST_BUS_KEY  # noqa: PLC0415 - needs pytest
    from tests.sitl.helpers import free_port_config  # noqa: PLC0415

    ports = free_port_config(n, gcs=False)
    env = {**os.environ, "MISSION_BUS_KEY": TEST_BUS_KEY, "PYTHONUNBUFFERED": "1"}
    world = _start(
        folder, env, "world.log", "emulate", str(scenario), "--no-gcs", "--api-port-base",
        str(ports.api_remote_base), "--api-local-port-base", str(ports.api_local_base),
    )  # fmt: skip
    _wait_for_line(folder / "world.log", "world on the mqtt bus", world)
    ground = _start(folder, env, "ground.log", "ground", str(scenario), "--out", str(folder))
    vehicles = {
        f"vehicle {i}": _start(
            folder, env, f"vehicle_{i}.log", "vehicle", str(scenario), "--id", str(i),
            "--url", f"udpin://0.0.0.0:{ports.api_remote_base + i - 1}",
            "--out", str(folder / f"vehicle_{i}"),
        )
        for i in range(1, n + 1)
    }  # fmt: skip
    sampler.pids.update({"emulate": world.pid, "ground": ground.pid})
    sampler.pids.update({name: process.pid for name, process in vehicles.items()})
    deadline = time.monotonic() + 600.0
    done = {name: _reap(process, deadline) for name, process in vehicles.items()}
    done["ground"] = _reap(ground, deadline)
    world.send_signal(signal.SIGINT)
    done["emulate"] = _reap(world, time.monotonic() + 30.0)
    return done


def run_swarm(n: int, seconds: float, *, keep: bool = False) -> Outcome:
    from tests.mosquitto import MosquittoBroker  # noqa: PLC0415 - needs pytest

    with contextlib.ExitStack() as stack:
        name = tempfile.mkdtemp(prefix=f"bench-procs-{n}-")
        if not keep:
            stack.callback(shutil.rmtree, name, ignore_errors=True)
        folder = Path(name)
        broker = MosquittoBroker(folder / "broker")
        with broker.config_path.open("a") as config:
            config.write("sys_interval 1\n")
        broker.start()
        sampler = Sampler(broker.host, broker.port)
        thread = threading.Thread(target=sampler.run, name="bench-sampler")
        try:
            assert broker._process is not None
            sampler.pids["broker"] = broker._process.pid
            thread.start()
            scenario = _scenario(folder, n, seconds, broker.host, broker.port)
            done = _fly(folder, n, scenario, sampler)
            broker_rss = peak_rss_kib(broker._process.pid)
        finally:
            sampler.stop.set()
            if thread.is_alive():
                thread.join()
            broker.stop()
        if keep:
            print(f"      outputs kept in {folder}")
        return _outcome(n, folder, done, broker_rss, sampler)


def _outcome(
    n: int, folder: Path, done: dict[str, tuple[int, int]], broker_rss: int, sampler: Sampler
) -> Outcome:
    step_s = yaml.safe_load((folder / "scenario.yaml").read_text())["timing"]["step_s"]
    rows, first, last = _steps(folder, n)
    t0, cpu0, sys0 = sampler.at(first)
    t1, cpu1, sys1 = sampler.before(last)
    window_s = max(t1 - t0, 1e-9)
    cpu = {name: 100 * (cpu1[name] - cpu0[name]) / window_s for name in cpu1 if name in cpu0}
    rates = {key: (sys1.get(key, 0) - sys0.get(key, 0)) / window_s for key in sys1}
    lateness = [float(row["setpoint_lateness_s"]) for row in rows]
    everyone = set(range(1, n + 1))
    complete = [  # 0 in neighbours_used is the target, for the vehicle that senses it
        everyone - {int(row["vehicle"])} <= {int(i) for i in row["neighbours_used"].split()}
        for row in rows
    ]
    vehicle_steps = max(len(rows), 1)
    missed = collections.Counter(  # whose step message a vehicle's step went without
        peer
        for row in rows
        for peer in everyone
        - {int(row["vehicle"])}
        - {int(i) for i in row["neighbours_used"].split()}
    )
    return Outcome(
        n=n,
        step_s=step_s,
        codes={name: code for name, (code, _) in done.items()},
        maxrss_kib={**{name: rss for name, (_, rss) in done.items()}, "broker": broker_rss},
        cpu_percent=cpu,
        on_time=sum(late <= step_s / 2 for late in lateness) / vehicle_steps,
        all_neighbours=sum(complete) / vehicle_steps,
        following=sum(row["state"] == "following" for row in rows) / vehicle_steps,
        window_s=window_s,
        rates=rates,
        missed=dict(missed),
    )


def print_outcome(o: Outcome) -> None:
    vehicles = [v for k, v in o.cpu_percent.items() if k.startswith("vehicle")]
    rss = [v / 1024 for k, v in o.maxrss_kib.items() if k.startswith("vehicle")]
    failed = [name for name, code in o.codes.items() if code]
    print(
        f"N={o.n:3d} {'HELD' if o.held else 'NOT HELD':8s} on time {o.on_time:6.1%}, all "
        f"neighbours {o.all_neighbours:6.1%}, following {o.following:6.1%}, window "
        f"{o.window_s:.0f} s" + (f"; failed: {', '.join(failed)}" if failed else "")
    )
    if o.missed:
        worst = sorted(o.missed.items(), key=lambda item: -item[1])
        print(
            "      vehicle-steps without a peer's step message, by peer: "
            + ", ".join(f"{peer}: {count}" for peer, count in worst)
        )
    print(
        f"      CPU % of a core: vehicle {min(vehicles, default=0):.1f}-"
        f"{max(vehicles, default=0):.1f} (sum {sum(vehicles):.0f}), ground "
        f"{o.cpu_percent.get('ground', 0):.1f}, emulate {o.cpu_percent.get('emulate', 0):.1f}, "
        f"broker {o.cpu_percent.get('broker', 0):.1f}"
    )
    print(
        f"      max RSS MiB: vehicle {max(rss, default=0):.0f}, ground "
        f"{o.maxrss_kib['ground'] / 1024:.0f}, emulate {o.maxrss_kib['emulate'] / 1024:.0f}, "
        f"broker {o.maxrss_kib['broker'] / 1024:.1f}"
    )
    r = o.rates
    kinds = sorted(key.split()[0] for key in r if key.endswith(" messages"))
    mission = sum(r[f"{kind} messages"] for kind in kinds)
    mission_bytes = sum(r[f"{kind} bytes"] for kind in kinds)
    print(
        f"      broker: in {r.get('messages/received', 0):.0f} msg/s "
        f"{r.get('bytes/received', 0) / 1e3:.1f} kB/s, out to the swarm "
        f"{r.get('messages/sent', 0) - mission:.0f} msg/s "
        f"{(r.get('bytes/sent', 0) - mission_bytes) / 1e3:.1f} kB/s (the bench's own `#` "
        "subscriber's copies taken off)"
    )
    print(
        "      published: "
        + ", ".join(
            f"{kind} {r[f'{kind} messages']:.1f}/s x {step_bytes(o, kind):.0f} B" for kind in kinds
        )
    )


def step_bytes(outcome: Outcome, kind: str = "step") -> float:
    """Mean size on the wire of a ``kind`` message (payload, topic, header) [B]."""
    r = outcome.rates
    return r.get(f"{kind} bytes", 0) / max(r.get(f"{kind} messages", 0), 1e-9)


def project(outcome: Outcome, sizes: list[int]) -> None:
    """What a complete graph asks of one broker at ``sizes``, from ``outcome``'s measured step
    message size and broker CPU per message handled (in + out)."""
    r, step_s = outcome.rates, outcome.step_s
    size_b = step_bytes(outcome)
    handled = r.get("messages/received", 0) + r.get("messages/sent", 0)
    cpu_us = 1e6 * outcome.cpu_percent.get("broker", 0) / 100 / max(handled, 1)
    print(
        f"\ncomplete graph, T = {step_s} s: the broker takes in N/T step messages a second and "
        f"hands out N(N-1)/T; a step message is {size_b:.0f} B on the wire (measured at "
        f"N={outcome.n}; without algorithm.shared_ranges its size does not grow with N); the "
        f"broker spent {cpu_us:.1f} us of CPU a message handled (in + out, measured)"
    )
    for n in sizes:
        into, out = n / step_s, n * (n - 1) / step_s
        print(
            f"N={n:5d}: in {into:,.0f} msg/s ({into * size_b / 1e6:.2f} MB/s), out {out:,.0f} "
            f"msg/s ({out * size_b / 1e6:,.1f} MB/s = {8 * out * size_b / 1e9:,.2f} Gbit/s); "
            f"~{(into + out) * cpu_us / 1e6:,.1f} cores of broker CPU at the measured cost"
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 12, 16])
    parser.add_argument("--seconds", type=float, default=20.0, help="mission length (default 20)")
    parser.add_argument("--keep-going", action="store_true", help="past an N that did not hold")
    parser.add_argument("--keep", action="store_true", help="keep each run's folder (logs)")
    arguments = parser.parse_args(argv)
    compile_packages(ROOT)  # as an install does: the processes read bytecode
    held: list[Outcome] = []
    last: Outcome | None = None
    for n in arguments.sizes:
        load = subprocess.run(["uptime"], check=False, capture_output=True, text=True).stdout
        print(f"uptime: {load.strip()}")
        last = run_swarm(n, arguments.seconds, keep=arguments.keep)
        print_outcome(last)
        if last.held:
            held.append(last)
        elif not arguments.keep_going:
            break
    print(
        f"\nlargest N held in real time: {held[-1].n if held else 'none'} "
        f"(sizes tried: {', '.join(str(n) for n in arguments.sizes)})"
    )
    if last is not None:
        project(held[-1] if held else last, [100, 1000])


if __name__ == "__main__":
    main()

"""A swarm across several machines, on one: each vehicle process in its own network namespace,
joined to the root namespace by a veth link, talking to the broker and to its autopilot only
across that link, through the userspace Wi-Fi of :mod:`tests.netem`.

The root namespace stands for the ground machine: mosquitto, the emulated autopilots (``sitl``,
with SIH's ground-truth stream), the range aid (``mission-runner ranges --source sih``) and the
ground station. Namespace ``i`` stands for vehicle ``i``'s companion computer, at ``10.X.i.2``;
the root side of its link is ``10.X.i.1``. One relay process (``python -m tests.netem``) carries:

- MQTT: vehicle ``i`` connects to ``10.X.i.1:<relay port>``, relayed to the broker on loopback;
- MAVLink: the emulator sends every vehicle's telemetry to one host (``ports.remote_host``,
  127.0.0.1), so the relay listens on 127.0.0.1 at vehicle ``i``'s client port and forwards to
  ``10.X.i.2`` at the same port, where the vehicle process listens (``udpin://0.0.0.0:<port>``);
  the vehicle answers the relay's socket, which hands the answers to the emulator.

Needs root (``ip netns``, veth). The namespaces share the host's clock: time synchronisation
between machines is not exercised here (docs/multi-machine.md says what it needs).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mission_runner.bus.broker import BrokerFiles
from mission_runner.bus.topics import Topics
from tests.mosquitto import MosquittoBroker, free_loopback_port, secured_broker
from tests.netem import Impairment
from tests.sitl.helpers import free_port_config, free_truth_stream

ROOT = Path(__file__).resolve().parents[1]


class NetnsUnavailable(RuntimeError):
    """Network namespaces or veth links cannot be made here (the reason is the message)."""


@dataclass(frozen=True)
class Namespace:
    """A network namespace joined to the root one by a veth link."""

    name: str
    host_ip: str  # the root namespace's end of the link
    ip: str  # the namespace's end

    def command(self, *argv: str) -> list[str]:
        """``argv`` run inside the namespace."""
        return ["ip", "netns", "exec", self.name, *argv]


def unavailable() -> str | None:
    """Why namespaces cannot be made here, or None."""
    if os.geteuid() != 0:
        return "needs root: network namespaces and veth links (ip netns)"
    if shutil.which("ip") is None:
        return "iproute2's `ip` is not installed (ip netns)"
    return None


def _ip(*argv: str) -> None:
    done = subprocess.run(["ip", *argv], capture_output=True, text=True, timeout=30, check=False)
    if done.returncode:
        raise NetnsUnavailable(f"`ip {' '.join(argv)}` failed: {done.stderr.strip()}")


@contextlib.contextmanager
def namespaces(count: int) -> Iterator[list[Namespace]]:
    """``count`` namespaces, each with a veth link to the root namespace (10.X.i.1 root side,
    10.X.i.2 inside, X from this process's id) and its loopback up; deleted on exit."""
    tag = f"mr{os.getpid() % 100_000}"
    subnet = f"10.{100 + os.getpid() % 100}"
    made: list[Namespace] = []
    try:
        for i in range(1, count + 1):
            space = Namespace(f"{tag}-v{i}", f"{subnet}.{i}.1", f"{subnet}.{i}.2")
            host_end, inner_end = f"{tag}h{i}", f"{tag}n{i}"
            _ip("netns", "add", space.name)
            made.append(space)
            _ip("link", "add", host_end, "type", "veth", "peer", "name", inner_end)
            _ip("link", "set", inner_end, "netns", space.name)
            _ip("addr", "add", f"{space.host_ip}/24", "dev", host_end)
            _ip("link", "set", host_end, "up")
            _ip("-n", space.name, "addr", "add", f"{space.ip}/24", "dev", inner_end)
            _ip("-n", space.name, "link", "set", inner_end, "up")
            _ip("-n", space.name, "link", "set", "lo", "up")
        yield made
    finally:
        for space in made:  # the veth pair goes with the namespace its inner end is in
            subprocess.run(["ip", "netns", "del", space.name], capture_output=True, check=False)
        for i in range(1, count + 1):
            subprocess.run(["ip", "link", "del", f"{tag}h{i}"], capture_output=True, check=False)


def _start(argv: list[str], log: Path | None = None) -> subprocess.Popen[str]:
    """``argv`` as a child process, no stdin, both output streams into ``log``, or as text lines
    on a pipe without one (for a process that says when it is ready, and little else)."""
    with contextlib.ExitStack() as stack:
        output = stack.enter_context(log.open("w")) if log is not None else subprocess.PIPE
        return subprocess.Popen(
            argv,
            stdin=subprocess.DEVNULL,
            stdout=output,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            text=True,
            cwd=ROOT,
        )


def _read_until(process: subprocess.Popen[str], text: str) -> None:
    """``process``'s output up to a line containing ``text`` (it says it is ready)."""
    assert process.stdout is not None
    seen = []
    for line in process.stdout:
        seen.append(line)
        if text in line:
            return
    raise RuntimeError(f"no {text!r} from {process.args}:\n{''.join(seen[-30:])}")


@dataclass
class Flight:
    """What a mission across namespaces left: each process's exit code and output, the
    relay's counts, the merged ``summary.json``."""

    mission_dir: Path
    codes: dict[str, int] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)

    @property
    def summary(self) -> dict[str, Any]:
        path = self.mission_dir / "summary.json"
        return json.loads(path.read_text()) if path.exists() else {}


def mission_data(base: str, steps: int, **flight: Any) -> dict[str, Any]:
    """``configs/<base>.yaml`` renamed, ``steps`` long, flown in real time (``flight`` added to
    its ``flight:``); its bus is :func:`secured_mission`'s."""
    data: dict[str, Any] = yaml.safe_load((ROOT / "configs" / f"{base}.yaml").read_text())
    data["name"] = f"{data['name']}_netns"
    data["timing"]["steps"] = steps
    data["flight"] = {**data["flight"], "clock": "realtime", **flight}
    return data


@dataclass
class _Layout:
    """Ports and files of one mission."""

    folder: Path
    spaces: list[Namespace]
    relay_port: int = field(default_factory=free_loopback_port)

    def __post_init__(self) -> None:
        self.ports = free_port_config(len(self.spaces), gcs=False)
        self.truth = free_truth_stream(len(self.spaces), self.ports)
        self.mission = self.folder / "mission"

    def scenario(self, data: dict[str, Any], space: Namespace | None = None) -> str:
        """The scenario file of the root namespace, or of the vehicle in ``space`` (its broker
        is the relay at its link's root end)."""
        if space is not None:
            mqtt = {**data["bus"]["mqtt"], "host": space.host_ip, "port": self.relay_port}
            data = {**data, "bus": {**data["bus"], "mqtt": mqtt}}
        path = self.folder / f"scenario{'_' + space.name if space else ''}.yaml"
        path.write_text(yaml.safe_dump(data))
        return str(path)

    def mqtt_routes(self, data: dict[str, Any]) -> list[str]:
        broker = f"{data['bus']['mqtt']['host']}:{data['bus']['mqtt']['port']}"
        return [f"--tcp={space.host_ip}:{self.relay_port}={broker}" for space in self.spaces]

    def mavlink_routes(self) -> list[str]:
        ports = [self.ports.api_remote_port(i) for i in range(len(self.spaces))]
        return [
            f"--udp=127.0.0.1:{port}={space.ip}:{port}"
            for space, port in zip(self.spaces, ports, strict=True)
        ]

    def emulator_file(self, data: dict[str, Any]) -> str:
        """The emulator's settings: each vehicle where the scenario starts it."""
        positions = [
            {"north_m": v["initial_position_m"][0], "east_m": v["initial_position_m"][1]}
            for v in data["vehicles"]
        ]
        path = self.folder / "emulator.yaml"
        path.write_text(yaml.safe_dump({"placement": {"positions": positions}}))
        return str(path)


def _netem_options(impairment: Impairment, seed: int) -> list[str]:
    """``python -m tests.netem``'s options for ``impairment``."""
    low_ms, high_ms = impairment.delay_min_s * 1e3, impairment.delay_max_s * 1e3
    return [
        f"--seed={seed}", "--delay-ms", f"{low_ms:g}", f"{high_ms:g}",
        f"--loss={impairment.loss:g}", f"--rto-ms={impairment.retransmit_s * 1e3:g}",
    ]  # fmt: skip


def _python(*argv: str) -> list[str]:
    return [sys.executable, "-m", *argv]


@contextlib.contextmanager
def _running(flight: Flight, logs: Path) -> Iterator[dict[str, subprocess.Popen[str]]]:
    """The processes the body starts (by name); each stopped at the end (SIGINT: the ones that
    run until told, and write their counts then), killed if it does not stop, its output kept
    (from its pipe, else from ``logs/<name>.log``)."""
    processes: dict[str, subprocess.Popen[str]] = {}
    try:
        yield processes
    finally:
        for name, process in reversed(processes.items()):
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
            try:
                output, _ = process.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                output, _ = process.communicate(timeout=10)
            log = logs / f"{name}.log"
            if output is None and log.exists():
                output = log.read_text(errors="replace")
            flight.codes[name], flight.outputs[name] = process.returncode, output or ""


def secured_mission(folder: Path, data: dict[str, Any]) -> tuple[MosquittoBroker, BrokerFiles]:
    """A broker (not started) with ``broker-config``'s logins, ACL and bus key for ``data``'s
    mission, on a free loopback port; ``data``'s bus points at it."""
    topics = Topics.for_mission(data["name"])
    broker, files = secured_broker(folder, topics, [v["id"] for v in data["vehicles"]])
    data["bus"] = {"kind": "mqtt", "mqtt": {"host": broker.host, "port": broker.port}}
    return broker, files


def machine_credentials(files: BrokerFiles, vehicle_id: int, folder: Path) -> Path:
    """What vehicle ``vehicle_id``'s companion computer gets of ``broker-config``'s credentials:
    its own two logins (``vehicle-<id>`` and ``vehicle-<id>-flight``), no one else's."""
    own = (f"vehicle-{vehicle_id}:", f"vehicle-{vehicle_id}-flight:")
    lines = [line for line in files.credentials.read_text().splitlines() if line.startswith(own)]
    path = folder / f"credentials_vehicle_{vehicle_id}"
    path.touch(mode=0o600)
    path.write_text("\n".join(lines) + "\n")
    return path


def fly(
    folder: Path,
    spaces: list[Namespace],
    files: BrokerFiles,
    data: dict[str, Any],
    impairment: Impairment,
    *,
    mavlink: Impairment | None = None,
    seed: int = 1,
    timeout_s: float = 240.0,
) -> Flight:
    """Fly the mission ``data`` (on the broker :func:`secured_mission` made, ``files`` its
    logins and key) with vehicle ``i`` in ``spaces[i - 1]``, its MQTT connection impaired by
    ``impairment`` and its MAVLink link by ``mavlink`` (default: the same), seeded by ``seed``;
    returns once the ground station has given its verdict and every process has stopped."""
    layout = _Layout(folder, spaces)
    flight = Flight(layout.mission)
    root_scenario = layout.scenario(data)
    ports, truth = layout.ports, layout.truth
    root_auth = ["--bus-key-file", str(files.bus_key), "--bus-credentials", str(files.credentials)]
    logs = folder / "logs"
    logs.mkdir(exist_ok=True)
    with _running(flight, logs) as run:
        run["sitl"] = _start(
            _python("sitl", "--vehicles", str(len(spaces)), "--config", layout.emulator_file(data),
                    "--no-gcs", "--host-unix-time", "--api-port-base", str(ports.api_remote_base),
                    "--api-local-port-base", str(ports.api_local_base), "--truth-stream",
                    "--truth-port-base", str(truth.local_base),
                    "--truth-remote-port-base", str(truth.remote_base))
        )  # fmt: skip
        _read_until(run["sitl"], "udpin://")  # the vehicles are up once it lists their links
        for name, routes, link in (
            ("netem mqtt", layout.mqtt_routes(data), impairment),
            ("netem mavlink", layout.mavlink_routes(), mavlink or impairment),
        ):
            run[name] = _start(_python("tests.netem", *_netem_options(link, seed), *routes))
            _read_until(run[name], "netem: ready")
        run["ranges"] = _start(
            _python("mission_runner.cli", "ranges", root_scenario, "--source", "sih",
                    "--truth-port-base", str(truth.remote_base),
                    "--out", str(layout.mission / "truth"), *root_auth),
            logs / "ranges.log",
        )  # fmt: skip
        for i, space in enumerate(spaces, start=1):
            run[f"vehicle {i}"] = _start(
                space.command(
                    *_python("mission_runner.cli", "vehicle", layout.scenario(data, space),
                             "--id", str(i), "--url",
                             f"udpin://0.0.0.0:{ports.api_remote_port(i - 1)}",
                             "--out", str(layout.mission / f"vehicle_{i}"),
                             "--bus-key-file", str(files.bus_key), "--bus-credentials",
                             str(machine_credentials(files, i, folder)))
                ),
                logs / f"vehicle {i}.log",
            )  # fmt: skip
        ground = run["ground"] = _start(
            _python("mission_runner.cli", "ground", root_scenario, "--out", str(layout.mission),
                    "--no-figures", *root_auth),
            logs / "ground.log",
        )  # fmt: skip
        ground.wait(timeout=timeout_s)
        for i in range(1, len(spaces) + 1):
            run[f"vehicle {i}"].wait(timeout=60)
    return flight

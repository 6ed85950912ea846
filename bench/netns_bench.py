"""The swarm across machines, on one: vehicle processes in their own network namespaces, their
MQTT and MAVLink links through a userspace Wi-Fi (``tests/netem.py``: 10-30 ms each way, 2 %
lost), against the same links without impairment. Needs root (``ip netns``, veth).

    python bench/netns_bench.py                                   # none, mqtt, both; seed 1
    python bench/netns_bench.py --links none both --seeds 1 2 --config configs/wifi_mesh_flight.yaml

For each run: ``sitl`` (with SIH's ground-truth stream) + the range aid + ``ground`` in the root
namespace, one ``vehicle`` process per namespace (``tests/netns.py``); links are ``none`` (relayed,
not impaired), ``mqtt`` (only the bus impaired: companion computer to autopilot stays local, as
on a drone) or ``both`` (the MAVLink link too). Printed per run: the ground's verdict, tail
tracking RMS, final localization and phase spacing errors, steps held or skipped on stale data,
setpoint lateness (p50/p99 over every vehicle-step), neighbours' step messages used per step and
what the relays did (TCP chunks retransmitted, datagrams dropped). Asserts nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import math
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from statistics import quantiles

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import yaml  # noqa: E402

from tests.netem import Impairment  # noqa: E402
from tests.netns import Flight, fly, namespaces, secured_mission, unavailable  # noqa: E402

LINKS = {
    "none": (Impairment.none(), Impairment.none()),
    "mqtt": (Impairment(), Impairment.none()),
    "both": (Impairment(), Impairment()),
}


def _vehicle_rows(flight: Flight, n: int) -> list[dict[str, str]]:
    rows = []
    for i in range(1, n + 1):
        path = flight.mission_dir / f"vehicle_{i}" / "steps.csv"
        if path.exists():
            with path.open() as file:
                rows += [{**row, "vehicle": str(i)} for row in csv.DictReader(file)]
    return rows


def report(name: str, flight: Flight, n: int) -> str:
    """One run's figures, a few lines."""
    metrics = flight.summary.get("metrics", {})
    verdict = flight.summary.get("expectations", {})
    rows = _vehicle_rows(flight, n)
    lateness_ms = [1e3 * float(row["setpoint_lateness_s"]) for row in rows]
    lateness_ms = [late for late in lateness_ms if not math.isnan(late)]  # skipped: none sent
    p50, p99 = (quantiles(lateness_ms, n=100)[i] for i in (49, 98)) if rows else (0.0, 0.0)
    used = [len([p for p in row["neighbours_used"].split() if p != "0"]) for row in rows]
    relays = "; ".join(
        line.removeprefix("netem: ")
        for key in ("netem mqtt", "netem mavlink")
        for line in flight.outputs.get(key, "").splitlines()
        if re.search(r"\d+ (retransmitted|dropped)", line)
    )
    totals = {
        kind: sum(int(m) for m in re.findall(rf"(\d+) {kind}", relays))
        for kind in ("retransmitted", "dropped")
    }
    return (
        f"{name}: exit {flight.codes.get('ground')}, expectations "
        f"{'PASS' if verdict.get('passed') else 'FAIL ' + str(verdict.get('failures'))}\n"
        f"  tail tracking RMS {metrics.get('tail_tracking_error_rms_m', float('nan')):.3f} m, "
        f"final localization {metrics.get('final_localization_error_m', float('nan')):.3f} m, "
        f"final phase spacing {metrics.get('final_phase_spacing_error_rad', float('nan')):.4f} "
        f"rad, steps on stale data {metrics.get('steps_on_stale_data')} of {len(rows)}\n"
        f"  setpoint after t_k p50 {p50:.0f} ms, p99 {p99:.0f} ms; neighbours' step messages "
        f"used per step {sum(used) / max(len(used), 1):.2f} of {n - 1}; relays: "
        f"{totals['retransmitted']} TCP chunks retransmitted, {totals['dropped']} datagrams "
        "dropped"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "wifi_mesh_flight.yaml"))
    parser.add_argument(
        "--links", nargs="+", choices=sorted(LINKS), default=["none", "mqtt", "both"]
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[1])
    parser.add_argument("--steps", type=int, default=None, help="shorten the mission")
    parser.add_argument("--set-flight", action="append", default=[], metavar="KEY=YAML")
    parser.add_argument("--keep", action="store_true", help="keep each run's folder (logs)")
    arguments = parser.parse_args(argv)
    if reason := unavailable():
        sys.exit(f"netns_bench: {reason}")
    for seed in arguments.seeds:
        for links in arguments.links:
            data = yaml.safe_load(Path(arguments.config).read_text())
            if arguments.steps:
                data["timing"]["steps"] = arguments.steps
            for item in arguments.set_flight:
                key, value = item.split("=", 1)
                data["flight"][key] = yaml.safe_load(value)
            load = subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout
            print(f"uptime: {load.strip()}", flush=True)
            with contextlib.ExitStack() as stack:
                folder = Path(tempfile.mkdtemp(prefix="netns-bench-"))
                if not arguments.keep:
                    stack.callback(shutil.rmtree, folder, ignore_errors=True)
                broker, files = secured_mission(folder, data)
                broker.start()
                try:
                    with namespaces(len(data["vehicles"])) as spaces:
                        mqtt, mavlink = LINKS[links]
                        flight = fly(folder, spaces, files, data, mqtt, mavlink=mavlink, seed=seed)
                finally:
                    broker.stop()
                print(report(f"links {links}, seed {seed}", flight, len(data["vehicles"])))
                if arguments.keep:
                    print(f"  kept in {folder}")


if __name__ == "__main__":
    main()

"""Command line: ``sitl --vehicles N`` runs N emulated PX4 vehicles until Ctrl-C/SIGTERM.

Examples::

    sitl --vehicles 4                         # PX4 SITL ports: MAVSDK udpin://0.0.0.0:14540..14543
    sitl --vehicles 10 --speed 5 --tlog-dir runs/tlogs
    sitl --config emulator.yaml --api-port-base 24540   # beside a real PX4 SITL
    sitl --vehicles 4 --sih-like              # clocks, GPS error and ground truth like PX4 SIH
    sitl --signing-passphrase "$PASS" --signing-key-dir keys   # MAVLink 2 signing on from the start

``--config`` takes a YAML file holding :class:`sitl.config.EmulatorConfig` fields, or a scenario
file with an ``emulator:`` section; command line options override it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml
from pydantic import ValidationError

if TYPE_CHECKING:  # imported where used: the options alone (a parser's --help) load no MAVLink
    from sitl.config import EmulatorConfig
    from sitl.emulator import Emulator

logger = logging.getLogger("sitl")

#: ``--sih-like``: what 4 real SIH instances did (measured 2026-12-01); see sitl/README.md.
SIH_LIKE: dict[str, Any] = {
    "clock": {"speed": 0.986, "unix_time": "host"},
    "boot_clock": {"spread_s": 10.0},
    "gps_error": {"bias_std_m": 0.2, "bias_time_constant_s": 30.0, "noise_std_m": 0.02},
    "truth_stream": {"enabled": True},
}
#: Emulator sections that only the PX4-SIH fidelity options touch (clock and ports go apart).
FIDELITY = ("boot_clock", "gps_error", "truth_stream")
SIH_LIKE_SUMMARY = (
    "speed 0.986 with SYSTEM_TIME on the host clock, boot clocks 0-10 s apart, GPS bias 0.2 m "
    "(30 s) + 0.02 m noise, ground-truth stream"
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sitl",
        description="Run N lightweight PX4-like vehicles that MAVSDK, QGroundControl and "
        "MAVProxy talk to as to PX4 SITL.",
    )
    add_emulator_options(parser)
    parser.add_argument("--scenario", type=Path, help=argparse.SUPPRESS)  # moved, see main()
    parser.add_argument(
        "--log-level",
        default="INFO",
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging level (default INFO)",
    )
    return parser


def add_emulator_options(parser: argparse.ArgumentParser) -> None:
    """The emulator's options (vehicles, clock, ports, settings file, PX4-SIH fidelity), for this
    command and for tools that run the emulator for their own purpose; :func:`load_config` reads
    them back."""
    parser.add_argument("--vehicles", "-n", type=int, help="number of vehicles (default 1)")
    parser.add_argument("--speed", type=float, help="simulated seconds per wall second")
    parser.add_argument(
        "--lockstep",
        action="store_true",
        help="lockstep clock: run as fast as possible (no participants from the command line)",
    )
    _add_port_options(parser)
    parser.add_argument("--config", type=Path, help="emulator settings (YAML)")
    parser.add_argument("--tlog-dir", type=Path, help="record vehicle_<sysid>.tlog files here")
    parser.add_argument(
        "--seed", type=int, help="random seed (wind, odometry noise, GPS error, boot offsets)"
    )
    _add_signing_options(parser)
    _add_sih_options(parser)


def _add_port_options(parser: argparse.ArgumentParser) -> None:
    """Where each vehicle's API and GCS links bind and send."""
    parser.add_argument(
        "--api-port-base",
        type=int,
        help="client port of vehicle 0's API link (MAVSDK listens on base+i, skipping the GCS "
        "port; default 14540); the vehicles bind base+40+i (or the ports right after the "
        "client ports for more than 39 vehicles) unless --api-local-port-base is given",
    )
    parser.add_argument(
        "--api-local-port-base", type=int, help="vehicle 0's API bind port (default 14580)"
    )
    parser.add_argument(
        "--gcs-port-base", type=int, help="vehicle 0's GCS-link bind port (default 18570)"
    )
    parser.add_argument(
        "--gcs-remote-port", type=int, help="port the GCS links send to (default 14550)"
    )
    parser.add_argument("--no-gcs", action="store_true", help="do not open the GCS links")
    parser.add_argument(
        "--px4-compat-ports",
        action="store_true",
        help="like PX4 SITL, vehicles with index > 9 all send to api-port-base + 9",
    )


def _add_signing_options(parser: argparse.ArgumentParser) -> None:
    """MAVLink 2 signing from the start: the key and where it is kept."""
    signing = parser.add_argument_group("MAVLink 2 message signing (as PX4)")
    signing.add_argument(
        "--signing-passphrase",
        metavar="PASS",
        help="start every vehicle with signing on, the key being SHA-256 of PASS (MAVProxy: "
        "'signing key PASS'); without it a ground station can still set a key with "
        "SETUP_SIGNING",
    )
    signing.add_argument(
        "--signing-key-dir",
        type=Path,
        metavar="DIR",
        help="keep each vehicle's key and timestamp in DIR/vehicle_<sysid>/"
        "mavlink-signing-key.bin across runs (PX4's format); a vehicle with a key there "
        "starts with signing on",
    )


def _add_sih_options(parser: argparse.ArgumentParser) -> None:
    """The PX4-SIH fidelity group: the preset and the boot clocks, then the rest."""
    sih = parser.add_argument_group("PX4 SIH fidelity")
    sih.add_argument(
        "--sih-like",
        action="store_true",
        help=f"what real PX4 SITL (SIH) does, as one preset: {SIH_LIKE_SUMMARY}; the options "
        "below override parts of it",
    )
    sih.add_argument(
        "--host-unix-time",
        action="store_true",
        help="SYSTEM_TIME's UNIX time follows the host's clock (realtime mode), like PX4 SITL",
    )
    sih.add_argument(
        "--boot-offset-spread",
        type=float,
        metavar="S",
        help="each vehicle's boot clock starts a random 0..S s before simulated time 0",
    )
    sih.add_argument(
        "--boot-offsets",
        type=float,
        nargs="+",
        metavar="S",
        help="boot-clock offset of vehicle 0, 1, ... in s (one per vehicle)",
    )
    _add_truth_options(sih)


def _add_truth_options(sih: argparse._ArgumentGroup) -> None:
    """GPS error, the ground-truth stream and arming denials, in the PX4-SIH group ``sih``."""
    sih.add_argument(
        "--gps-bias-std", type=float, metavar="M", help="GPS/EKF position bias per axis, m"
    )
    sih.add_argument(
        "--gps-bias-time", type=float, metavar="S", help="correlation time of that bias, s"
    )
    sih.add_argument(
        "--gps-noise-std", type=float, metavar="M", help="white noise on reported positions, m"
    )
    sih.add_argument(
        "--truth-stream",
        action="store_true",
        help="send SIH's ground truth (HIL_STATE_QUATERNION) from 19450+i to 19410+i",
    )
    sih.add_argument("--truth-rate", type=float, metavar="HZ", help="ground-truth rate (25)")
    sih.add_argument(
        "--truth-port-base",
        type=int,
        metavar="PORT",
        help="vehicle 0's ground-truth bind port (19450)",
    )
    sih.add_argument(
        "--truth-remote-port-base",
        type=int,
        metavar="PORT",
        help="vehicle 0's ground-truth client port (19410)",
    )
    sih.add_argument(
        "--deny-arming",
        action="append",
        metavar="INDEX[:COUNT]",
        help="refuse vehicle INDEX's first COUNT (default 1) arm attempts like PX4's health "
        "checks do; repeatable",
    )


def load_config(args: argparse.Namespace) -> EmulatorConfig:
    """The configuration from ``--config`` plus command line overrides (ValidationError if bad)."""
    from sitl.config import EmulatorConfig  # noqa: PLC0415 - `sitl --help` without the emulator

    data: dict[str, Any] = {}
    if args.config is not None:
        loaded = yaml.safe_load(args.config.read_text()) or {}
        if not isinstance(loaded, dict):
            raise ValueError(f"{args.config}: expected a mapping at the top level")
        data = loaded.get("emulator", loaded) if "emulator" in loaded else loaded
        data = dict(data)
    if args.sih_like:
        for section, values in SIH_LIKE.items():
            data[section] = {**values, **dict(data.get(section) or {})}
    if args.vehicles is not None:
        data["vehicles"] = args.vehicles
    if args.seed is not None:
        data["seed"] = args.seed
    if args.tlog_dir is not None:
        data["tlog_dir"] = str(args.tlog_dir)
    clock = dict(data.get("clock") or {})
    if args.speed is not None:
        clock["speed"] = args.speed
    if args.lockstep:
        clock["mode"] = "lockstep"
    data["clock"] = clock
    ports = dict(data.get("ports") or {})
    if args.api_port_base is not None:
        ports["api_remote_base"] = args.api_port_base
    if args.api_local_port_base is not None:
        ports["api_local_base"] = args.api_local_port_base
    if args.gcs_port_base is not None:
        ports["gcs_local_base"] = args.gcs_port_base
    if args.gcs_remote_port is not None:
        ports["gcs_remote_port"] = args.gcs_remote_port
    if args.no_gcs:
        ports["gcs_enabled"] = False
    if args.px4_compat_ports:
        ports["px4_compat_ports"] = True
    data["ports"] = ports
    if args.signing_passphrase is not None or args.signing_key_dir is not None:
        signing = dict(data.get("signing") or {})
        if args.signing_passphrase is not None:
            signing.pop("key_hex", None)  # the command line wins over the file's key
            signing["passphrase"] = args.signing_passphrase
        if args.signing_key_dir is not None:
            signing["key_dir"] = str(args.signing_key_dir)
        data["signing"] = signing
    _apply_sih_options(args, data)
    return EmulatorConfig.model_validate(data)


def fidelity_overrides(config: EmulatorConfig, scenario_emulator: dict[str, Any]) -> dict[str, Any]:
    """What the options and ``--config`` set of the PX4-SIH fidelity sections, for a scenario's
    emulator settings: sections left at their defaults keep the scenario's, faults add up."""
    from sitl.config import EmulatorConfig  # noqa: PLC0415 - `sitl --help` without the emulator

    defaults = EmulatorConfig()
    overrides: dict[str, Any] = {
        name: getattr(config, name).model_dump()
        for name in FIDELITY
        if getattr(config, name) != getattr(defaults, name)
    }
    if config.faults:
        overrides["faults"] = [
            *(scenario_emulator.get("faults") or []),
            *(fault.model_dump() for fault in config.faults),
        ]
    return overrides


def _apply_sih_options(args: argparse.Namespace, data: dict[str, Any]) -> None:
    """The PX4-SIH fidelity options, on top of the file and ``--sih-like``."""

    def section(name: str) -> dict[str, Any]:
        part: dict[str, Any] = dict(data.get(name) or {})
        data[name] = part
        return part

    if args.host_unix_time:
        section("clock")["unix_time"] = "host"
    if args.boot_offsets is not None:
        section("boot_clock").update(offset_s=args.boot_offsets, spread_s=0.0)
    if args.boot_offset_spread is not None:
        section("boot_clock").update(spread_s=args.boot_offset_spread, offset_s=[])
    for option, field in (
        ("gps_bias_std", "bias_std_m"),
        ("gps_bias_time", "bias_time_constant_s"),
        ("gps_noise_std", "noise_std_m"),
    ):
        if getattr(args, option) is not None:
            section("gps_error")[field] = getattr(args, option)
    if args.truth_stream:
        section("truth_stream")["enabled"] = True
    for option, field in (
        ("truth_rate", "rate_hz"),
        ("truth_port_base", "local_base"),
        ("truth_remote_port_base", "remote_base"),
    ):
        if getattr(args, option) is not None:
            section("truth_stream")[field] = getattr(args, option)
    for spec in args.deny_arming or []:
        index, _, count = spec.partition(":")
        try:
            fault = {"kind": "deny_arming", "vehicle_index": int(index), "count": int(count or 1)}
        except ValueError:
            raise ValueError(f"--deny-arming {spec!r}: expected INDEX or INDEX:COUNT") from None
        data["faults"] = [*(data.get("faults") or []), fault]


async def until_stopped() -> None:
    """Return on SIGINT or SIGTERM."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    await stop.wait()


def describe(emulator: Emulator, config: EmulatorConfig) -> None:
    """Print the vehicles' endpoints, for the user to connect MAVSDK, QGroundControl or MAVProxy."""
    print(
        f"sitl: {config.vehicles} vehicle(s) ready, clock {config.clock.mode} "
        f"x{config.clock.speed:g}"
    )
    for ep in emulator.endpoints:
        gcs = (
            f", GCS link :{ep.gcs_local_port} -> :{ep.gcs_remote_port}" if ep.gcs_local_port else ""
        )
        truth = (
            f", ground truth :{ep.truth_local_port} -> :{ep.truth_remote_port}"
            if ep.truth_local_port
            else ""
        )
        print(
            f"  sysid {ep.sysid}: MAVSDK {ep.mavsdk_url} (vehicle :{ep.api_local_port}){gcs}{truth}"
        )
    if config.tlog_dir is not None:
        print(f"  recording tlogs in {config.tlog_dir}")
    signed = [ep.sysid for ep in emulator.endpoints if emulator.signing(ep.index).active]
    if signed:
        print(f"  MAVLink signing on for sysid {', '.join(map(str, signed))}")
    if config.signing.key_dir is not None:
        print(f"  signing keys kept in {config.signing.key_dir}")
    sys.stdout.flush()


def describe_stop(emulator: Emulator) -> None:
    stats = emulator.stats()
    print(
        f"sitl: stopped after {stats.sim_time_s:.1f} s simulated in {stats.wall_time_s:.1f} s; "
        f"{stats.rx_packets} packets in, {stats.tx_packets} out"
    )


async def run(config: EmulatorConfig) -> None:
    """Run the emulator until SIGINT or SIGTERM."""
    from sitl.emulator import Emulator  # noqa: PLC0415 - `sitl --help` without the emulator

    async with Emulator(config) as emulator:
        describe(emulator, config)
        await until_stopped()
        print("sitl: stopping")
    describe_stop(emulator)


def main(argv: list[str] | None = None) -> int:
    from sitl.errors import SitlError  # noqa: PLC0415 - `sitl --help` without the emulator

    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if args.scenario is not None:
        print(
            "sitl: --scenario moved to the mission runner (the world around the vehicles is "
            f"mission code): run 'mission-runner emulate {args.scenario}' with the same options",
            file=sys.stderr,
        )
        return 2
    try:
        config = load_config(args)
    except ValidationError as exc:
        print(f"sitl: invalid settings:\n{exc}", file=sys.stderr)
        return 2
    except (OSError, ValueError, yaml.YAMLError) as exc:
        print(f"sitl: cannot read settings: {exc}", file=sys.stderr)
        return 2
    try:
        asyncio.run(run(config))
    except SitlError as exc:
        print(f"sitl: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())

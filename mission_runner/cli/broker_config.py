"""``mission-runner broker-config``."""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import argtypes
from .common import EXIT_OK


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    broker = commands.add_parser(
        "broker-config",
        help="write a mosquitto configuration for the scenario's mission: listener, optional "
        "TLS, one login per role (random passwords, 0600 credentials file), an ACL (each "
        "vehicle publishes only its own topics, only the ground station commands) and a bus key",
    )
    broker.add_argument("config", type=Path, help="scenario YAML file (bus.kind: mqtt)")
    broker.add_argument("--out", type=Path, required=True, help="folder to write the files in")
    broker.add_argument(
        "--port", type=argtypes.port, default=None, help="listener port (default: bus.mqtt.port)"
    )
    broker.add_argument("--bind", default=None, help="listen on this address only")
    broker.add_argument("--tls-cert", type=Path, default=None, help="broker certificate (PEM)")
    broker.add_argument("--tls-key", type=Path, default=None, help="its private key (PEM)")
    broker.add_argument(
        "--tls-ca", type=Path, default=None, help="CA file, for clients with certificates"
    )
    broker.add_argument(
        "--no-bus-key", action="store_true", help="keep the mission's existing bus key"
    )
    broker.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    from ..bus.broker import TlsListener, write_broker_config  # noqa: PLC0415 - fast `--help`
    from ..checks import load_scenario  # noqa: PLC0415 - fast `--help`
    from ..errors import ConfigError  # noqa: PLC0415 - fast `--help`

    scenario = load_scenario(arguments.config)
    source = str(arguments.config)
    if scenario.bus.kind != "mqtt":
        raise ConfigError(source, [("bus.kind", "a broker is for bus.kind: mqtt")])
    if (arguments.tls_cert is None) != (arguments.tls_key is None):
        raise ConfigError("broker-config", [("--tls-cert/--tls-key", "give both or neither")])
    tls = None
    if arguments.tls_cert is not None:
        tls = TlsListener(arguments.tls_cert, arguments.tls_key, arguments.tls_ca)
    files = write_broker_config(
        arguments.out,
        scenario.bus.topics(scenario.name),
        [vehicle.id for vehicle in scenario.vehicles],
        port=arguments.port or scenario.bus.mqtt.port,
        bind_address=arguments.bind,
        tls=tls,
        write_bus_key=not arguments.no_bus_key,
        max_message_bytes=scenario.bus.auth.max_message_bytes,
    )
    print(f"broker-config: users {', '.join(files.users)}")
    print(f"  start the broker:   mosquitto -c {files.config}")
    print(f"  broker logins:      {files.credentials} (0600; each machine needs its own line)")
    if not arguments.no_bus_key:
        print(f"  message key:        {files.bus_key} (0600; every process: --bus-key-file)")
    print(f"  access control:     {files.acl}")
    return EXIT_OK

"""The broker side of a secured bus: mosquitto's configuration for one mission, and the broker
credentials each process logs in with.

``write_broker_config`` (``mission-runner broker-config CONFIG --out DIR``) writes into DIR:

- ``mosquitto.conf``: one listener (optionally TLS, with certificate files the operator gives),
  no anonymous access, the password file and the ACL below, and each connection's client id
  replaced by its login (``use_username_as_clientid``);
- ``passwords``: one user per client of the mission (``ground``, ``vehicle-<id>`` and
  ``vehicle-<id>-flight`` for its controller's connection, ``ranges``, and ``operator`` for
  ``mission-runner control``, ``viewer`` for a live view) with a random password, hashed as
  mosquitto 2 stores them (``$7$``: PBKDF2-SHA512, 101 iterations, 12-byte salt; computed here, so
  no password appears on a command line);
- ``acl``: each vehicle (both its logins) publishes only its own topics, only the ground station
  and its operator publish on ``control``, the range aid only ranges and target observations, the
  viewer nothing; everyone reads the mission;
- ``credentials`` (mode 0600): the users' ``user:password`` lines, for ``--bus-credentials``
  (give each machine only its own line);
- ``bus.key`` (mode 0600): a fresh random message key for ``--bus-key-file`` (every process).

The broker forwards no message longer than the receivers accept (``max_packet_size``,
``message_size_limit``).

mosquitto enforces the ACL per user, whatever the message says: a vehicle's credentials cannot
publish a ``start``, even with the bus key. A denied publish is dropped by the broker silently
(MQTT 3.1.1 has no way to say so at QoS 0).

Client ids are bound to logins: mosquitto drops a connection when another arrives with its client
id, and publishes its last will. With the id replaced by the login, vehicle 1's login can only
ever take vehicle 1's own connection, never vehicle 2's; the price is one connection per login,
hence a login for each client that runs beside the ground station (``operator``, ``viewer``).
"""

from __future__ import annotations

import base64
import hashlib
import os
import secrets
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from mission_runner.bus.auth import Sender
from mission_runner.bus.errors import BusAuthError
from mission_runner.bus.paho_reader import max_packet_bytes
from mission_runner.bus.topics import Topics
from mission_runner.environment import PASSWORD_ENV, USERNAME_ENV

#: mosquitto 2's password hash: PBKDF2-SHA512 with this many iterations (mosquitto_passwd's
#: default) and a 12-byte salt.
MOSQUITTO_ITERATIONS = 101
_SALT_BYTES = 12


def mosquitto_password_hash(
    password: str, *, salt: bytes | None = None, iterations: int = MOSQUITTO_ITERATIONS
) -> str:
    """``password`` as a mosquitto 2 password file stores it: ``$7$<iterations>$<salt>$<hash>``
    (base64), what ``mosquitto_passwd -b`` writes."""
    salt = secrets.token_bytes(_SALT_BYTES) if salt is None else salt
    digest = hashlib.pbkdf2_hmac("sha512", password.encode("utf-8"), salt, iterations)
    encode = base64.b64encode
    return f"$7${iterations}${encode(salt).decode()}${encode(digest).decode()}"


def read_credentials(path: Path) -> dict[str, str]:
    """The ``user:password`` lines of ``path`` (blank lines and ``#`` comments skipped).
    Raises BusAuthError when it cannot be read or a line is not ``user:password``."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise BusAuthError(
            f"cannot read the broker credentials file {path}: {error}",
            hint="give a readable file with --bus-credentials or bus.mqtt.credentials_file",
        ) from None
    users: dict[str, str] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        user, colon, password = line.partition(":")
        if not colon or not user or not password:
            raise BusAuthError(f"{path}:{number}: expected 'user:password'")
        users[user] = password
    return users


#: Logins of clients that run beside the ground station and sign as it (or sign nothing): with
#: client ids bound to logins, each needs its own, or it would take the ground's connection.
OPERATOR_USER = "operator"
VIEWER_USER = "viewer"


def broker_login(
    credentials_file: Path | None,
    sender: Sender,
    environ: Mapping[str, str] | None = None,
    *,
    user: str | None = None,
) -> tuple[str | None, str | None]:
    """``(user, password)`` for ``sender``'s connection: the environment's
    ``MISSION_BUS_USERNAME``/``MISSION_BUS_PASSWORD`` if set, else ``credentials_file``'s line
    for ``user`` (default: the sender's role user, ``str(sender)``) or its only line, else
    ``(None, None)`` (anonymous)."""
    environ = os.environ if environ is None else environ
    if environ.get(USERNAME_ENV):
        return environ[USERNAME_ENV], environ.get(PASSWORD_ENV)
    if credentials_file is None:
        return None, None
    users = read_credentials(credentials_file)
    wanted = user or str(sender)
    if wanted in users:
        return wanted, users[wanted]
    if len(users) == 1:
        ((only, password),) = users.items()
        return only, password
    raise BusAuthError(
        f"the broker credentials file {credentials_file} has no user {wanted!r}",
        hint=f"this client logs in as {wanted}; broker-config writes one user per client "
        "(run it again if the file is older than the operator and viewer logins)",
    )


@dataclass(frozen=True)
class TlsListener:
    """PEM files of the broker's TLS listener (the operator's; nothing is generated)."""

    cert_file: Path
    key_file: Path
    ca_file: Path | None = None


@dataclass(frozen=True)
class BrokerFiles:
    """What :func:`write_broker_config` wrote."""

    config: Path
    passwords: Path
    acl: Path
    credentials: Path
    bus_key: Path
    users: tuple[str, ...]


def flight_user(vehicle_id: int) -> str:
    """The login of a vehicle process's second connection, its controller's (``vehicle-<id>-
    flight``; see ``runner.process.flight_bus``): a broker that binds client ids to logins lets
    one login hold one connection."""
    return f"{Sender.vehicle(vehicle_id)}-flight"


def acl_text(topics: Topics, vehicle_ids: Sequence[int]) -> str:
    """mosquitto ACL of a mission: who may write which topic (everyone reads the mission)."""
    prefix = topics.prefix
    lines = [
        "# mission-runner broker ACL: who may publish what (mosquitto drops anything else).",
        f"# Mission topics under {prefix}/",
        "",
        "user ground",
        f"topic write {topics.control()}",
        f"topic read {topics.everything()}",
        "",
        f"user {OPERATOR_USER}",
        f"topic write {topics.control()}",
        f"topic read {topics.everything()}",
        "",
        f"user {VIEWER_USER}",
        f"topic read {topics.everything()}",
        "",
        "user ranges",
        f"topic write {prefix}/vehicle/+/ranges",
        f"topic write {prefix}/vehicle/+/target",
        f"topic read {topics.everything()}",
    ]
    for vehicle_id in vehicle_ids:
        # The vehicle's two connections (see flight_user): the same rights.
        for user in (str(Sender.vehicle(vehicle_id)), flight_user(vehicle_id)):
            lines += [
                "",
                f"user {user}",
                f"topic write {topics.step(vehicle_id)}",
                f"topic write {topics.status(vehicle_id)}",
                f"topic write {topics.ranges(vehicle_id)}",
                f"topic write {topics.target(vehicle_id)}",
                f"topic read {topics.everything()}",
            ]
    return "\n".join(lines) + "\n"


def size_limits(max_message_bytes: int) -> list[str]:
    """mosquitto.conf lines that forward nothing longer than the receivers accept
    (``bus.auth.max_message_bytes``): a longer packet's sender is disconnected before its
    payload is read, and a longer payload in a shorter packet is dropped. Without them, four
    64 MiB payloads on the control topic stalled the vehicles until they were declared lost;
    even skipped unread by the receivers, each is still forwarded to every subscriber, and the
    broker forwards nothing else meanwhile (bench/flood_bench.py --no-limits)."""
    return [
        f"max_packet_size {max_packet_bytes(max_message_bytes)}",
        f"message_size_limit {max_message_bytes}",
    ]


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` readable by its owner only (also when it existed)."""
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "w", encoding="utf-8") as handle:
        os.fchmod(handle.fileno(), 0o600)
        handle.write(text)


def write_broker_config(
    out_dir: Path,
    topics: Topics,
    vehicle_ids: Sequence[int],
    *,
    port: int = 1883,
    bind_address: str | None = None,
    tls: TlsListener | None = None,
    write_bus_key: bool = True,
    max_message_bytes: int = 16384,
) -> BrokerFiles:
    """Write a mosquitto configuration for the mission (see the module docstring).
    ``max_message_bytes``: the scenario's ``bus.auth.max_message_bytes``; the broker refuses
    anything longer."""
    out_dir.mkdir(parents=True, exist_ok=True)
    out_dir = out_dir.resolve()
    users = (
        "ground",
        OPERATOR_USER,
        VIEWER_USER,
        "ranges",
        *(user for i in vehicle_ids for user in (str(Sender.vehicle(i)), flight_user(i))),
    )
    files = BrokerFiles(
        config=out_dir / "mosquitto.conf",
        passwords=out_dir / "passwords",
        acl=out_dir / "acl",
        credentials=out_dir / "credentials",
        bus_key=out_dir / "bus.key",
        users=users,
    )
    _write_logins(files)
    if write_bus_key:
        _write_private(files.bus_key, secrets.token_hex(32) + "\n")
    files.acl.write_text(acl_text(topics, vehicle_ids), encoding="utf-8")
    lines = _mosquitto_conf_lines(
        files, port=port, bind_address=bind_address, tls=tls, max_message_bytes=max_message_bytes
    )
    files.config.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return files


def _write_logins(files: BrokerFiles) -> None:
    """A fresh password for every user: mosquitto's hashes in ``files.passwords``, the logins
    themselves in ``files.credentials``."""
    users = files.users
    passwords = {user: secrets.token_urlsafe(24) for user in users}
    # The hashes are not secret the way the passwords are, but mosquitto 2 warns about a
    # world-readable password file, and nobody else needs to read it.
    _write_private(
        files.passwords,
        "".join(f"{user}:{mosquitto_password_hash(passwords[user])}\n" for user in users),
    )
    _write_private(
        files.credentials,
        "# broker logins, one per role: give each machine only its own line\n"
        + "".join(f"{user}:{passwords[user]}\n" for user in users),
    )


def _mosquitto_conf_lines(
    files: BrokerFiles,
    *,
    port: int,
    bind_address: str | None,
    tls: TlsListener | None,
    max_message_bytes: int,
) -> list[str]:
    """The lines of ``mosquitto.conf``: one listener (with TLS if given), logins and ACL from
    ``files``, client ids bound to logins, no Nagle delay, the size limits."""
    listener = f"listener {port}" + (f" {bind_address}" if bind_address else "")
    lines = [
        "# mosquitto configuration of a mission-runner mission (mission-runner broker-config).",
        "# Start: mosquitto -c " + str(files.config),
        "per_listener_settings false",
        listener,
    ]
    if tls is not None:
        lines += [f"certfile {tls.cert_file.resolve()}", f"keyfile {tls.key_file.resolve()}"]
        if tls.ca_file is not None:
            lines.append(f"cafile {tls.ca_file.resolve()}")
    lines += [
        "allow_anonymous false",
        f"password_file {files.passwords}",
        f"acl_file {files.acl}",
        # The login is the client id: no login can take over another's connection (and have
        # its last will published).
        "use_username_as_clientid true",
        # Without it Nagle's algorithm holds step messages to subscribers by up to 40 ms.
        "set_tcp_nodelay true",
        *size_limits(max_message_bytes),
    ]
    if os.geteuid() == 0:
        lines += [
            "# Written as root, the logins are root's (0600): started as root, mosquitto would",
            '# switch to the user "mosquitto" and fail to read them. Run as another user: drop it.',
            "user root",
        ]
    return lines

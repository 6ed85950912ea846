"""A private mosquitto broker for tests: own config, own free loopback port, own lifetime.

Any test package can use it::

    from tests.mosquitto import MosquittoBroker, require_mosquitto

    broker = MosquittoBroker(tmp_path / "broker")
    broker.start()          # returns once the port accepts connections
    ...
    broker.kill()           # a crash: SIGKILL, no goodbye to clients
    broker.start()          # same port again
    broker.stop()

Async tests call ``astart``/``astop``/``akill``, which run the blocking parts in a thread.
The broker never touches the system's mosquitto service or port 1883.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import secrets
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import pytest

from mission_runner.bus.auth import BusKey
from mission_runner.bus.broker import BrokerFiles, mosquitto_password_hash, write_broker_config
from mission_runner.bus.topics import Topics

#: The bus key of the tests (MQTT buses refuse to open without one); tests/conftest.py puts it in
#: the environment of every test, so that processes a test starts share it.
TEST_BUS_KEY = "test-bus-key-0123456789abcdef0123456789abcdef"


def bus_test_key() -> BusKey:
    """:data:`TEST_BUS_KEY` as a key, for buses a test builds itself."""
    return BusKey.from_text(TEST_BUS_KEY, "tests")


_CANDIDATES = ("mosquitto", "/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto")


def mosquitto_binary() -> str | None:
    """Path of the mosquitto executable, or None if it is not installed."""
    for candidate in _CANDIDATES:
        found = shutil.which(candidate)
        if found:
            return found
    return None


def mosquitto_passwd_binary() -> str | None:
    """Path of mosquitto_passwd, or None if it is not installed."""
    return shutil.which("mosquitto_passwd") or shutil.which("/usr/bin/mosquitto_passwd")


def require_mosquitto() -> str:
    """The mosquitto path; skips the calling test if mosquitto is not installed."""
    binary = mosquitto_binary()
    if binary is None:
        pytest.skip("mosquitto is not installed (apt-get install mosquitto); broker tests need it")
    return binary


@dataclass(frozen=True)
class TlsFiles:
    """PEM files of a throw-away CA and a server certificate for 127.0.0.1."""

    ca_file: Path
    cert_file: Path
    key_file: Path


def make_test_certificates(directory: Path, *, name: str = "test") -> TlsFiles:
    """A fresh CA and a server certificate for IP 127.0.0.1 it signed (needs openssl)."""
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("openssl is not installed; cannot make test certificates")
    directory.mkdir(parents=True, exist_ok=True)
    ca_key, ca_cert = directory / f"{name}-ca.key", directory / f"{name}-ca.crt"
    key, csr, cert = (directory / f"{name}-server.{ext}" for ext in ("key", "csr", "crt"))
    extensions = directory / f"{name}-server.ext"
    extensions.write_text("subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\n")
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    commands = [
        [openssl, "req", "-x509", *ec, "-keyout", ca_key, "-out", ca_cert, "-days", "2",
         "-subj", f"/CN={name} test CA", "-addext", "basicConstraints=critical,CA:TRUE",
         "-addext", "keyUsage=critical,keyCertSign,cRLSign"],
        [openssl, "req", *ec, "-keyout", key, "-out", csr, "-subj", "/CN=127.0.0.1"],
        [openssl, "x509", "-req", "-in", csr, "-CA", ca_cert, "-CAkey", ca_key,
         "-CAcreateserial", "-out", cert, "-days", "2", "-extfile", extensions],
    ]  # fmt: skip
    for command in commands:
        subprocess.run([str(part) for part in command], check=True, capture_output=True, timeout=30)
    return TlsFiles(ca_file=ca_cert, cert_file=cert, key_file=key)


def free_loopback_port() -> int:
    """A TCP port that was free on 127.0.0.1 a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class MosquittoBroker:
    """One mosquitto process on ``127.0.0.1:<port>`` with a generated minimal config.

    ``users`` (name -> password) turns off anonymous access and writes a password file
    with ``mosquitto_passwd``; ``tls`` makes the listener TLS-only with that server
    certificate. ``config_file`` runs that configuration instead (``broker-config``'s: its
    listener must be ``port`` on 127.0.0.1), with this class's logging. ``port`` stays the
    same across restarts.
    """

    def __init__(
        self,
        directory: Path,
        *,
        port: int | None = None,
        users: dict[str, str] | None = None,
        tls: TlsFiles | None = None,
        config_file: Path | None = None,
        ready_timeout_s: float = 10.0,
    ) -> None:
        self.binary = require_mosquitto()
        self.directory = directory
        self.directory.mkdir(parents=True, exist_ok=True)
        self.port = port if port is not None else free_loopback_port()
        self.host = "127.0.0.1"
        self.ready_timeout_s = ready_timeout_s
        self.config_path = self.directory / "mosquitto.conf"
        self.log_path = self.directory / "mosquitto.log"
        self._process: subprocess.Popen[bytes] | None = None
        self._log: IO[bytes] | None = None
        self._write_config(users, tls, config_file)

    def _write_config(
        self, users: dict[str, str] | None, tls: TlsFiles | None, config_file: Path | None
    ) -> None:
        given = config_file.read_text().splitlines() if config_file is not None else []
        lines = given or [f"listener {self.port} 127.0.0.1"]
        lines += [
            "persistence false",
            # Without it mosquitto lets Nagle's algorithm delay small messages to its
            # subscribers by up to a delayed-ACK period (40 ms on Linux).
            "set_tcp_nodelay true",
            # Flushed line by line (stdout is not, into a file): a test can read who connected.
            f"log_dest file {self.log_path}",
            "log_type error",
            "log_type warning",
            "log_type notice",
        ]
        if os.geteuid() == 0 and "user root" not in lines:
            # Started as root, mosquitto would switch to the "mosquitto" user, who cannot
            # read files in the test's private temporary directory (broker-config's own
            # configuration says so itself).
            lines.append("user root")
        if given:
            pass  # access control is the given configuration's
        elif users:
            passwd = mosquitto_passwd_binary()
            if passwd is None:
                pytest.skip("mosquitto_passwd is not installed; cannot make a password file")
            password_file = self.directory / "passwords"
            password_file.touch(mode=0o600)
            for name, password in users.items():
                subprocess.run(
                    [passwd, "-b", str(password_file), name, password],
                    check=True,
                    capture_output=True,
                    timeout=10,
                )
            lines += ["allow_anonymous false", f"password_file {password_file}"]
        else:
            lines.append("allow_anonymous true")
        if tls is not None:
            lines += [
                f"cafile {tls.ca_file}",
                f"certfile {tls.cert_file}",
                f"keyfile {tls.key_file}",
            ]
        self.config_path.write_text("\n".join(lines) + "\n")

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def log_text(self) -> str:
        """What the broker logged so far."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def start(self) -> None:
        """Start the broker and return once its port accepts TCP connections."""
        if self.running:
            raise RuntimeError(f"mosquitto on port {self.port} is already running")
        self._close_log()
        self._log = self.log_path.open("ab")
        self._process = subprocess.Popen(
            [self.binary, "-c", str(self.config_path)],
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + self.ready_timeout_s
        while True:
            if self._process.poll() is not None:
                code = self._process.returncode
                self._reap()
                raise RuntimeError(
                    f"mosquitto exited with code {code} while starting on port {self.port}:\n"
                    f"{self.log_text()}"
                )
            try:
                with socket.create_connection((self.host, self.port), timeout=0.5):
                    return
            except OSError:
                if time.monotonic() > deadline:
                    self.stop()
                    raise RuntimeError(
                        f"mosquitto did not accept connections on port {self.port} within "
                        f"{self.ready_timeout_s} s:\n{self.log_text()}"
                    ) from None
                time.sleep(0.01)  # polling interval of the readiness probe, not a sync point

    def kill(self) -> None:
        """Crash the broker: SIGKILL, so clients see the connection drop without notice."""
        if self._process is not None and self._process.poll() is None:
            self._process.send_signal(signal.SIGKILL)
        self._reap()

    def stop(self) -> None:
        """Stop the broker (SIGTERM, then SIGKILL after 5 s) and release its files."""
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._process.kill()
        self._reap()

    def _reap(self) -> None:
        if self._process is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._process.wait(timeout=5)
            self._process = None
        self._close_log()

    def _close_log(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None

    async def astart(self) -> None:
        await asyncio.to_thread(self.start)

    async def astop(self) -> None:
        await asyncio.to_thread(self.stop)

    async def akill(self) -> None:
        await asyncio.to_thread(self.kill)


def secured_broker(
    directory: Path, topics: Topics, vehicle_ids: list[int]
) -> tuple[MosquittoBroker, BrokerFiles]:
    """A mosquitto (not yet started) running ``mission-runner broker-config``'s configuration for
    the mission under ``topics`` with ``vehicle_ids``, on a free loopback port, and the files
    written (logins, ACL, bus key)."""
    port = free_loopback_port()
    files = write_broker_config(
        directory / "broker-config", topics, vehicle_ids, port=port, bind_address="127.0.0.1"
    )
    return MosquittoBroker(directory / "broker", port=port, config_file=files.config), files


def add_login(files: BrokerFiles, user: str, acl: list[str]) -> None:
    """Add a login ``user`` (random password, in ``files.credentials``) allowed ``acl`` (mosquitto
    ACL lines) to ``broker-config``'s files before the broker starts: a login beside the mission's
    own, for an intruder that must not share (and so take over) one of theirs."""
    password = secrets.token_urlsafe(24)
    with files.passwords.open("a", encoding="utf-8") as passwords:
        passwords.write(f"{user}:{mosquitto_password_hash(password)}\n")
    with files.credentials.open("a", encoding="utf-8") as credentials:
        credentials.write(f"{user}:{password}\n")
    with files.acl.open("a", encoding="utf-8") as acl_file:
        acl_file.write("\n" + "\n".join([f"user {user}", *acl]) + "\n")

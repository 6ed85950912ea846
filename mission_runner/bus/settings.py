"""Typed settings of the bus, as they appear under ``bus:`` in a scenario file.

Example::

    bus:
      kind: mqtt
      topic_prefix: enclosing/field-test-3
      auth:
        key_file: /etc/mission_runner/bus.key     # the key itself never goes in a scenario
      mqtt:
        host: 192.168.1.10
        port: 8883
        credentials_file: /etc/mission_runner/credentials   # user:password lines (0600)
        tls:
          ca_file: /etc/mission_runner/ca.crt

Everything is validated once, at load; ``open_bus`` turns a valid model into a bus. What a
process brings that a scenario must not hold (the command line's ``--bus-key-file``,
``--bus-credentials`` and ``--insecure-bus``) is attached with ``with_access`` (a
:class:`BusAccess`), never read from the file.
"""

from __future__ import annotations

import ssl
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal, Self

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    SecretStr,
    Strict,
    field_validator,
    model_validator,
)

from mission_runner.bus.auth import AuthPolicy, BusKey, resolve_key
from mission_runner.bus.base import DEFAULT_QUEUE_SIZE
from mission_runner.bus.inprocess import LinkModel
from mission_runner.bus.topics import DEFAULT_PREFIX_ROOT, Topics
from mission_runner.environment import DEFAULT_KEY_ENV

#: As strict as the rest of a scenario: ``"0.01"``, ``true`` or ``1883.0`` where a number or a
#: port is meant are errors, not guesses (``true`` read as a loss probability of 1.0), and so are
#: NaN and infinities.
_STRICT = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)
#: A file name: a string in the YAML (a strict Path would take only Path objects).
FilePath = Annotated[Path, Strict(False)]
#: The longest any wait on the broker may be [s]: the event loop's timers overflow long before
#: 1e300, and an hour is beyond any sensible connect or subscribe timeout.
MAX_TIMEOUT_S = 3600.0
#: The simulated link's longest delay [s]: a minute is beyond any network's.
MAX_LINK_DELAY_S = 60.0


class TlsSettings(BaseModel):
    """TLS towards the broker: whom to trust and, optionally, a client certificate."""

    model_config = _STRICT

    ca_file: FilePath | None = Field(
        None,
        title="CA certificate file",
        description="PEM file of the CA(s) that signed the broker's certificate; "
        "None trusts the system's default CAs.",
    )
    cert_file: FilePath | None = Field(
        None,
        title="Client certificate file",
        description="PEM client certificate, for brokers that authenticate clients by "
        "certificate (mutual TLS). Needs key_file unless the key is in the same file.",
    )
    key_file: FilePath | None = Field(
        None,
        title="Client key file",
        description="PEM private key of cert_file.",
    )
    key_password: SecretStr | None = Field(
        None,
        title="Client key password",
        description="Password of an encrypted key_file.",
    )
    check_hostname: bool = Field(
        True,
        title="Check the broker's host name",
        description="Verify that the broker certificate names the host connected to. "
        "Turn off only on a closed test network.",
    )

    @model_validator(mode="after")
    def _key_needs_cert(self) -> Self:
        if self.key_file is not None and self.cert_file is None:
            raise ValueError("key_file is set but cert_file is not; give both or neither")
        return self

    def ssl_context(self) -> ssl.SSLContext:
        """A client SSL context from these settings. Reads files: call it off the loop.

        Raises OSError if a file is missing and ssl.SSLError if one is not valid PEM.
        """
        context = ssl.create_default_context(
            ssl.Purpose.SERVER_AUTH, cafile=str(self.ca_file) if self.ca_file else None
        )
        context.check_hostname = self.check_hostname
        if self.cert_file is not None:
            context.load_cert_chain(
                str(self.cert_file),
                str(self.key_file) if self.key_file else None,
                self.key_password.get_secret_value() if self.key_password else None,
            )
        return context


class MqttSettings(BaseModel):
    """Where the MQTT broker is, how to log in, and how to ride out broker outages."""

    model_config = _STRICT

    host: str = Field(
        "127.0.0.1",
        min_length=1,
        title="Broker host",
        description="Host name or IP address of the MQTT broker.",
    )
    port: int = Field(
        1883,
        ge=1,
        le=65535,
        title="Broker port",
        description="TCP port of the broker: usually 1883, or 8883 with TLS.",
    )
    client_id: str | None = Field(
        None,
        min_length=1,
        max_length=128,
        title="MQTT client identifier",
        description="Must be unique per connection: a second client with the same id makes "
        "the broker drop the first. None generates one; the runner passes one per vehicle.",
    )
    credentials_file: FilePath | None = Field(
        None,
        title="Broker credentials file",
        description="File of 'user:password' lines (as `mission-runner broker-config` writes, "
        "mode 0600): each process logs in as its role's user (ground, vehicle-<id>, ranges), "
        "or as the file's only user. --bus-credentials overrides it; so do the environment "
        "variables MISSION_BUS_USERNAME and MISSION_BUS_PASSWORD. None: anonymous. Passwords "
        "never go in a scenario file.",
    )
    tls: TlsSettings | None = Field(
        None, title="TLS", description="TLS settings; None connects in plain TCP."
    )
    qos: Literal[0, 1, 2] = Field(
        0,
        title="Quality of service",
        description="MQTT QoS of publishes and subscriptions. 0 suits step messages: a "
        "message superseded by the next step is not worth retransmitting.",
    )
    keepalive_s: int = Field(
        5,
        ge=1,
        le=65535,
        title="Keep-alive interval (s)",
        description="The client pings the broker this often when idle; a silent broker is "
        "declared lost after about 1.5 times this.",
    )
    connect_timeout_s: float = Field(
        5.0,
        gt=0.0,
        le=MAX_TIMEOUT_S,
        title="Connect timeout (s)",
        description="Bound on one connection attempt, and on the wait for the first "
        "connection when the bus opens.",
    )
    subscribe_timeout_s: float = Field(
        5.0,
        gt=0.0,
        le=MAX_TIMEOUT_S,
        title="Subscribe timeout (s)",
        description="Bound on the wait for the broker to acknowledge a subscription.",
    )
    reconnect_initial_s: float = Field(
        0.1,
        gt=0.0,
        le=MAX_TIMEOUT_S,
        title="First reconnect delay (s)",
        description="Delay before the first reconnection attempt after losing the broker; "
        "doubles on each failed attempt, with random jitter.",
    )
    reconnect_max_s: float = Field(
        5.0,
        gt=0.0,
        le=MAX_TIMEOUT_S,
        title="Longest reconnect delay (s)",
        description="Cap of the reconnect delay; must be >= reconnect_initial_s.",
    )

    @model_validator(mode="after")
    def _consistent(self) -> Self:
        if self.reconnect_max_s < self.reconnect_initial_s:
            raise ValueError(
                f"reconnect_max_s ({self.reconnect_max_s}) must be >= "
                f"reconnect_initial_s ({self.reconnect_initial_s})"
            )
        return self


class LinkSettings(BaseModel):
    """A simulated bad network for the in-process bus (see ``LinkModel``)."""

    model_config = _STRICT

    latency_s: float = Field(
        0.0,
        ge=0.0,
        le=MAX_LINK_DELAY_S,
        title="Latency (s)",
        description="Fixed delay of every delivery.",
    )
    jitter_s: float = Field(
        0.0,
        ge=0.0,
        le=MAX_LINK_DELAY_S,
        title="Jitter (s)",
        description="Extra delay of each delivery, uniform in [0, jitter_s].",
    )
    loss_probability: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        title="Loss probability",
        description="Probability that a delivery to one subscriber is dropped.",
    )
    seed: int = Field(
        0, ge=0, title="Random seed", description="Seed of the loss and jitter draws."
    )
    reorder: bool = Field(
        False,
        title="Allow reordering",
        description="Let jitter reorder messages; off keeps each subscriber's order.",
    )

    def link_model(self) -> LinkModel:
        """The ``LinkModel`` these settings describe."""
        return LinkModel(
            latency_s=self.latency_s,
            jitter_s=self.jitter_s,
            loss_probability=self.loss_probability,
            seed=self.seed,
            reorder=self.reorder,
        )


class AuthSettings(BaseModel):
    """How messages are authenticated (see :mod:`mission_runner.bus.auth`). The key itself is
    never in a scenario: a file named here or on the command line, or an environment variable."""

    model_config = _STRICT

    key_file: FilePath | None = Field(
        None,
        title="Bus key file",
        description="File holding the mission's HMAC key (at least 32 characters, e.g. "
        "`openssl rand -hex 32`), the same on every process of the mission. --bus-key-file "
        "and the environment variable key_env take precedence.",
    )
    key_env: str = Field(
        DEFAULT_KEY_ENV,
        min_length=1,
        title="Bus key environment variable",
        description="Environment variable holding the key (used before key_file).",
    )
    time_window_s: float = Field(
        10.0,
        gt=0.0,
        le=3600.0,
        title="Freshness window (s)",
        description="A message sent longer ago than this, or this far ahead of the receiver's "
        "clock, is dropped as stale: the bound on clock skew between machines.",
    )
    retained_max_age_s: float = Field(
        600.0,
        gt=0.0,
        le=86400.0,
        title="Oldest retained message (s)",
        description="Retained messages (the ground's prepare, statuses) handed over by the "
        "broker are accepted this long after they were sent.",
    )
    max_message_bytes: int = Field(
        16384,
        ge=1024,
        le=1 << 24,
        title="Largest message (bytes)",
        description="Payloads larger than this are dropped unread.",
    )

    def policy(self) -> AuthPolicy:
        return AuthPolicy(self.time_window_s, self.retained_max_age_s, self.max_message_bytes)


@dataclass(frozen=True)
class BusAccess:
    """What a process brings to the bus from its command line, never from the scenario file:
    a key file (``--bus-key-file``), broker credentials (``--bus-credentials``) and the
    choice to run an MQTT bus without a key (``--insecure-bus``)."""

    key_file: Path | None = None
    credentials_file: Path | None = None
    insecure: bool = False


class BusSettings(BaseModel):
    """Which bus the vehicles talk over, and its settings."""

    model_config = _STRICT

    kind: Literal["inprocess", "mqtt"] = Field(
        "inprocess",
        title="Bus kind",
        description="'inprocess' runs every vehicle in one process with no broker; 'mqtt' "
        "talks through an MQTT broker (one process or machine per vehicle).",
    )
    topic_prefix: str | None = Field(
        None,
        min_length=1,
        title="Topic prefix",
        description=f"Prefix of every topic of the mission; None means "
        f"'{DEFAULT_PREFIX_ROOT}/<mission_id>'.",
    )
    queue_size: int = Field(
        DEFAULT_QUEUE_SIZE,
        ge=1,
        le=1_000_000,
        title="Subscription queue size",
        description="Messages a subscription buffers before dropping the oldest.",
    )
    mqtt: MqttSettings = Field(
        default_factory=MqttSettings,
        title="MQTT",
        description="Broker settings; used when kind is 'mqtt'.",
    )
    link: LinkSettings | None = Field(
        None,
        title="Simulated link",
        description="Latency, jitter and loss of the in-process bus; None is a perfect "
        "network. Used when kind is 'inprocess'.",
    )
    auth: AuthSettings = Field(
        default_factory=AuthSettings,
        title="Authentication",
        description="Where the message key is and how strict receivers are.",
    )
    _access: BusAccess = PrivateAttr(default_factory=BusAccess)
    _key: BusKey | None = PrivateAttr(None)

    @field_validator("topic_prefix")
    @classmethod
    def _prefix_is_valid(cls, prefix: str | None) -> str | None:
        if prefix is not None:
            Topics(prefix)  # TopicError is a ValueError: pydantic reports it at the field
        return prefix

    @property
    def access(self) -> BusAccess:
        """What the command line added (see :meth:`with_access`)."""
        return self._access

    def with_access(self, access: BusAccess, *, environ: Mapping[str, str] | None = None) -> Self:
        """These settings with ``access`` attached and the key resolved now (so a missing or
        unreadable key is reported before anything connects). Raises BusAuthError."""
        copy = self.model_copy()
        copy._access = access
        copy._key = None
        copy._key = copy.bus_key(environ=environ)
        return copy

    def bus_key(self, *, environ: Mapping[str, str] | None = None) -> BusKey:
        """The key this process signs and checks with (see ``auth.resolve_key``): resolved once
        by :meth:`with_access`, else now. Raises BusAuthError."""
        if self._key is not None:
            return self._key
        return resolve_key(
            kind=self.kind,
            key_file=self.auth.key_file,
            cli_key_file=self._access.key_file,
            key_env=self.auth.key_env,
            insecure=self._access.insecure,
            environ=environ,
        )

    def topics(self, mission_id: str) -> Topics:
        """The mission's topics: under ``topic_prefix``, or ``enclosing/<mission_id>``."""
        if self.topic_prefix is not None:
            return Topics(self.topic_prefix)
        return Topics.for_mission(mission_id)

"""Typed settings of the bus, as they appear under ``bus:`` in a scenario file.

Example::

    bus:
      kind: mqtt
      topic_prefix: enclosing/field-test-3
      mqtt:
        host: 192.168.1.10
        port: 8883
        username: vehicle
        password: change-me
        tls:
          ca_file: /etc/mission_runner/ca.crt

Everything is validated once, at load; ``open_bus`` turns a valid model into a bus.
"""

from __future__ import annotations

import ssl
from pathlib import Path
from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator

from mission_runner.bus.base import DEFAULT_QUEUE_SIZE
from mission_runner.bus.inprocess import LinkModel
from mission_runner.bus.topics import DEFAULT_PREFIX_ROOT, Topics


class TlsSettings(BaseModel):
    """TLS towards the broker: whom to trust and, optionally, a client certificate."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    ca_file: Path | None = Field(
        None,
        title="CA certificate file",
        description="PEM file of the CA(s) that signed the broker's certificate; "
        "None trusts the system's default CAs.",
    )
    cert_file: Path | None = Field(
        None,
        title="Client certificate file",
        description="PEM client certificate, for brokers that authenticate clients by "
        "certificate (mutual TLS). Needs key_file unless the key is in the same file.",
    )
    key_file: Path | None = Field(
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

    model_config = ConfigDict(extra="forbid", frozen=True)

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
    username: str | None = Field(
        None, min_length=1, title="User name", description="User name for the broker, if any."
    )
    password: SecretStr | None = Field(
        None, title="Password", description="Password for username; needs username."
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
        title="Connect timeout (s)",
        description="Bound on one connection attempt, and on the wait for the first "
        "connection when the bus opens.",
    )
    subscribe_timeout_s: float = Field(
        5.0,
        gt=0.0,
        title="Subscribe timeout (s)",
        description="Bound on the wait for the broker to acknowledge a subscription.",
    )
    reconnect_initial_s: float = Field(
        0.1,
        gt=0.0,
        title="First reconnect delay (s)",
        description="Delay before the first reconnection attempt after losing the broker; "
        "doubles on each failed attempt, with random jitter.",
    )
    reconnect_max_s: float = Field(
        5.0,
        gt=0.0,
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
        if self.password is not None and self.username is None:
            raise ValueError("password is set but username is not")
        return self


class LinkSettings(BaseModel):
    """A simulated bad network for the in-process bus (see ``LinkModel``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    latency_s: float = Field(
        0.0, ge=0.0, title="Latency (s)", description="Fixed delay of every delivery."
    )
    jitter_s: float = Field(
        0.0,
        ge=0.0,
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
    seed: int = Field(0, title="Random seed", description="Seed of the loss and jitter draws.")
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


class BusSettings(BaseModel):
    """Which bus the vehicles talk over, and its settings."""

    model_config = ConfigDict(extra="forbid", frozen=True)

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

    @field_validator("topic_prefix")
    @classmethod
    def _prefix_is_valid(cls, prefix: str | None) -> str | None:
        if prefix is not None:
            Topics(prefix)  # TopicError is a ValueError: pydantic reports it at the field
        return prefix

    def topics(self, mission_id: str) -> Topics:
        """The mission's topics: under ``topic_prefix``, or ``enclosing/<mission_id>``."""
        if self.topic_prefix is not None:
            return Topics(self.topic_prefix)
        return Topics.for_mission(mission_id)

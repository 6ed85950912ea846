"""Bus settings, the open_bus factory and the reconnect backoff (no broker needed)."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel, ValidationError

from mission_runner.bus import (
    AuthSettings,
    Backoff,
    BusAuthError,
    BusSettings,
    InProcessBus,
    LinkModel,
    LinkSettings,
    MqttBus,
    MqttSettings,
    Sender,
    TlsSettings,
    open_bus,
)

MODELS: list[type[BaseModel]] = [
    BusSettings,
    MqttSettings,
    TlsSettings,
    LinkSettings,
    AuthSettings,
]


@pytest.mark.parametrize("model", MODELS, ids=lambda model: model.__name__)
def test_every_field_has_a_title_and_a_description(model: type[BaseModel]) -> None:
    for name, field in model.model_fields.items():
        assert field.title, f"{model.__name__}.{name} has no title"
        assert field.description, f"{model.__name__}.{name} has no description"


def test_defaults_are_an_in_process_bus_under_the_mission_prefix() -> None:
    settings = BusSettings()
    assert settings.kind == "inprocess"
    assert settings.topics("demo").prefix == "enclosing/demo"
    assert isinstance(open_bus(settings, sender=None), InProcessBus)


def test_a_scenario_yaml_section_validates() -> None:
    section = yaml.safe_load(
        """
        kind: mqtt
        topic_prefix: field/test-3
        mqtt:
          host: 192.168.1.10
          port: 8883
          credentials_file: /etc/mission_runner/credentials
          qos: 1
          tls:
            ca_file: /etc/mission_runner/ca.crt
        """
    )
    settings = BusSettings.model_validate(section)
    assert settings.topics("ignored").prefix == "field/test-3"
    assert settings.mqtt.tls is not None
    assert str(settings.mqtt.tls.ca_file) == "/etc/mission_runner/ca.crt"
    assert str(settings.mqtt.credentials_file) == "/etc/mission_runner/credentials"


def test_passwords_and_keys_are_not_scenario_settings() -> None:
    sections = [{"mqtt": {"password": "x"}}, {"mqtt": {"username": "x"}}, {"auth": {"key": "x"}}]
    for section in sections:
        with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
            BusSettings.model_validate(section)


@pytest.mark.parametrize(
    ("section", "location"),
    [
        ({"kind": "zeromq"}, ("kind",)),
        ({"mqtt": {"port": 0}}, ("mqtt", "port")),
        ({"mqtt": {"hots": "x"}}, ("mqtt", "hots")),
        ({"mqtt": {"qos": 3}}, ("mqtt", "qos")),
        ({"mqtt": {"reconnect_initial_s": 2.0, "reconnect_max_s": 1.0}}, ("mqtt",)),
        ({"auth": {"time_window_s": 0}}, ("auth", "time_window_s")),
        ({"auth": {"max_message_bytes": 10}}, ("auth", "max_message_bytes")),
        ({"mqtt": {"tls": {"key_file": "k.pem"}}}, ("mqtt", "tls")),
        ({"topic_prefix": "a/+/b"}, ("topic_prefix",)),
        ({"link": {"loss_probability": 1.5}}, ("link", "loss_probability")),
        ({"queue_size": 0}, ("queue_size",)),
        ({"unknown": 1}, ("unknown",)),
    ],
)
def test_invalid_settings_name_the_offending_path(
    section: dict[str, object], location: tuple[str, ...]
) -> None:
    with pytest.raises(ValidationError) as raised:
        BusSettings.model_validate(section)
    assert raised.value.errors()[0]["loc"] == location


@pytest.mark.parametrize(
    ("section", "location", "rule"),
    [
        # Once read as numbers and booleans: true became a loss probability of 1.0.
        ({"link": {"loss_probability": "0.01"}}, ("link", "loss_probability"), "valid number"),
        ({"link": {"loss_probability": True}}, ("link", "loss_probability"), "valid number"),
        ({"link": {"reorder": "yes"}}, ("link", "reorder"), "valid boolean"),
        ({"link": {"seed": "3"}}, ("link", "seed"), "valid integer"),
        ({"mqtt": {"port": "1883"}}, ("mqtt", "port"), "valid integer"),
        ({"mqtt": {"port": 1883.0}}, ("mqtt", "port"), "valid integer"),
        ({"mqtt": {"tls": {"check_hostname": "no"}}}, ("mqtt", "tls", "check_hostname"), "boolean"),
        ({"queue_size": "100"}, ("queue_size",), "valid integer"),
        ({"auth": {"time_window_s": "10"}}, ("auth", "time_window_s"), "valid number"),
        # Bounded, with the bound in the message.
        ({"mqtt": {"connect_timeout_s": 1e300}}, ("mqtt", "connect_timeout_s"), "3600"),
        ({"mqtt": {"reconnect_max_s": 1e300}}, ("mqtt", "reconnect_max_s"), "3600"),
        ({"link": {"latency_s": 1e300}}, ("link", "latency_s"), "60"),
        ({"link": {"jitter_s": 1e9}}, ("link", "jitter_s"), "60"),
        ({"link": {"seed": -1}}, ("link", "seed"), "greater than or equal to 0"),
        ({"link": {"latency_s": float("nan")}}, ("link", "latency_s"), "finite number"),
    ],
)
def test_bus_settings_are_as_strict_and_bounded_as_the_rest_of_a_scenario(
    section: dict[str, object], location: tuple[str, ...], rule: str
) -> None:
    with pytest.raises(ValidationError) as raised:
        BusSettings.model_validate(section)
    [error] = raised.value.errors()
    assert error["loc"] == location and rule in error["msg"], error


def test_file_names_stay_strings_in_the_yaml_while_numbers_must_be_numbers() -> None:
    section: dict[str, dict[str, object]] = {
        "auth": {"key_file": "bus.key"},
        "mqtt": {"tls": {"ca_file": "ca.crt"}},
    }
    with pytest.raises(ValidationError, match="valid integer"):
        BusSettings.model_validate({**section, "mqtt": {"port": "1883"}})
    settings = BusSettings.model_validate(section)
    assert settings.auth.key_file == Path("bus.key")
    assert settings.mqtt.tls is not None and settings.mqtt.tls.ca_file == Path("ca.crt")
    assert BusSettings.model_validate(settings.model_dump(mode="json")) == settings


def test_open_bus_passes_mqtt_settings_through(tmp_path: Path) -> None:
    credentials = tmp_path / "credentials"
    credentials.write_text("ground:g-pass\nvehicle-4:v4-pass\n")
    settings = BusSettings(
        kind="mqtt",
        queue_size=32,
        mqtt=MqttSettings(
            host="broker.local",
            port=1884,
            client_id="from-config",
            credentials_file=credentials,
            qos=1,
            keepalive_s=7,
        ),
    )
    bus = open_bus(settings, sender=Sender.ground())
    assert isinstance(bus, MqttBus)
    assert bus.client_id.startswith("from-config-")  # and a random suffix
    assert (bus.endpoint, bus.client_id[:11], bus.qos, bus.keepalive_s, bus.queue_size) == (
        "broker.local:1884",
        "from-config",
        1,
        7,
        32,
    )
    assert (bus._username, bus._password) == ("ground", "g-pass")
    vehicle = open_bus(settings, sender=Sender.vehicle(4), client_id="vehicle-4")
    assert isinstance(vehicle, MqttBus)
    assert (vehicle.client_id[:10], vehicle._username, vehicle._password) == (
        "vehicle-4-",
        "vehicle-4",
        "v4-pass",
    )
    with pytest.raises(BusAuthError, match="no user 'vehicle-2'"):
        open_bus(settings, sender=Sender.vehicle(2))


def test_generated_client_ids_differ() -> None:
    settings = BusSettings(kind="mqtt")
    first, second = open_bus(settings, sender=None), open_bus(settings, sender=None)
    assert isinstance(first, MqttBus) and isinstance(second, MqttBus)
    assert first.client_id != second.client_id


def test_open_bus_builds_the_link_model_for_the_in_process_bus() -> None:
    settings = BusSettings(link=LinkSettings(latency_s=0.05, loss_probability=0.1, seed=4))
    bus = open_bus(settings, sender=None)
    assert isinstance(bus, InProcessBus)
    assert bus.link == LinkModel(latency_s=0.05, loss_probability=0.1, seed=4)


class TestBackoff:
    def test_doubles_up_to_the_cap_with_jitter_in_the_upper_half(self) -> None:
        backoff = Backoff(0.1, 1.0, random.Random(1))
        ceilings = [0.1, 0.2, 0.4, 0.8, 1.0, 1.0, 1.0]
        for ceiling in ceilings:
            delay = backoff.next_delay_s()
            assert 0.5 * ceiling <= delay <= ceiling
        assert backoff.attempts == len(ceilings)

    def test_reset_starts_over(self) -> None:
        backoff = Backoff(0.1, 10.0, random.Random(1))
        for _ in range(5):
            backoff.next_delay_s()
        backoff.reset()
        assert backoff.next_delay_s() <= 0.1

    def test_jitter_spreads_vehicles_that_lost_the_broker_together(self) -> None:
        delays = {Backoff(1.0, 1.0, random.Random(seed)).next_delay_s() for seed in range(8)}
        assert len(delays) == 8

    def test_many_attempts_do_not_overflow(self) -> None:
        backoff = Backoff(0.1, 5.0, random.Random(1))
        for _ in range(10_000):
            assert backoff.next_delay_s() <= 5.0

    @pytest.mark.parametrize(("initial_s", "max_s"), [(0.0, 1.0), (2.0, 1.0), (-1.0, 1.0)])
    def test_bounds_are_checked(self, initial_s: float, max_s: float) -> None:
        with pytest.raises(ValueError, match="initial_s"):
            Backoff(initial_s, max_s, random.Random())

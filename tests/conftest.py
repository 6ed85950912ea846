"""Shared test settings: property-based tests are derandomized to check the same cases each run;
every test (and every process it starts) has the same bus key, as a mission's processes do."""

from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import settings

from mission_runner.environment import DEFAULT_KEY_ENV
from tests.mosquitto import TEST_BUS_KEY, MosquittoBroker

settings.register_profile("deterministic", derandomize=True, deadline=None, max_examples=60)
settings.load_profile("deterministic")


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[MosquittoBroker]:
    """A running anonymous mosquitto on a free loopback port, stopped after the test."""
    broker = MosquittoBroker(tmp_path / "mosquitto")
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()


@pytest.fixture(autouse=True)
def bus_key(monkeypatch: pytest.MonkeyPatch) -> str:
    """The key every bus of the test signs with, in the environment (``MISSION_BUS_KEY``), so
    that vehicle processes a test starts share it. A test of a missing key deletes it."""
    monkeypatch.setenv(DEFAULT_KEY_ENV, TEST_BUS_KEY)
    return TEST_BUS_KEY

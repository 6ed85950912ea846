from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.mosquitto import MosquittoBroker


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[MosquittoBroker]:
    """This test's own mosquitto on a free loopback port (restarts touch only it)."""
    broker = MosquittoBroker(tmp_path / "mosquitto")
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()

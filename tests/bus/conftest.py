"""Fixtures of the bus tests: a private mosquitto broker per test."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.mosquitto import MosquittoBroker


@pytest.fixture
def mosquitto_with_users(tmp_path: Path) -> Iterator[MosquittoBroker]:
    """A running mosquitto that only lets in user ``vehicle`` with password ``s3cret``."""
    broker = MosquittoBroker(tmp_path / "mosquitto-auth", users={"vehicle": "s3cret"})
    broker.start()
    try:
        yield broker
    finally:
        broker.stop()

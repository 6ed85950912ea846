"""The swarm across several machines, on one: every vehicle process in its own network namespace,
reaching the broker and its autopilot only over a veth link through a userspace Wi-Fi mesh
(``tests/netem.py``: 10-30 ms each way, 2 % lost; TCP losses as a 200 ms retransmission) - the
processes as ``tests/netns.py`` starts them, with ``broker-config``'s logins (each vehicle only
its own) and key. The mission must meet its scenario's ``expect:``."""

import re

import pytest
import yaml

from tests.netem import Impairment
from tests.netns import NetnsUnavailable, fly, namespaces, secured_mission, unavailable

from .flying import CONFIGS

pytestmark = [pytest.mark.mavsdk, pytest.mark.mqtt, pytest.mark.slow]


@pytest.fixture
def spaces():
    """Four namespaces joined to this one by veth links; skipped where they cannot be made."""
    if reason := unavailable():
        pytest.skip(reason)
    try:
        with namespaces(4) as made:
            yield made
    except NetnsUnavailable as error:
        pytest.skip(f"no network namespaces here: {error}")


def _counts(relay_output, kind):
    """Per route, what a relay (``python -m tests.netem``) counted on exit: ``kind`` is
    ``retransmitted`` or ``dropped``; ``{listen address: (chunks, kind)}``."""
    found = re.findall(rf"netem: \w+ (\S+)=\S+: (\d+) chunks, \d+ B, (\d+) {kind}", relay_output)
    return {route: (int(chunks), int(lost)) for route, chunks, lost in found}


@pytest.mark.timeout(360)
def test_the_mission_meets_its_expectations_with_each_vehicle_across_a_lossy_wifi_link(
    tmp_path, spaces
):
    data = yaml.safe_load((CONFIGS / "wifi_mesh_flight.yaml").read_text())
    broker, files = secured_mission(tmp_path, data)
    broker.start()
    try:
        flight = fly(tmp_path, spaces, files, data, Impairment(), seed=1)
    finally:
        broker.stop()

    ground = flight.outputs["ground"]
    assert re.search(r"mission \w+ over; 4 vehicle\(s\) done, lost: none", ground), ground
    assert "expectations: PASS (5 checked)" in ground, ground
    assert flight.codes["ground"] == 0, ground
    assert flight.summary["expectations"]["passed"]
    for i, space in enumerate(spaces, start=1):
        output = flight.outputs[f"vehicle {i}"]
        assert flight.codes[f"vehicle {i}"] == 0, output
        # Its broker was the relay at its own link's far end, reached from its namespace.
        assert f"connected to MQTT broker {space.host_ip}:" in output, output
    # Every link carried the mission, and lost some of it.
    mqtt = _counts(flight.outputs["netem mqtt"], "retransmitted")
    mavlink = _counts(flight.outputs["netem mavlink"], "dropped")
    assert len(mqtt) == len(mavlink) == 4, flight.outputs
    assert all(chunks > 1000 and lost > 0 for chunks, lost in [*mqtt.values(), *mavlink.values()])

"""One vehicle link, without sockets: what a decoder or handler failure costs."""

from __future__ import annotations

import logging

import pytest
from pymavlink.dialects.v20 import common as mavlink

from sitl.config import StreamRates
from sitl.link import VehicleLink

CLIENT = ("127.0.0.1", 14540)


def heartbeat_datagram() -> bytes:
    encoder = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    message = encoder.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    return bytes(message.pack(encoder))


def make_link(deliver: object) -> VehicleLink:
    return VehicleLink(
        "api",
        sysid=1,
        local_port=14580,
        remote_address=CLIENT,
        rates=StreamRates(),
        deliver=deliver,  # type: ignore[arg-type]
    )


def test_a_decoder_failure_costs_that_datagram_only(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    delivered: list[str] = []
    link = make_link(lambda msg, _link: delivered.append(msg.get_type()))
    parser = link._parser
    parse_buffer = parser.parse_buffer

    def failing_once(data: bytes) -> list[mavlink.MAVLink_message] | None:
        monkeypatch.setattr(parser, "parse_buffer", parse_buffer)
        parse_buffer(data[:5])  # leaves a partial packet in the parser, as a failure might
        raise IndexError("decoder bug")

    monkeypatch.setattr(parser, "parse_buffer", failing_once)
    with caplog.at_level(logging.WARNING, logger="sitl.link"):
        link.datagram_received(heartbeat_datagram(), CLIENT)
    assert (link.rx_bad, link.decoder_errors, delivered) == (1, 1, [])
    assert "decoder failed on a" in caplog.text and "127.0.0.1:14540" in caplog.text

    link.datagram_received(heartbeat_datagram(), CLIENT)  # the next one decodes cleanly
    assert (link.rx_bad, link.rx_packets, delivered) == (1, 1, ["HEARTBEAT"])


def test_a_handler_failure_costs_that_message_only(caplog: pytest.LogCaptureFixture) -> None:
    delivered: list[int] = []

    def deliver(msg: mavlink.MAVLink_message, _link: VehicleLink) -> None:
        if not delivered:
            delivered.append(0)
            raise ValueError("handler bug")
        delivered.append(1)

    link = make_link(deliver)
    with caplog.at_level(logging.ERROR, logger="sitl.link"):
        link.datagram_received(heartbeat_datagram() * 2, CLIENT)  # two packets, one datagram
    assert (link.handler_errors, delivered) == (1, [0, 1])
    assert "error handling HEARTBEAT" in caplog.text

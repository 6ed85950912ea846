"""Mission transfer protocol (upload, download, clear, retries) without flying."""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as mavlink

from sitl.mission import MissionTransfer
from tests.sitl.helpers import FakeLink, roundtrip


class Recorder:
    def __init__(self) -> None:
        self.uploads: list[tuple[int, int]] = []
        self.current: list[int] = []
        self.current_sent = 0


def transfer() -> tuple[MissionTransfer, Recorder]:
    rec = Recorder()
    mt = MissionTransfer(
        1,
        1,
        on_uploaded=lambda kind, items: rec.uploads.append((kind, len(items))),
        on_set_current=lambda seq: rec.current.append(seq) or True,
        send_current=lambda: setattr(rec, "current_sent", rec.current_sent + 1),
    )
    return mt, rec


def item(seq: int, frame: int = 6, command: int = 16) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_mission_item_int_message(
        1, 1, seq, frame, command, 0, 1, 0, 1, 0, math.nan, 473977418, 85455939, 10.0, 0
    )


def deliver(
    mt: MissionTransfer,
    link: FakeLink,
    msg: mavlink.MAVLink_message,
    t: float = 0.0,
    src: tuple[int, int] = (255, 190),
) -> None:
    mt.handle(roundtrip(msg, *src), link, t)


def test_upload_requests_every_item_then_acks() -> None:
    mt, rec = transfer()
    link = FakeLink()
    deliver(mt, link, mavlink.MAVLink_mission_count_message(1, 1, 3, 0))
    for seq in range(3):
        assert link.sent[-1].get_type() == "MISSION_REQUEST_INT" and link.sent[-1].seq == seq
        deliver(mt, link, item(seq))
    assert link.sent[-1].get_type() == "MISSION_ACK" and link.sent[-1].type == 0
    assert rec.uploads == [(0, 3)]
    assert len(mt.items) == 3


def test_duplicates_are_rerequested_and_silence_is_retried() -> None:
    mt, _ = transfer()
    link = FakeLink()
    deliver(mt, link, mavlink.MAVLink_mission_count_message(1, 1, 2, 0))
    deliver(mt, link, item(0))
    deliver(mt, link, item(0))  # duplicate
    assert [m.seq for m in link.of_type("MISSION_REQUEST_INT")] == [0, 1, 1]
    mt.update(0.5)
    assert len(link.of_type("MISSION_REQUEST_INT")) == 3
    mt.update(1.1)
    assert [m.seq for m in link.of_type("MISSION_REQUEST_INT")][-1] == 1
    for k in range(2, 20):
        mt.update(1.1 * k)
    assert link.sent[-1].get_type() == "MISSION_ACK" and link.sent[-1].type == 15  # cancelled


def test_a_second_uploader_is_denied_and_bad_frames_rejected() -> None:
    mt, rec = transfer()
    link = FakeLink()
    deliver(mt, link, mavlink.MAVLink_mission_count_message(1, 1, 2, 0))
    deliver(mt, link, mavlink.MAVLink_mission_count_message(1, 1, 2, 0), src=(254, 1))
    assert link.sent[-1].get_type() == "MISSION_ACK" and link.sent[-1].type == 14  # denied
    deliver(mt, link, item(0, frame=1))  # LOCAL_NED is not supported
    assert link.sent[-1].type == 2  # unsupported frame
    assert rec.uploads == []


def test_download_and_clear() -> None:
    mt, rec = transfer()
    link = FakeLink()
    deliver(mt, link, mavlink.MAVLink_mission_count_message(1, 1, 1, 0))
    deliver(mt, link, item(0))
    deliver(mt, link, mavlink.MAVLink_mission_request_list_message(1, 1, 0))
    assert link.sent[-1].get_type() == "MISSION_COUNT" and link.sent[-1].count == 1
    deliver(mt, link, mavlink.MAVLink_mission_request_int_message(1, 1, 0, 0))
    got = link.sent[-1]
    assert got.get_type() == "MISSION_ITEM_INT" and (got.x, got.y, got.z) == (
        473977418,
        85455939,
        10.0,
    )
    deliver(mt, link, mavlink.MAVLink_mission_request_int_message(1, 1, 5, 0))
    assert link.sent[-1].get_type() == "MISSION_ACK" and link.sent[-1].type == 13
    deliver(mt, link, mavlink.MAVLink_mission_clear_all_message(1, 1, 0))
    assert link.sent[-1].type == 0 and mt.items == []
    assert rec.uploads[-1] == (0, 0)


def test_foreign_targets_are_ignored_and_set_current_is_reported() -> None:
    mt, rec = transfer()
    link = FakeLink()
    deliver(mt, link, mavlink.MAVLink_mission_count_message(2, 1, 3, 0))
    assert link.sent == []
    deliver(mt, link, mavlink.MAVLink_mission_set_current_message(1, 1, 2))
    assert rec.current == [2] and rec.current_sent == 1

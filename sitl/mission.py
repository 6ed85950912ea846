"""MAVLink mission protocol of one vehicle: upload, download, clear, set current.

Synchronous: :meth:`MissionTransfer.handle` takes a decoded message and the link it came on,
:meth:`MissionTransfer.update` retransmits requests that went unanswered. Flying the mission is
the autopilot's business; this module only stores what was uploaded (per mission type) and
tells the autopilot through callbacks.

Upload: MISSION_COUNT -> MISSION_REQUEST_INT(seq) -> MISSION_ITEM_INT(seq) ... -> MISSION_ACK.
Download: MISSION_REQUEST_LIST -> MISSION_COUNT -> MISSION_REQUEST_INT(seq) -> MISSION_ITEM_INT
... <- MISSION_ACK. Legacy float MISSION_ITEM / MISSION_REQUEST are accepted and answered in kind.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Protocol

from pymavlink.dialects.v20 import common as mavlink

logger = logging.getLogger(__name__)

MISSION_TYPE_MISSION = 0
MISSION_TYPE_FENCE = 1
MISSION_TYPE_RALLY = 2
MISSION_TYPE_ALL = 255

MAV_MISSION_ACCEPTED = 0
MAV_MISSION_ERROR = 1
MAV_MISSION_UNSUPPORTED_FRAME = 2
MAV_MISSION_UNSUPPORTED = 3
MAV_MISSION_NO_SPACE = 4
MAV_MISSION_INVALID = 5
MAV_MISSION_INVALID_SEQUENCE = 13
MAV_MISSION_DENIED = 14
MAV_MISSION_OPERATION_CANCELLED = 15

MAX_ITEMS = 1000
RETRY_PERIOD_S = 1.0
MAX_RETRIES = 10

#: Frames a positional item may use: GLOBAL, GLOBAL_RELATIVE_ALT, GLOBAL_INT,
#: GLOBAL_RELATIVE_ALT_INT; MISSION (2) for items without position.
GLOBAL_FRAMES = frozenset([0, 3, 5, 6])
RELATIVE_ALT_FRAMES = frozenset([3, 6])
FRAME_MISSION = 2


class MissionLink(Protocol):
    def send(self, msg: mavlink.MAVLink_message) -> None: ...


@dataclass(slots=True)
class MissionItem:
    """One item as stored; ``x``/``y`` are degrees x 1e7 as in MISSION_ITEM_INT."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = MISSION_TYPE_MISSION

    @classmethod
    def from_message(cls, msg: mavlink.MAVLink_message) -> MissionItem:
        if msg.get_type() == "MISSION_ITEM":
            if not (math.isfinite(msg.x) and math.isfinite(msg.y)):
                raise ValueError("MISSION_ITEM with non-finite latitude/longitude")
            x, y = round(msg.x * 1e7), round(msg.y * 1e7)
        else:
            x, y = int(msg.x), int(msg.y)
        return cls(
            msg.seq,
            msg.frame,
            msg.command,
            msg.current,
            msg.autocontinue,
            msg.param1,
            msg.param2,
            msg.param3,
            msg.param4,
            x,
            y,
            msg.z,
            getattr(msg, "mission_type", MISSION_TYPE_MISSION),
        )

    @property
    def latitude_deg(self) -> float:
        return self.x * 1e-7

    @property
    def longitude_deg(self) -> float:
        return self.y * 1e-7

    def to_int_message(self, target_system: int, target_component: int) -> mavlink.MAVLink_message:
        return mavlink.MAVLink_mission_item_int_message(
            target_system,
            target_component,
            self.seq,
            self.frame,
            self.command,
            self.current,
            self.autocontinue,
            self.param1,
            self.param2,
            self.param3,
            self.param4,
            self.x,
            self.y,
            self.z,
            self.mission_type,
        )

    def to_float_message(
        self, target_system: int, target_component: int
    ) -> mavlink.MAVLink_message:
        return mavlink.MAVLink_mission_item_message(
            target_system,
            target_component,
            self.seq,
            self.frame,
            self.command,
            self.current,
            self.autocontinue,
            self.param1,
            self.param2,
            self.param3,
            self.param4,
            self.latitude_deg,
            self.longitude_deg,
            self.z,
            self.mission_type,
        )

    def problem(self) -> int | None:
        """MAV_MISSION_RESULT error for an item the vehicle cannot store, or None if fine."""
        if self.frame in GLOBAL_FRAMES:
            if not (
                -900_000_000 <= self.x <= 900_000_000 and -1_800_000_000 <= self.y <= 1_800_000_000
            ):
                return MAV_MISSION_INVALID
            if not math.isfinite(self.z) and self.command != 21:
                return MAV_MISSION_INVALID
        elif self.frame != FRAME_MISSION:
            return MAV_MISSION_UNSUPPORTED_FRAME
        return None


@dataclass(slots=True)
class _Upload:
    link: MissionLink
    partner: tuple[int, int]
    mission_type: int
    count: int
    items: list[MissionItem]
    last_activity_s: float
    retries: int = 0
    use_int: bool = True


class MissionTransfer:
    """Mission storage and transfer for vehicle ``sysid`` (component ``compid``).

    ``on_uploaded(mission_type, items)`` runs after a complete, valid upload or a clear (with an
    empty list); ``on_set_current(seq)`` after MISSION_SET_CURRENT and returns whether ``seq``
    was accepted; ``send_current()`` sends MISSION_CURRENT (on every link).
    """

    def __init__(
        self,
        sysid: int,
        compid: int,
        on_uploaded: Callable[[int, list[MissionItem]], None],
        on_set_current: Callable[[int], bool],
        send_current: Callable[[], None],
    ) -> None:
        self.sysid = sysid
        self.compid = compid
        self.missions: dict[int, list[MissionItem]] = {
            MISSION_TYPE_MISSION: [],
            MISSION_TYPE_FENCE: [],
            MISSION_TYPE_RALLY: [],
        }
        self._on_uploaded = on_uploaded
        self._on_set_current = on_set_current
        self._send_current = send_current
        self._upload: _Upload | None = None

    @property
    def items(self) -> list[MissionItem]:
        return self.missions[MISSION_TYPE_MISSION]

    def _for_us(self, msg: mavlink.MAVLink_message) -> bool:
        return msg.target_system == self.sysid and msg.target_component in (0, self.compid)

    def handle(self, msg: mavlink.MAVLink_message, link: MissionLink, now_s: float) -> None:
        """Process one mission-protocol message (others are ignored)."""
        kind = msg.get_type()
        handler = self._handlers.get(kind)
        if handler is None or not self._for_us(msg):
            return
        handler(self, msg, link, now_s)

    # ---------------------------------------------------------------- upload
    def _count(self, msg: mavlink.MAVLink_message, link: MissionLink, now_s: float) -> None:
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        mission_type = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        if mission_type not in self.missions:
            self._ack(link, partner, MAV_MISSION_UNSUPPORTED, mission_type)
            return
        upload = self._upload
        if upload is not None and upload.partner != partner:
            self._ack(link, partner, MAV_MISSION_DENIED, mission_type)
            return
        if msg.count > MAX_ITEMS:
            self._upload = None
            self._ack(link, partner, MAV_MISSION_NO_SPACE, mission_type)
            return
        if msg.count == 0:
            self._upload = None
            self._store(mission_type, [])
            self._ack(link, partner, MAV_MISSION_ACCEPTED, mission_type)
            return
        self._upload = _Upload(link, partner, mission_type, msg.count, [], now_s)
        self._request(self._upload)

    def _item(self, msg: mavlink.MAVLink_message, link: MissionLink, now_s: float) -> None:
        upload = self._upload
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        if upload is None or upload.partner != partner:
            return
        mission_type = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        if mission_type != upload.mission_type:
            self._upload = None
            self._ack(link, partner, MAV_MISSION_ERROR, upload.mission_type)
            return
        expected = len(upload.items)
        if msg.seq != expected:
            # A duplicate or an item from the future: ask again for the one we need.
            upload.last_activity_s = now_s
            self._request(upload)
            return
        try:
            item = MissionItem.from_message(msg)
        except (ValueError, OverflowError):
            self._upload = None
            self._ack(link, partner, MAV_MISSION_INVALID, upload.mission_type)
            return
        problem = item.problem()
        if problem is not None:
            self._upload = None
            self._ack(link, partner, problem, upload.mission_type)
            return
        upload.items.append(item)
        upload.use_int = msg.get_type() == "MISSION_ITEM_INT"
        upload.last_activity_s = now_s
        upload.retries = 0
        if len(upload.items) < upload.count:
            self._request(upload)
            return
        self._upload = None
        self._store(upload.mission_type, upload.items)
        self._ack(link, partner, MAV_MISSION_ACCEPTED, upload.mission_type)

    def _request(self, upload: _Upload) -> None:
        seq = len(upload.items)
        target = upload.partner
        if upload.use_int:
            msg = mavlink.MAVLink_mission_request_int_message(
                target[0], target[1], seq, upload.mission_type
            )
        else:
            msg = mavlink.MAVLink_mission_request_message(
                target[0], target[1], seq, upload.mission_type
            )
        upload.link.send(msg)

    def update(self, now_s: float) -> None:
        """Retransmit the pending item request; give up after MAX_RETRIES."""
        upload = self._upload
        if upload is None or now_s - upload.last_activity_s < RETRY_PERIOD_S:
            return
        if upload.retries >= MAX_RETRIES:
            logger.info("vehicle %d: mission upload timed out", self.sysid)
            self._upload = None
            self._ack(
                upload.link, upload.partner, MAV_MISSION_OPERATION_CANCELLED, upload.mission_type
            )
            return
        upload.retries += 1
        upload.last_activity_s = now_s
        self._request(upload)

    def _store(self, mission_type: int, items: list[MissionItem]) -> None:
        for seq, item in enumerate(items):
            item.seq = seq
        self.missions[mission_type] = list(items)
        self._on_uploaded(mission_type, self.missions[mission_type])

    # -------------------------------------------------------------- download
    def _request_list(self, msg: mavlink.MAVLink_message, link: MissionLink, now_s: float) -> None:
        mission_type = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        if mission_type not in self.missions:
            self._ack(link, partner, MAV_MISSION_UNSUPPORTED, mission_type)
            return
        link.send(
            mavlink.MAVLink_mission_count_message(
                partner[0], partner[1], len(self.missions[mission_type]), mission_type
            )
        )

    def _request_item(self, msg: mavlink.MAVLink_message, link: MissionLink, now_s: float) -> None:
        mission_type = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        items = self.missions.get(mission_type)
        if items is None:
            self._ack(link, partner, MAV_MISSION_UNSUPPORTED, mission_type)
            return
        if not 0 <= msg.seq < len(items):
            self._ack(link, partner, MAV_MISSION_INVALID_SEQUENCE, mission_type)
            return
        item = items[msg.seq]
        if msg.get_type() == "MISSION_REQUEST_INT":
            link.send(item.to_int_message(partner[0], partner[1]))
        else:
            link.send(item.to_float_message(partner[0], partner[1]))

    # ------------------------------------------------------------ clear etc.
    def _clear_all(self, msg: mavlink.MAVLink_message, link: MissionLink, now_s: float) -> None:
        mission_type = getattr(msg, "mission_type", MISSION_TYPE_MISSION)
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        if mission_type == MISSION_TYPE_ALL:
            for kind in self.missions:
                self._store(kind, [])
        elif mission_type in self.missions:
            self._store(mission_type, [])
        else:
            self._ack(link, partner, MAV_MISSION_UNSUPPORTED, mission_type)
            return
        self._ack(link, partner, MAV_MISSION_ACCEPTED, mission_type)

    def _set_current(self, msg: mavlink.MAVLink_message, link: MissionLink, now_s: float) -> None:
        self._on_set_current(msg.seq)
        self._send_current()

    def _ack_received(self, msg: mavlink.MAVLink_message, link: MissionLink, now_s: float) -> None:
        upload = self._upload
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        if upload is not None and upload.partner == partner:
            # The uploader gave up (e.g. cancelled).
            self._upload = None

    def _ack(
        self, link: MissionLink, partner: tuple[int, int], result: int, mission_type: int
    ) -> None:
        link.send(mavlink.MAVLink_mission_ack_message(partner[0], partner[1], result, mission_type))

    _handlers: ClassVar[dict[str, Callable[..., None]]] = {
        "MISSION_COUNT": _count,
        "MISSION_ITEM_INT": _item,
        "MISSION_ITEM": _item,
        "MISSION_REQUEST_LIST": _request_list,
        "MISSION_REQUEST_INT": _request_item,
        "MISSION_REQUEST": _request_item,
        "MISSION_CLEAR_ALL": _clear_all,
        "MISSION_SET_CURRENT": _set_current,
        "MISSION_ACK": _ack_received,
    }

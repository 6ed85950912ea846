"""Message authentication (mission_runner.bus.auth): sealing, opening, what is dropped and
counted, who may publish what, and where keys come from. Clocks are injected: nothing sleeps."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest

from mission_runner.bus import (
    AuthPolicy,
    BusAuthError,
    BusKey,
    BusSettings,
    ControlCommand,
    InProcessBus,
    MessageAuth,
    MissionControl,
    Sender,
    StepMessage,
    Topics,
    open_bus,
)
from mission_runner.bus.auth import RateLimitedWarnings, allowed, resolve_key

TOPICS = Topics.for_mission("auth-test")
KEY = BusKey.from_text("k" * 40, "test")
OTHER_KEY = BusKey.from_text("o" * 40, "test")
BODY = StepMessage(2, 5, 0.625, 0.1, 1.0, 2.0).to_payload()


class Clock:
    """UNIX time that moves only when told."""

    def __init__(self, now_s: float = 1_800_000_000.0) -> None:
        self.now_s = now_s

    def __call__(self) -> float:
        return self.now_s


def pair(clock: Clock, policy: AuthPolicy | None = None) -> tuple[MessageAuth, MessageAuth]:
    """A sending and a receiving end with the same key and clock."""
    return (
        MessageAuth(KEY, policy, wall_clock=clock, log_clock=clock),
        MessageAuth(KEY, policy, wall_clock=clock, log_clock=clock),
    )


def test_a_sealed_message_opens_to_its_body() -> None:
    sender, receiver = pair(Clock())
    sealed = sender.seal(Sender.vehicle(2), TOPICS.step(2), BODY)
    assert sealed.startswith(b"MR1 ") and sealed.endswith(BODY)
    assert receiver.open(TOPICS.step(2), sealed) == BODY
    assert receiver.counters.as_dict() == {
        "accepted": 1,
        "oversized": 0,
        "malformed": 0,
        "forged": 0,
        "unauthorised": 0,
        "stale": 0,
        "replayed": 0,
        "empty": 0,
    }


@pytest.mark.parametrize(
    "tamper",
    [
        lambda sealed: sealed.replace(b'"step":5', b'"step":6'),  # the body
        lambda sealed: sealed.replace(b"vehicle-2", b"vehicle-3"),  # the signer
        lambda sealed: sealed[:4] + b"A" * 43 + sealed[47:],  # the MAC itself
    ],
    ids=["body", "sender", "mac"],
)
def test_any_changed_byte_is_a_forgery(tamper: object) -> None:
    sender, receiver = pair(Clock())
    sealed = sender.seal(Sender.vehicle(2), TOPICS.step(2), BODY)
    assert callable(tamper)
    assert receiver.open(TOPICS.step(2), tamper(sealed)) is None
    assert receiver.counters.forged == 1 and receiver.counters.accepted == 0


def test_another_key_another_topic_or_another_mission_is_a_forgery() -> None:
    clock = Clock()
    stranger = MessageAuth(OTHER_KEY, wall_clock=clock)
    _, receiver = pair(clock)
    assert (
        receiver.open(TOPICS.step(2), stranger.seal(Sender.vehicle(2), TOPICS.step(2), BODY))
        is None
    )
    mine = MessageAuth(KEY, wall_clock=clock)
    other_mission = Topics.for_mission("another-mission")
    sealed = mine.seal(Sender.vehicle(2), other_mission.step(2), BODY)
    assert receiver.open(TOPICS.step(2), sealed) is None  # replayed into this mission
    assert receiver.counters.forged == 2


def test_an_unsigned_payload_is_malformed_and_an_empty_one_is_counted_apart() -> None:
    _, receiver = pair(Clock())
    for payload in (BODY, b"MR1 x y", b"MR1 " + b"A" * 43 + b" ground 1 2\n{}", b"\xff" * 10):
        assert receiver.open(TOPICS.step(2), payload) is None
    assert receiver.counters.malformed == 4
    # MQTT's "clear the retained value": no message, so none is handed on, but a flood of them
    # is seen.
    for _ in range(3):
        assert receiver.open(TOPICS.control(), b"") is None
    assert receiver.counters.empty == 3
    assert receiver.counters.rejected == 7
    assert receiver.counters.as_dict()["empty"] == 3


def test_oversized_payloads_are_dropped_before_the_mac_is_computed() -> None:
    sender, receiver = pair(Clock(), AuthPolicy(max_message_bytes=2048))
    sealed = sender.seal(Sender.ground(), TOPICS.control(), b"x" * 4096)
    assert receiver.open(TOPICS.control(), sealed) is None
    assert receiver.counters.oversized == 1


def test_a_replayed_message_is_dropped_and_a_newer_one_accepted() -> None:
    clock = Clock()
    sender, receiver = pair(clock)
    first = sender.seal(Sender.vehicle(2), TOPICS.step(2), BODY)
    second = sender.seal(Sender.vehicle(2), TOPICS.step(2), BODY)
    assert receiver.open(TOPICS.step(2), first) == BODY
    assert receiver.open(TOPICS.step(2), first) is None
    assert receiver.open(TOPICS.step(2), second) == BODY
    assert receiver.open(TOPICS.step(2), first) is None  # older than the last accepted
    assert receiver.counters.replayed == 2


def test_sequence_numbers_continue_above_a_restarted_senders_previous_run() -> None:
    clock = Clock()
    before_restart = MessageAuth(KEY, wall_clock=clock)
    _, receiver = pair(clock)
    old = [before_restart.seal(Sender.ground(), TOPICS.control(), b"{}") for _ in range(50)]
    assert all(receiver.open(TOPICS.control(), sealed) for sealed in old)
    clock.now_s += 0.001  # a new process of the same role, a millisecond later
    restarted = MessageAuth(KEY, wall_clock=clock)
    assert receiver.open(TOPICS.control(), restarted.seal(Sender.ground(), TOPICS.control(), b"{}"))


def test_stale_and_future_messages_are_dropped() -> None:
    clock = Clock()
    sender, receiver = pair(clock, AuthPolicy(time_window_s=10.0))
    sealed = sender.seal(Sender.ground(), TOPICS.control(), b"{}")
    clock.now_s += 10.5
    assert receiver.open(TOPICS.control(), sealed) is None
    ahead = MessageAuth(KEY, wall_clock=Clock(clock.now_s + 10.5))  # its clock 10.5 s ahead
    assert (
        receiver.open(TOPICS.control(), ahead.seal(Sender.ground(), TOPICS.control(), b"{}"))
        is None
    )
    assert receiver.counters.stale == 2


def test_a_retained_message_is_accepted_for_longer_and_again_for_a_new_subscription() -> None:
    clock = Clock()
    sender, receiver = pair(clock, AuthPolicy(time_window_s=10.0, retained_max_age_s=600.0))
    prepare = sender.seal(Sender.ground(), TOPICS.control(), b"{}", retain=True)
    clock.now_s += 120.0  # a vehicle process started two minutes after the ground station
    assert receiver.open(TOPICS.control(), prepare, retained=True) == b"{}"
    assert receiver.open(TOPICS.control(), prepare, retained=True) == b"{}"  # 2nd subscription
    assert receiver.open(TOPICS.control(), prepare, retained=False) is None  # replayed live
    clock.now_s += 600.0
    late = MessageAuth(KEY, wall_clock=clock)
    assert late.open(TOPICS.control(), prepare, retained=True) is None  # older than 10 min
    # A live message re-published retained by someone else keeps the live window.
    live = sender.seal(Sender.ground(), TOPICS.control(), b"{}")
    clock.now_s += 60.0
    assert MessageAuth(KEY, wall_clock=clock).open(TOPICS.control(), live, retained=True) is None


def test_a_last_will_is_accepted_whenever_the_broker_publishes_it_but_only_once() -> None:
    clock = Clock()
    vehicle, ground = pair(clock)
    will = vehicle.seal(Sender.vehicle(3), TOPICS.status(3), b'{"state":"lost"}', will=True)
    status = vehicle.seal(Sender.vehicle(3), TOPICS.status(3), b'{"state":"following"}')
    assert ground.open(TOPICS.status(3), status) is not None
    clock.now_s += 3600.0  # the connection drops an hour later
    assert ground.open(TOPICS.status(3), will) == b'{"state":"lost"}'
    assert ground.open(TOPICS.status(3), will) is None
    assert ground.counters.replayed == 1


@pytest.mark.parametrize(
    ("sender", "topic", "ok"),
    [
        (Sender.ground(), TOPICS.control(), True),
        (Sender.vehicle(1), TOPICS.control(), False),
        (Sender.ranges(), TOPICS.control(), False),
        (Sender.vehicle(1), TOPICS.step(1), True),
        (Sender.vehicle(1), TOPICS.step(2), False),
        (Sender.ground(), TOPICS.step(2), False),
        (Sender.ranges(), TOPICS.step(2), False),
        (Sender.vehicle(2), TOPICS.status(2), True),
        (Sender.ranges(), TOPICS.status(2), False),
        (Sender.ranges(), TOPICS.ranges(2), True),
        (Sender.ranges(), TOPICS.target(3), True),
        (Sender.vehicle(2), TOPICS.ranges(2), True),
        (Sender.vehicle(1), TOPICS.ranges(2), False),
        (Sender.ground(), TOPICS.ranges(2), False),
        (Sender.vehicle(1), "somewhere/else", True),
    ],
)
def test_who_may_publish_what(sender: Sender, topic: str, ok: bool) -> None:
    assert allowed(sender, topic) is ok


def test_a_signed_message_from_the_wrong_role_is_unauthorised() -> None:
    clock = Clock()
    vehicle, receiver = pair(clock)
    start = MissionControl(ControlCommand.START, 1000.0, mission_id="m").to_payload()
    sealed = vehicle.seal(Sender.vehicle(2), TOPICS.control(), start)
    assert receiver.open(TOPICS.control(), sealed) is None
    assert receiver.counters.unauthorised == 1


def test_sender_names_round_trip_and_odd_ones_are_refused() -> None:
    for sender in (Sender.ground(), Sender.ranges(), Sender.vehicle(12)):
        assert Sender.parse(str(sender)) == sender
    for text in ("vehicle-0", "vehicle-01", "vehicle-", "vehicle-x", "pilot", "vehicle-+1"):
        with pytest.raises(ValueError):
            Sender.parse(text)
    assert Sender.for_topic(TOPICS.ranges(4)) == Sender.vehicle(4)
    assert Sender.for_topic(TOPICS.control()) == Sender.ground()


def test_rejections_are_logged_at_most_once_per_interval(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    _, receiver = pair(clock)
    with caplog.at_level(logging.WARNING, logger="mission_runner.bus.auth"):
        for _ in range(100):
            receiver.open(TOPICS.step(2), BODY)
        clock.now_s += 10.0
        receiver.open(TOPICS.step(2), BODY)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2
    assert "dropped a malformed message" in lines[0]
    assert "99 more since the last report" in lines[1] and "101 dropped so far" in lines[1]
    assert receiver.counters.malformed == 101


def test_rate_limited_warnings_keep_kinds_apart(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    warnings = RateLimitedWarnings(logging.getLogger("t"), interval_s=5.0, clock=clock)
    with caplog.at_level(logging.WARNING, logger="t"):
        assert warnings.warn("forged", "a")
        assert warnings.warn("replayed", "b")
        assert not warnings.warn("forged", "c")
    assert [r.getMessage() for r in caplog.records] == ["a", "b"]


class TestKeys:
    def test_the_command_line_file_wins_over_the_environment_and_the_settings(
        self, tmp_path: Path
    ) -> None:
        cli, configured = tmp_path / "cli.key", tmp_path / "configured.key"
        cli.write_text("c" * 64 + "\n")
        configured.write_text("s" * 64)
        environ = {"MISSION_BUS_KEY": "e" * 64}
        key = resolve_key(kind="mqtt", key_file=configured, cli_key_file=cli, environ=environ)
        assert key.secret == b"c" * 64 and str(cli) in key.source
        key = resolve_key(kind="mqtt", key_file=configured, environ=environ)
        assert key.secret == b"e" * 64 and "MISSION_BUS_KEY" in key.source
        assert resolve_key(kind="mqtt", key_file=configured, environ={}).secret == b"s" * 64

    def test_an_mqtt_bus_without_a_key_is_refused_unless_insecure(self) -> None:
        with pytest.raises(BusAuthError, match="--bus-key-file") as raised:
            resolve_key(kind="mqtt", key_file=None, environ={})
        assert "--insecure-bus" in str(raised.value)
        insecure = resolve_key(kind="mqtt", key_file=None, insecure=True, environ={})
        assert insecure.insecure and "NO authentication" in insecure.source

    def test_an_in_process_bus_without_a_key_makes_its_own(self) -> None:
        first = resolve_key(kind="inprocess", key_file=None, environ={})
        second = resolve_key(kind="inprocess", key_file=None, environ={})
        assert len(first.secret) == 64 and first.secret != second.secret

    def test_short_and_unreadable_keys_are_refused(self, tmp_path: Path) -> None:
        with pytest.raises(BusAuthError, match="at least 32"):
            resolve_key(kind="mqtt", key_file=None, environ={"MISSION_BUS_KEY": "short"})
        with pytest.raises(BusAuthError, match="cannot read the bus key file"):
            resolve_key(kind="mqtt", key_file=tmp_path / "missing", environ={})

    def test_a_key_file_others_can_read_is_warned_about(
        self, tmp_path: Path, caplog: pytest.LogCaptureFixture
    ) -> None:
        path = tmp_path / "bus.key"
        path.write_text("k" * 64)
        os.chmod(path, 0o644)
        with caplog.at_level(logging.WARNING, logger="mission_runner.bus.auth"):
            BusKey.from_file(path)
        assert "chmod 600" in caplog.text

    def test_the_key_never_shows_in_a_repr_and_has_a_fingerprint(self) -> None:
        assert "k" * 40 not in repr(KEY)
        assert KEY.fingerprint != OTHER_KEY.fingerprint and len(KEY.fingerprint) == 12

    def test_open_bus_refuses_an_mqtt_bus_without_a_key(
        self, monkeypatch: pytest.MonkeyPatch
    ) -> None:
        monkeypatch.delenv("MISSION_BUS_KEY")
        with pytest.raises(BusAuthError, match="an MQTT bus needs a key"):
            open_bus(BusSettings(kind="mqtt"), sender=Sender.ground())


@pytest.mark.asyncio
async def test_the_in_process_bus_drops_a_member_publishing_as_another() -> None:
    async with InProcessBus() as bus, bus.subscribe(TOPICS.everything()) as everything:
        vehicle_1 = bus.as_sender(Sender.vehicle(1))
        await vehicle_1.publish_message(TOPICS.step(1), StepMessage(1, 0, 0.0, 0, 0, 0), timeout=1)
        await vehicle_1.publish_message(TOPICS.step(2), StepMessage(2, 0, 0.0, 0, 0, 0), timeout=1)
        start = MissionControl(ControlCommand.START, 1000.0)
        await vehicle_1.publish_message(TOPICS.control(), start, timeout=1)
        assert [topic for topic, _ in everything.drain_messages(StepMessage)] == [TOPICS.step(1)]
    assert bus.auth_counters.unauthorised == 2

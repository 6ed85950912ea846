"""MAVLink 2 message signing as PX4 does it: the rules on packets built with pymavlink, then real
clients over UDP (a pymavlink ground station, MAVProxy's signing module)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import stat
import subprocess
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from pydantic import ValidationError
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from sitl.cli import build_parser, load_config
from sitl.config import EmulatorConfig, PortsConfig, SigningConfig
from sitl.emulator import Emulator
from sitl.signing import (
    BLANK_KEY,
    FileKeyStore,
    MemoryKeyStore,
    SetupResult,
    SigningKey,
    VehicleSigning,
    Verdict,
    key_from_passphrase,
    signing_timestamp,
)
from tests.sitl.helpers import RawClient, free_port_config

KEY = key_from_passphrase("correct horse battery staple")
OTHER_KEY = key_from_passphrase("wrong")
NOW_S = 1_750_000_000.0  # a fixed host clock for the rules below
NOW = signing_timestamp(NOW_S)
GCS = (255, 190)


def packet(
    msg: mavlink.MAVLink_message,
    *,
    key: bytes | None = None,
    timestamp: int = NOW,
    link_id: int = 0,
    src: tuple[int, int] = GCS,
) -> mavlink.MAVLink_message:
    """``msg`` as a vehicle link decodes it from a client (signed with ``key`` if given)."""
    encoder = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    if key is not None:
        encoder.signing.secret_key = key
        encoder.signing.sign_outgoing = True
        encoder.signing.link_id = link_id
        encoder.signing.timestamp = timestamp
    decoded = mavlink.MAVLink(None).parse_buffer(msg.pack(encoder))
    assert decoded is not None and len(decoded) == 1
    return decoded[0]


def setup_signing(key: bytes, timestamp: int = NOW, target: tuple[int, int] = (1, 1)):
    return mavlink.MAVLink_setup_signing_message(*target, list(key), timestamp)


def param_set(value: float) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_param_set_message(1, 1, b"MIS_TAKEOFF_ALT", value, 9)


def heartbeat() -> mavlink.MAVLink_message:
    return mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3)


def signing(*, armed: bool = False, store: MemoryKeyStore | None = None, **kwargs):
    return VehicleSigning(
        1, store=store, unix_time_s=lambda: NOW_S, is_armed=lambda: armed, **kwargs
    )


def provisioned(**kwargs) -> VehicleSigning:
    vehicle = signing(**kwargs)
    msg = packet(setup_signing(KEY))
    assert vehicle.check(msg) is Verdict.ACCEPTED
    assert vehicle.setup(msg) is SetupResult.KEY_ACCEPTED
    return vehicle


def sent_by(vehicle: VehicleSigning, msg: mavlink.MAVLink_message, link_id: int = 1) -> bytes:
    """The bytes a vehicle link would send for ``msg``."""
    written: list[bytes] = []

    class Sink:
        def write(self, data: bytes) -> None:
            written.append(bytes(data))

    vehicle.send(mavlink.MAVLink(Sink(), srcSystem=1, srcComponent=1), msg, link_id)
    return written[0]


# ---------------------------------------------------------------- the rules, as PX4 has them
def test_without_a_key_everything_is_accepted_and_nothing_is_signed() -> None:
    vehicle = signing()
    assert not vehicle.active
    for msg in (packet(param_set(3.0)), packet(param_set(3.0), key=OTHER_KEY)):
        assert vehicle.check(msg) is Verdict.ACCEPTED
    data = sent_by(vehicle, heartbeat())
    assert data[2] & mavlink.MAVLINK_IFLAG_SIGNED == 0


def test_setup_signing_turns_signing_on_and_every_packet_sent_is_signed_with_the_key() -> None:
    store = MemoryKeyStore()
    vehicle = provisioned(store=store)
    assert vehicle.active
    assert store.keys[1] == SigningKey(KEY, NOW)  # stored as it arrives, as PX4 writes its file
    checker = mavlink.MAVLink(None)
    checker.signing.secret_key = KEY  # a client with the key checks every signature
    stamps = []
    for link_id in (0, 1, 4):
        data = sent_by(vehicle, heartbeat(), link_id)
        assert data[2] & mavlink.MAVLINK_IFLAG_SIGNED
        assert data[-13] == link_id
        stamps.append(int.from_bytes(data[-12:-6], "little"))
        assert checker.parse_buffer(data)[0].get_type() == "HEARTBEAT"
    assert checker.signing.goodsig_count == 3 and checker.signing.badsig_count == 0
    assert stamps == [NOW, NOW + 1, NOW + 2]  # one clock for the links, one tick per packet


@pytest.mark.parametrize(
    ("msg", "accepted"),
    [
        (heartbeat(), True),
        (mavlink.MAVLink_radio_status_message(200, 190, 50, 40, 30, 0, 0), True),
        (
            mavlink.MAVLink_adsb_vehicle_message(
                1, 473977420, 85455940, 0, 50000, 0, 0, 0, b"TEST", 0, 1, 0, 0
            ),
            True,
        ),
        (mavlink.MAVLink_collision_message(0, 1, 1, 1, 1.0, 1.0, 1.0), True),
        (param_set(9.0), False),
        (mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0), False),
        (setup_signing(OTHER_KEY), False),  # a new key must come signed with the current one
    ],
)
def test_unsigned_packets_are_refused_except_px4s_accept_list(
    msg: mavlink.MAVLink_message, accepted: bool
) -> None:
    vehicle = provisioned()
    expected = Verdict.ACCEPTED_UNSIGNED if accepted else Verdict.UNSIGNED
    assert vehicle.check(packet(msg)) is expected
    assert vehicle.rejected == (0 if accepted else 1)


def test_a_wrong_key_is_refused_yet_an_allowlisted_message_still_passes() -> None:
    vehicle = provisioned()
    assert vehicle.check(packet(param_set(9.0), key=OTHER_KEY)) is Verdict.BAD_SIGNATURE
    assert vehicle.check(packet(heartbeat(), key=OTHER_KEY)) is Verdict.ACCEPTED_UNSIGNED
    assert vehicle.check(packet(param_set(9.0), key=KEY)) is Verdict.ACCEPTED


def test_a_replayed_or_older_timestamp_is_refused_per_stream() -> None:
    vehicle = provisioned()
    first = packet(param_set(4.0), key=KEY, timestamp=NOW + 10)
    assert vehicle.check(first) is Verdict.ACCEPTED
    assert vehicle.check(first) is Verdict.REPLAY  # the same bytes again
    assert vehicle.check(packet(param_set(4.0), key=KEY, timestamp=NOW + 9)) is Verdict.REPLAY
    # Another link id or sender is another stream with its own timestamps.
    assert vehicle.check(packet(param_set(4.0), key=KEY, timestamp=NOW + 5, link_id=3)) is (
        Verdict.ACCEPTED
    )
    other_sender = packet(param_set(4.0), key=KEY, timestamp=NOW + 5, src=(254, 1))
    assert vehicle.check(other_sender) is Verdict.ACCEPTED
    assert vehicle.check(packet(param_set(4.0), key=KEY, timestamp=NOW + 11)) is Verdict.ACCEPTED
    assert vehicle.verdicts[Verdict.REPLAY] == 2


def test_a_new_stream_may_be_at_most_a_minute_behind_the_vehicle() -> None:
    vehicle = provisioned()
    minute = 60 * 100_000
    old = packet(param_set(4.0), key=KEY, timestamp=NOW - minute - 1, link_id=1)
    assert vehicle.check(old) is Verdict.OLD_TIMESTAMP
    late = packet(param_set(4.0), key=KEY, timestamp=NOW - minute, link_id=2)
    assert vehicle.check(late) is Verdict.ACCEPTED


def test_an_accepted_timestamp_moves_the_vehicles_own_clock_forward() -> None:
    vehicle = provisioned()
    ahead = NOW + 5_000_000
    assert vehicle.check(packet(param_set(4.0), key=KEY, timestamp=ahead)) is Verdict.ACCEPTED
    data = sent_by(vehicle, heartbeat())
    assert int.from_bytes(data[-12:-6], "little") == ahead


def test_at_most_16_streams_are_tracked() -> None:
    vehicle = provisioned()
    for link_id in range(16):
        assert vehicle.check(packet(heartbeat(), key=KEY, link_id=link_id)) is Verdict.ACCEPTED
    assert vehicle.check(packet(param_set(1.0), key=KEY, link_id=16)) is Verdict.TOO_MANY_STREAMS


def test_only_a_signed_blank_key_turns_signing_off() -> None:
    store = MemoryKeyStore()
    vehicle = provisioned(store=store)
    unsigned_blank = packet(setup_signing(bytes(32), 0))
    assert vehicle.check(unsigned_blank) is Verdict.UNSIGNED  # never reaches the handler
    assert vehicle.setup(unsigned_blank) is SetupResult.BLANK_KEY_REJECTED  # nor would it pass
    assert vehicle.active
    signed_blank = packet(setup_signing(bytes(32), 0), key=KEY, timestamp=NOW + 1)
    assert vehicle.check(signed_blank) is Verdict.ACCEPTED
    assert vehicle.setup(signed_blank) is SetupResult.SIGNING_DISABLED
    assert not vehicle.active and store.keys[1] == BLANK_KEY
    assert vehicle.check(packet(param_set(1.0))) is Verdict.ACCEPTED


def test_a_signed_setup_signing_replaces_the_key() -> None:
    vehicle = provisioned()
    change = packet(setup_signing(OTHER_KEY, NOW), key=KEY, timestamp=NOW + 1)
    assert vehicle.check(change) is Verdict.ACCEPTED
    assert vehicle.setup(change) is SetupResult.KEY_ACCEPTED
    assert vehicle.check(packet(param_set(1.0), key=KEY, timestamp=NOW + 2)) is (
        Verdict.BAD_SIGNATURE
    )
    assert vehicle.check(packet(param_set(1.0), key=OTHER_KEY, timestamp=NOW + 2)) is (
        Verdict.ACCEPTED
    )


def test_keys_do_not_change_while_armed_nor_for_another_vehicle() -> None:
    armed = signing(armed=True)
    assert armed.setup(packet(setup_signing(KEY))) is SetupResult.REJECTED_ARMED
    assert not armed.active
    vehicle = signing()
    for target in ((2, 1), (1, 154)):
        assert vehicle.setup(packet(setup_signing(KEY, target=target))) is (
            SetupResult.NOT_ADDRESSED
        )
    assert not vehicle.active
    assert vehicle.setup(packet(setup_signing(KEY, target=(0, 0)))) is SetupResult.KEY_ACCEPTED


def test_the_timestamp_never_goes_back_for_the_same_key() -> None:
    store = MemoryKeyStore({1: SigningKey(KEY, NOW + 700)})
    vehicle = signing(store=store)  # boots with the stored key and its timestamp
    assert vehicle.active and vehicle.timestamp == NOW + 700
    vehicle.timestamp = NOW + 900  # as if 200 packets went out
    again = packet(setup_signing(KEY, 5), key=KEY, timestamp=NOW + 901)
    assert vehicle.check(again) is Verdict.ACCEPTED
    assert vehicle.setup(again) is SetupResult.KEY_ACCEPTED
    assert vehicle.timestamp == NOW + 901 and store.keys[1].timestamp == NOW + 901
    # A key older than the host clock starts at the host clock.
    fresh = signing(store=MemoryKeyStore({1: SigningKey(OTHER_KEY, 3)}))
    assert fresh.timestamp == NOW


def test_a_clean_shutdown_stores_the_timestamp_for_the_next_boot() -> None:
    store = MemoryKeyStore()
    vehicle = provisioned(store=store)
    for _ in range(5):
        sent_by(vehicle, heartbeat())
    vehicle.checkpoint()
    assert store.keys[1] == SigningKey(KEY, NOW + 5)
    assert signing(store=store).timestamp == NOW + 5


def test_the_key_file_is_px4s_40_bytes_readable_by_its_owner_only(tmp_path: Path) -> None:
    store = FileKeyStore(tmp_path / "keys")
    provisioned(store=store)
    path = tmp_path / "keys" / "vehicle_001" / "mavlink-signing-key.bin"
    assert path.read_bytes() == KEY + NOW.to_bytes(8, "little")
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    rebooted = VehicleSigning(1, store=store, unix_time_s=lambda: NOW_S)
    assert rebooted.active and rebooted.fingerprint == provisioned().fingerprint
    path.write_bytes(b"short")  # PX4 boots without a key when the file is not whole
    assert not VehicleSigning(1, store=store, unix_time_s=lambda: NOW_S).active


def test_the_start_up_key_comes_from_a_passphrase_or_hex_and_not_both(tmp_path: Path) -> None:
    assert SigningConfig(passphrase="pw").initial_key() == key_from_passphrase("pw")
    assert SigningConfig(key_hex=KEY.hex()).initial_key() == KEY
    assert SigningConfig().initial_key() is None
    for bad in (
        {"key_hex": "abcd"},
        {"key_hex": "zz" * 32},
        {"passphrase": "a", "key_hex": KEY.hex()},
    ):
        with pytest.raises(ValidationError):
            SigningConfig.model_validate(bad)
    assert "pw" not in repr(SigningConfig(passphrase="pw"))  # secrets stay out of logs
    args = build_parser().parse_args(
        ["--signing-passphrase", "pw", "--signing-key-dir", str(tmp_path)]
    )
    config = load_config(args)
    assert config.signing.initial_key() == key_from_passphrase("pw")
    assert config.signing.key_dir == tmp_path


# ------------------------------------------------------------------------ real clients, UDP
def ground_station(port: int, key: bytes) -> dict[str, object]:
    """A pymavlink ground station (blocking, as such scripts are): provision ``key``, set a
    parameter twice with signed packets, then replay the first set's datagram."""
    conn = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{port}", source_system=255, source_component=190
    )
    try:
        if conn.wait_heartbeat(timeout=5) is None:
            raise AssertionError("no heartbeat from the vehicle")
        conn.mav.setup_signing_send(1, 1, list(key), signing_timestamp(time.time()))
        conn.setup_signing(key, sign_outgoing=True)  # pymavlink's own signing from here on

        def set_and_wait(value: float) -> bytes:
            data = conn.mav.param_set_encode(1, 1, b"MIS_TAKEOFF_ALT", value, 9).pack(conn.mav)
            conn.write(data)
            reply = conn.recv_match(
                type="PARAM_VALUE",
                blocking=True,
                timeout=5,
                condition=f"abs(PARAM_VALUE.param_value - {value}) < 1e-3",
            )
            if reply is None:
                raise AssertionError(f"no PARAM_VALUE {value}")
            return bytes(data)

        first = set_and_wait(6.5)
        set_and_wait(7.5)
        conn.write(first)  # a replay of the signed 6.5
        conn.mav.param_request_read_send(1, 1, b"MIS_TAKEOFF_ALT", -1)
        after = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=5)
        return {"after_replay": after.param_value, "good": conn.mav.signing.goodsig_count}
    finally:
        conn.close()


@contextlib.asynccontextmanager
async def one_vehicle(**settings: object) -> AsyncIterator[tuple[Emulator, PortsConfig]]:
    ports = free_port_config(1)
    config = EmulatorConfig.model_validate({"vehicles": 1, "ports": ports, **settings})
    async with Emulator(config) as emulator:
        yield emulator, ports


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_pymavlink_sets_up_signing_then_unsigned_and_replayed_packets_are_refused() -> None:
    async with one_vehicle() as (emulator, ports):
        result = await asyncio.to_thread(ground_station, ports.gcs_remote_port, KEY)
        vehicle = emulator.signing(0)
        assert vehicle.active
        assert result["after_replay"] == pytest.approx(7.5)  # the replayed 6.5 did nothing
        assert vehicle.verdicts[Verdict.REPLAY] == 1
        assert result["good"] > 0  # the vehicle's replies carried valid signatures

        # A client without the key, on the API link: heard (HEARTBEAT) but not obeyed.
        async with RawClient(ports.api_remote_base) as stranger:
            await stranger.expect(lambda m: m.get_type() == "HEARTBEAT", 3.0, "heartbeat")
            stranger.heartbeat()
            stranger.send(param_set(9.0))
            with pytest.raises(TimeoutError):
                await stranger.command(1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, timeout_s=1.0)
        assert emulator.autopilot(0).params["MIS_TAKEOFF_ALT"] == pytest.approx(7.5)
        assert not emulator.autopilot(0).armed
        assert vehicle.verdicts[Verdict.UNSIGNED] >= 2  # PARAM_SET and the arm command
        assert vehicle.verdicts[Verdict.ACCEPTED_UNSIGNED] >= 1  # its heartbeat
        assert emulator.stats().rx_rejected == vehicle.rejected


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_vehicles_start_signed_from_the_config_and_keep_keys_in_the_key_dir(
    tmp_path: Path,
) -> None:
    keys = tmp_path / "keys"
    async with one_vehicle(signing={"passphrase": "pw", "key_dir": keys}) as (emulator, ports):
        assert emulator.signing(0).active
        async with RawClient(ports.api_remote_base) as client:
            client.parser.signing.secret_key = key_from_passphrase("pw")  # refuse unsigned
            await client.expect(lambda m: m.get_type() == "HEARTBEAT", 3.0, "signed heartbeat")
            with pytest.raises(TimeoutError):
                await client.command(1, mavlink.MAV_CMD_REQUEST_MESSAGE, 242, timeout_s=1.0)
            client.encoder.signing.secret_key = key_from_passphrase("pw")
            client.encoder.signing.sign_outgoing = True
            client.encoder.signing.timestamp = signing_timestamp(time.time())
            result = await client.command(1, mavlink.MAV_CMD_REQUEST_MESSAGE, 242)
            assert result == mavlink.MAV_RESULT_ACCEPTED
    # The next run finds the key in the key directory, without being told the passphrase.
    async with one_vehicle(signing={"key_dir": keys}) as (emulator, _):
        assert emulator.signing(0).active
        assert (
            emulator.signing(0).fingerprint
            == VehicleSigning(1, initial_key=key_from_passphrase("pw")).fingerprint
        )


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_setup_signing_never_reaches_the_tlog(tmp_path: Path) -> None:
    async with (
        one_vehicle(tlog_dir=tmp_path) as (emulator, ports),
        RawClient(ports.api_remote_base) as client,
    ):
        await client.expect(lambda m: m.get_type() == "HEARTBEAT", 3.0, "heartbeat")
        client.send(setup_signing(KEY, signing_timestamp(time.time())))
        await emulator.wait_for(lambda: emulator.signing(0).active, timeout_s=3.0)
    tlog = tmp_path / "vehicle_001.tlog"
    assert KEY not in tlog.read_bytes()  # the key travels in clear inside SETUP_SIGNING
    log = mavutil.mavlink_connection(str(tlog))
    kinds = set()
    while (msg := log.recv_msg()) is not None:
        kinds.add(msg.get_type())
    log.close()
    assert "HEARTBEAT" in kinds and "SETUP_SIGNING" not in kinds


MAVPROXY = shutil.which("mavproxy.py")


@pytest.mark.skipif(MAVPROXY is None, reason="MAVProxy is not installed (pip install -e '.[test]')")
@pytest.mark.asyncio
@pytest.mark.timeout(90)
async def test_mavproxy_signing_setup_then_its_commands_work_and_an_unsigned_client_is_ignored(
    tmp_path: Path,
) -> None:
    assert MAVPROXY is not None
    # No auto-disarm on the ground: the disarm below must be MAVProxy's.
    async with one_vehicle(params={"COM_DISARM_PRFLT": -1.0}) as (emulator, ports):
        process = await asyncio.create_subprocess_exec(
            MAVPROXY,
            f"--master=udpin:127.0.0.1:{ports.gcs_remote_port}",
            "--no-state",
            cwd=tmp_path,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        assert process.stdin is not None and process.stdout is not None
        seen: list[str] = []

        async def wait_for_line(text: str, timeout_s: float = 20.0) -> None:
            assert process.stdout is not None
            try:
                async with asyncio.timeout(timeout_s):
                    while not any(text in line for line in seen):
                        line = await process.stdout.readline()
                        if not line:
                            raise AssertionError(f"MAVProxy ended before {text!r}: {seen}")
                        seen.append(line.decode(errors="replace").strip())
            except TimeoutError:
                raise AssertionError(
                    f"MAVProxy did not print {text!r} within {timeout_s} s: {seen[-10:]}"
                ) from None

        async def mavproxy(command: str) -> None:
            assert process.stdin is not None
            process.stdin.write(command.encode() + b"\n")
            await process.stdin.drain()

        try:
            await wait_for_line("Detected vehicle 1:1")
            await mavproxy("set allow_unsigned 0")  # from now on MAVProxy drops unsigned packets
            await mavproxy("signing setup my-passphrase")
            await wait_for_line("Setup signing key")
            await emulator.wait_for(lambda: emulator.signing(0).active, timeout_s=5.0)
            await emulator.wait_for(
                lambda: emulator.autopilot(0).ready(emulator.time_s), timeout_s=5.0
            )
            await mavproxy("arm throttle")
            await emulator.wait_for(lambda: emulator.autopilot(0).armed, timeout_s=10.0)
            await wait_for_line("ARMED")  # in heartbeats whose signature MAVProxy checked

            async with RawClient(ports.api_remote_base) as stranger:  # no key
                await stranger.expect(lambda m: m.get_type() == "HEARTBEAT", 3.0, "heartbeat")
                before = emulator.signing(0).verdicts[Verdict.UNSIGNED]
                with pytest.raises(TimeoutError):
                    await stranger.command(
                        1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196, timeout_s=1.0
                    )
                assert emulator.signing(0).verdicts[Verdict.UNSIGNED] > before
            assert emulator.autopilot(0).armed  # the stranger's forced disarm was ignored

            await mavproxy("disarm")
            await emulator.wait_for(lambda: not emulator.autopilot(0).armed, timeout_s=10.0)
            await wait_for_line("DISARMED")
            assert emulator.signing(0).verdicts[Verdict.BAD_SIGNATURE] == 0

            await mavproxy("signing remove my-passphrase")  # a signed blank key
            await emulator.wait_for(lambda: not emulator.signing(0).active, timeout_s=5.0)
        finally:
            process.kill()
            await process.wait()

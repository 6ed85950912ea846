"""Flight logs: one ULog per flight as PX4's logger writes it (read back with pyulog), served as
PX4 serves them over the MAVLink log protocol (pymavlink, MAVSDK's log_files) and FTP."""

from __future__ import annotations

import asyncio
import io
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mavsdk.asyncio.plugins.ftp import FtpAsync
from mavsdk.asyncio.plugins.log_files import LogFilesAsync
from pymavlink.dialects.v20 import common as mavlink

from sitl import Emulator, EmulatorConfig
from sitl.config import ClockConfig, FlightLogConfig
from sitl.flight_log import FlightLog, FlightLogStore, nav_state
from sitl.log_handler import BYTES_PER_PUMP, LOG_DATA_BYTES, LogHandler
from sitl.modes import FlightMode
from sitl.params import PARAM_NAMES
from sitl.ulog import Topic, ULogWriter
from tests.sitl.helpers import Bench, FakeLink, RawClient, free_port_config, roundtrip
from tests.sitl.mavsdk_helpers import api_config, emulated_drones, landed_and_disarmed, take_off

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
Message = mavlink.MAVLink_message


def ulog(data: bytes | bytearray) -> Any:
    """The log as PX4's own reader, pyulog, parses it (the test skips without pyulog)."""
    pyulog = pytest.importorskip("pyulog", reason="pyulog reads the logs (pip install pyulog)")
    return pyulog.ULog(io.BytesIO(bytes(data)))


def fly(bench: Bench, hover_s: float = 3.0) -> None:
    """Arm, take off to MIS_TAKEOFF_ALT, hover, land and wait for the auto-disarm."""
    bench.run(1.0)
    assert bench.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED
    assert bench.command(mavlink.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == ACCEPTED
    bench.run_until(lambda: bench.position()[2] < -2.3, 20, "at take-off altitude")
    bench.run(hover_s)
    assert bench.command(mavlink.MAV_CMD_NAV_LAND) == ACCEPTED
    bench.run_until(lambda: not bench.ap.armed, 60, "landed and disarmed")


# ------------------------------------------------------------------ ULog
def test_ulog_writer_output_is_read_by_pyulog() -> None:
    topic = Topic("vehicle_attitude", (("uint64_t", "timestamp"), ("float[4]", "q")))
    writer = ULogWriter(1_000)
    writer.info("sys_name", "PX4")
    writer.format(topic)
    writer.parameter("MIS_TAKEOFF_ALT", 2.5, integer=False)
    writer.parameter("NAV_DLL_ACT", 2, integer=True)
    writer.subscribe("vehicle_attitude")
    writer.write("vehicle_attitude", (2_000, 1.0, 0.0, 0.0, 0.0))
    writer.log(4, 2_500, "Takeoff detected")
    writer.write("vehicle_attitude", (3_000, 0.0, 1.0, 0.0, 0.0))
    writer.sync()
    log = ulog(writer.data)
    assert log.start_timestamp == 1_000 and log.msg_info_dict["sys_name"] == "PX4"
    assert log.initial_parameters == {"MIS_TAKEOFF_ALT": 2.5, "NAV_DLL_ACT": 2}
    attitude = log.get_dataset("vehicle_attitude").data
    assert list(attitude["timestamp"]) == [2_000, 3_000] and list(attitude["q[1]"]) == [0.0, 1.0]
    (text,) = log.logged_messages
    assert (text.log_level_str(), text.timestamp, text.message) == (
        "WARNING",
        2_500,
        "Takeoff detected",
    )
    with pytest.raises(ValueError, match="timestamp"):
        Topic("bad", (("float", "x"),))


def test_nav_state_is_px4s_for_each_mode() -> None:
    assert nav_state(FlightMode.HOLD.custom_mode) == 4
    assert nav_state(FlightMode.TAKEOFF.custom_mode) == 17
    assert nav_state(FlightMode.LAND.custom_mode) == 18
    assert nav_state(FlightMode.OFFBOARD.custom_mode) == 14
    assert nav_state(FlightMode.MISSION.custom_mode) == 3


# ------------------------------------------------------------------ recording
def test_a_flight_is_one_log_from_arming_to_disarming() -> None:
    bench = Bench(
        flight_logs=FlightLogConfig(rate_hz=10.0), params={"MIS_TAKEOFF_ALT": 2.5, "SDLOG_MODE": 0}
    )
    bench.run(2.0)
    assert bench.ap.flight_logs.logs == []  # SDLOG_MODE 0: nothing before arming
    fly(bench)
    (flight,) = bench.ap.flight_logs.logs
    assert not flight.recording
    assert flight.name == "1970-01-01/00_00_03.ulg"  # UTC of the start (test epoch 0)
    log = ulog(flight.data)
    assert set(log.initial_parameters) == set(PARAM_NAMES)
    local = log.get_dataset("vehicle_local_position").data
    duration_s = (local["timestamp"][-1] - local["timestamp"][0]) / 1e6
    assert len(local["timestamp"]) == pytest.approx(duration_s * 10, abs=2)
    assert local["z"].min() == pytest.approx(-2.5, abs=0.05)
    status = log.get_dataset("vehicle_status").data
    assert status["arming_state"][0] == 2 and status["arming_state"][-1] == 1
    assert {17, 4, 18} <= set(status["nav_state"])  # take-off, hold, land
    accel = log.get_dataset("sensor_combined").data["accelerometer_m_s2[2]"]
    assert np.median(accel) == pytest.approx(-9.80665, abs=0.01)
    texts = [m.message for m in log.logged_messages]
    assert "Takeoff detected" in texts and "Landing detected" in texts
    fly(bench)
    assert len(bench.ap.flight_logs.logs) == 2  # one per flight


@pytest.mark.parametrize(
    ("mode", "logs_before_arming", "recording_after_landing"),
    [(1, 1, False), (2, 1, True), (3, 0, False), (4, 0, True)],
)
def test_sdlog_mode_decides_when_to_log_as_on_px4(
    mode: int, logs_before_arming: int, recording_after_landing: bool
) -> None:
    bench = Bench(flight_logs=FlightLogConfig(), params={"SDLOG_MODE": mode})
    bench.run(0.5)
    assert len(bench.ap.flight_logs.logs) == logs_before_arming
    fly(bench, hover_s=0.5)
    logs = bench.ap.flight_logs.logs
    assert len(logs) == (0 if mode == 3 else 1)  # 3: RC AUX1, and there is no RC
    assert any(log.recording for log in logs) == recording_after_landing


def test_logs_are_bounded_in_number_and_size() -> None:
    bench = Bench(flight_logs=FlightLogConfig(max_logs=2, max_log_bytes=20_000))
    for _ in range(3):
        fly(bench, hover_s=5.0)
    logs = bench.ap.flight_logs.logs
    assert len(logs) == 2
    assert all(20_000 <= log.size < 20_000 + 200 for log in logs)


# ------------------------------------------------------------------ the log protocol
def store_with(*sizes: int) -> FlightLogStore:
    store = FlightLogStore()
    for i, size in enumerate(sizes):
        data = bytearray((i * 7 + k) % 251 for k in range(size))
        store.add(FlightLog(f"2026-12-02/10_00_0{i}.ulg", data, 1_796_000_000 + i))
    return store


def ask(handler: LogHandler, link: FakeLink, msg: Message) -> list[Message]:
    link.clear()
    handler.handle(roundtrip(msg), link)
    return list(link.sent)


def test_list_answers_every_entry_with_px4s_last_log_num() -> None:
    handler, link = LogHandler(store_with(1000, 5000, 300), sysid=1), FakeLink()
    entries = ask(handler, link, mavlink.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF))
    assert [(e.id, e.num_logs, e.last_log_num, e.size) for e in entries] == [
        (0, 3, 3, 1000),  # PX4: last_log_num = number of logs when end is 0xFFFF
        (1, 3, 3, 5000),
        (2, 3, 3, 300),
    ]
    assert entries[1].time_utc == 1_796_000_001
    later = ask(handler, link, mavlink.MAVLink_log_request_list_message(1, 1, 1, 2))
    assert [(e.id, e.last_log_num) for e in later] == [(1, 2), (2, 2)]
    assert ask(handler, link, mavlink.MAVLink_log_request_list_message(2, 1, 0, 0xFFFF)) == []


def test_no_logs_no_answer_as_on_px4() -> None:
    handler, link = LogHandler(FlightLogStore(), sysid=1), FakeLink()
    assert ask(handler, link, mavlink.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF)) == []


def test_data_comes_in_90_byte_packets_for_the_range_asked() -> None:
    store = store_with(1000, 5000)
    handler, link = LogHandler(store, sysid=1), FakeLink()
    request = mavlink.MAVLink_log_request_data_message
    assert ask(handler, link, request(1, 1, 1, 0, 500)) == []  # not listed yet: PX4 ignores it
    ask(handler, link, mavlink.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF))
    packets = ask(handler, link, request(1, 1, 1, 180, 500))
    assert [(p.id, p.ofs, p.count) for p in packets] == [
        (1, 180 + k * LOG_DATA_BYTES, LOG_DATA_BYTES) for k in range(6)
    ]  # 540 bytes: PX4 sends whole packets until the range is covered
    received = b"".join(bytes(p.data[: p.count]) for p in packets)
    assert received == bytes(store.logs[1].data[180:720])
    (short,) = ask(handler, link, request(1, 1, 0, 100, 10))
    assert (short.ofs, short.count) == (100, LOG_DATA_BYTES)
    tail = ask(handler, link, request(1, 1, 0, 950, 0xFFFFFFFF))
    assert [(p.ofs, p.count) for p in tail] == [(950, 50)]  # the end of the file
    assert ask(handler, link, request(1, 1, 0, 1000, 90)) == []  # past the end
    assert ask(handler, link, request(1, 1, 2, 0, 90)) == []  # no such log


def test_a_long_download_goes_on_step_by_step_until_ended() -> None:
    size = 3 * BYTES_PER_PUMP + 1000
    store = store_with(size)
    handler, link = LogHandler(store, sysid=1), FakeLink()
    ask(handler, link, mavlink.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF))
    first = ask(handler, link, mavlink.MAVLink_log_request_data_message(1, 1, 0, 0, 0xFFFFFFFF))
    assert sum(p.count for p in first) == pytest.approx(BYTES_PER_PUMP, abs=LOG_DATA_BYTES)
    received = b"".join(bytes(p.data[: p.count]) for p in first)
    while handler.sending:
        link.clear()
        handler.pump()
        received += b"".join(bytes(p.data[: p.count]) for p in link.sent)
    assert received == bytes(store.logs[0].data)
    ask(handler, link, mavlink.MAVLink_log_request_data_message(1, 1, 0, 0, 0xFFFFFFFF))
    ask(handler, link, mavlink.MAVLink_log_request_end_message(1, 1))
    assert not handler.sending


def test_erase_deletes_every_log() -> None:
    store = store_with(100, 200)
    handler, link = LogHandler(store, sysid=1), FakeLink()
    ask(handler, link, mavlink.MAVLink_log_erase_message(1, 1))
    assert store.logs == []
    assert ask(handler, link, mavlink.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF)) == []


# ------------------------------------------------------------------ real clients
async def nothing_more_before_a_ping(
    client: RawClient, predicate: Callable[[Message], bool]
) -> None:
    """Replies on one link arrive in order: whatever ``predicate`` matches before the answer to
    a PING sent now has arrived by then."""
    client.keep_messages = True
    client.messages.clear()
    with client.matching(lambda m: m.get_type() == "PING" and m.seq == 4242) as pong:
        client.send(mavlink.MAVLink_ping_message(0, 4242, 0, 0))
        await asyncio.wait_for(pong, 3)
    assert not [m for m in client.messages if predicate(m)]


@pytest.mark.asyncio
async def test_pymavlink_lists_downloads_and_erases_over_udp() -> None:
    config = EmulatorConfig(vehicles=1, ports=free_port_config(1), clock=ClockConfig(speed=5.0))
    async with Emulator(config) as emulator, RawClient(config.ports.gcs_remote_port) as gcs:
        await gcs.expect(lambda m: m.get_type() == "HEARTBEAT", 3, "a heartbeat")
        await emulator.run_for(1.2)
        logs = emulator.autopilot(0).flight_logs.logs
        assert await gcs.command(1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == ACCEPTED
        await emulator.wait_for(lambda: bool(logs), timeout_s=3, what="a log once armed")
        await emulator.run_for(1.0)
        assert await gcs.command(1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == ACCEPTED
        (flight,) = logs
        await emulator.wait_for(lambda: not flight.recording, timeout_s=3, what="log closed")
        with gcs.matching(lambda m: m.get_type() == "LOG_ENTRY") as entry_future:
            gcs.send(mavlink.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF))
            entry = await asyncio.wait_for(entry_future, 3)
        assert (entry.id, entry.num_logs, entry.size) == (0, 1, flight.size)
        gcs.keep_messages = True
        with gcs.matching(
            lambda m: m.get_type() == "LOG_DATA" and m.ofs + m.count >= flight.size
        ) as last:
            gcs.send(mavlink.MAVLink_log_request_data_message(1, 1, 0, 0, 0xFFFFFFFF))
            await asyncio.wait_for(last, 3)
        data = sorted(
            (m.ofs, bytes(m.data[: m.count])) for m in gcs.messages if m.get_type() == "LOG_DATA"
        )
        assert b"".join(chunk for _, chunk in data) == bytes(flight.data)
        gcs.send(mavlink.MAVLink_log_erase_message(1, 1))
        gcs.send(mavlink.MAVLink_log_request_list_message(1, 1, 0, 0xFFFF))
        await nothing_more_before_a_ping(gcs, lambda m: m.get_type() == "LOG_ENTRY")
        assert emulator.autopilot(0).flight_logs.logs == []


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_log_files_and_ftp_get_the_flight_log(tmp_path: Path) -> None:
    async with emulated_drones(api_config(speed=4.0)) as (emulator, drones):
        drone = drones[0]
        await take_off(drone)
        await drone.action.land()
        await landed_and_disarmed(drone)
        (flight,) = emulator.autopilot(0).flight_logs.logs
        assert not flight.recording
        log_files = LogFilesAsync(drone.system)
        (entry,) = await log_files.get_entries()
        assert (entry.id, entry.size_bytes) == (0, flight.size)
        assert entry.date.startswith(flight.name[:10])  # the day of the flight, UTC
        target = tmp_path / "flight.ulg"
        async for _ in log_files.download_log_file(entry, str(target)):
            pass
        assert target.read_bytes() == bytes(flight.data)
        log = ulog(target.read_bytes())
        assert log.get_dataset("vehicle_local_position").data["z"].min() < -2.0

        ftp = FtpAsync(drone.system)
        day, file_name = flight.name.split("/")
        (day_entry,) = (await ftp.list_directory("/log")).entries
        assert day_entry.name == day
        (file_entry,) = (await ftp.list_directory(f"/log/{day}")).entries
        assert (file_entry.name, file_entry.size_bytes) == (file_name, flight.size)
        (tmp_path / "ftp").mkdir()
        async for _ in ftp.download(f"/log/{flight.name}", str(tmp_path / "ftp"), True):
            pass
        assert (tmp_path / "ftp" / file_name).read_bytes() == bytes(flight.data)


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_downloads_a_log_from_a_vehicle_that_never_flew(tmp_path: Path) -> None:
    """PX4 SITL logs from boot (its start script sets SDLOG_MODE 1), so MAVSDK's
    logfile_download example finds a log on a fresh vehicle; so does the emulator's."""
    async with emulated_drones(api_config(speed=4.0)) as (emulator, [drone]):
        assert emulator.autopilot(0).params["SDLOG_MODE"] == 1
        await emulator.run_for(2.0)
        log_files = LogFilesAsync(drone.system)
        (entry,) = await log_files.get_entries()
        (booted,) = emulator.autopilot(0).flight_logs.logs
        assert booted.recording and entry.id == 0
        target = tmp_path / "boot.ulg"
        async for _ in log_files.download_log_file(entry, str(target)):
            pass
        data = target.read_bytes()
        assert len(data) == entry.size_bytes and data == bytes(booted.data[: len(data)])
        status = ulog(data).get_dataset("vehicle_status").data
        assert set(status["arming_state"]) == {1}  # standby: never armed

"""Calibration commands answered and narrated as PX4 SITL (SIH) does, measured on the real
binary: stepped synchronously, then with MAVSDK's calibration plugin."""

from __future__ import annotations

import math

import pytest
from mavsdk.asyncio.plugins.calibration import CalibrationAsync, CalibrationError
from mavsdk.asyncio.plugins.calibration import CalibrationResult as Result
from pymavlink.dialects.v20 import common as mavlink
from pymavlink.dialects.v20.common import MAV_RESULT_ACCEPTED as ACCEPTED
from pymavlink.dialects.v20.common import MAV_RESULT_DENIED as DENIED
from pymavlink.dialects.v20.common import MAV_RESULT_TEMPORARILY_REJECTED as TEMPORARILY_REJECTED
from pymavlink.dialects.v20.common import MAV_RESULT_UNSUPPORTED as UNSUPPORTED

from tests.sitl.helpers import Bench
from tests.sitl.mavsdk_helpers import api_config, emulated_drones, healthy

CALIBRATE = mavlink.MAV_CMD_PREFLIGHT_CALIBRATION
NAN = math.nan


def calibrate(bench: Bench, *params: float) -> int | None:
    """PREFLIGHT_CALIBRATION with params 1-7 (MAVSDK leaves 6 and 7 NaN)."""
    return bench.command(CALIBRATE, *params, *[NAN] * (7 - len(params)))


def texts_after(bench: Bench, seconds: float) -> list[str]:
    before = len(bench.texts())
    bench.run(seconds)
    return bench.texts()[before:]


def test_gyro_calibration_reports_progress_then_done() -> None:
    bench = Bench()
    assert calibrate(bench, 1, 0, 0, 0, 0) == ACCEPTED
    assert bench.texts() == ["[cal] calibration started: 2 gyro"]
    assert bench.ap.telemetry.heartbeat(bench.t).system_status == mavlink.MAV_STATE_CALIBRATING
    assert bench.command(400, 1) == TEMPORARILY_REJECTED
    assert bench.texts()[-1] == "Arming denied: calibrating"
    said = texts_after(bench, 1.1)
    assert said == [f"[cal] progress <{p}>" for p in range(0, 101, 10)] + [
        "[cal] calibration done: gyro"
    ]
    assert not bench.ap.calibrating
    assert bench.ap.telemetry.heartbeat(bench.t).system_status == mavlink.MAV_STATE_STANDBY


def test_level_and_barometer_finish_the_rest_needs_a_vehicle_turned_over() -> None:
    bench = Bench()
    assert calibrate(bench, 0, 0, 0, 0, 2) == ACCEPTED
    assert texts_after(bench, 0.7)[-1] == "[cal] calibration done: level"
    assert calibrate(bench, 0, 0, 1, 0, 0) == ACCEPTED
    assert texts_after(bench, 3.1)[-1] == "[cal] calibration done: baro"
    assert calibrate(bench, 0, 0, 0, 0, 1) == ACCEPTED
    said = texts_after(bench, 26.3)
    assert "[cal] down side done, rotate to a different side" in said
    assert said[-1] == "[cal] down side already completed"
    assert texts_after(bench, 0.2) == [
        "[cal] calibration failed: timeout: no motion",
        "[cal] calibration failed: accel",
    ]
    assert calibrate(bench, 0, 1, 0, 0, 0) == ACCEPTED
    said = texts_after(bench, 45.1)
    assert "[cal] Rotate vehicle" in said and said[-1] == "[cal] calibration failed: mag"


def test_a_running_calibration_is_cancelled_by_all_zeros_and_denies_others() -> None:
    bench = Bench()
    assert calibrate(bench, 0, 1, 0, 0, 0) == ACCEPTED
    bench.run(3.0)
    assert calibrate(bench, 1, 0, 0, 0, 0) == DENIED
    assert bench.texts()[-1] == "command denied during calibration: 241"
    assert calibrate(bench, 0, 0, 0, 0, 0, 0, 0) == ACCEPTED
    assert texts_after(bench, 0.2) == ["[cal] calibration cancelled"]  # after the ACK
    assert not bench.ap.calibrating
    assert texts_after(bench, 50.0) == []


def test_calibration_answers_that_need_no_worker() -> None:
    bench = Bench()
    assert calibrate(bench, 0, 0, 0, 0, 0, 0, 1) == DENIED  # ESC: battery not disconnected
    assert bench.texts()[-1] == "[cal] calibration failed: Disconnect battery and try again"
    assert bench.link.of_type("STATUSTEXT")[-1].chunk_seq == 1  # 57 bytes: two chunks
    assert calibrate(bench, 3, 0, 0, 0, 0) == UNSUPPORTED  # temperature: PX4 SITL is silent
    assert calibrate(bench, 0, 0, 0, 1, 0) == ACCEPTED
    assert bench.texts()[-1] == "Calibration: Disabling RC input"
    assert bench.ap.calibrating
    assert calibrate(bench, 0, 0, 0, 0, 0) == ACCEPTED
    assert bench.texts()[-1] == "Calibration: Restoring RC input"
    assert calibrate(bench, 0, 0, 0, 2, 0) == ACCEPTED
    assert texts_after(bench, 0.5) == ["trim cal done"]
    assert calibrate(bench, 0, 0, 0, 0, 4) == ACCEPTED  # quick accelerometer: nothing said
    assert texts_after(bench, 0.5) == []
    assert calibrate(bench, 0, 0, 0, 0, 0, 1) == ACCEPTED  # airspeed: no sensor on a quad
    assert texts_after(bench, 35.1) == [
        "[cal] Ensure sensor is not measuring wind",
        "[cal] calibration failed: airspeed",
    ]
    assert calibrate(bench, 0, 0, 0, 5, 0) == UNSUPPORTED
    assert calibrate(bench, 7, 0, 0, 0, 0) == ACCEPTED  # PX4: p4 = 0 ends an RC calibration
    assert bench.command(mavlink.MAV_CMD_FIXED_MAG_CAL_YAW, 90.4, 0, 47.4, 8.5) == ACCEPTED
    assert bench.texts()[-1] == "Assuming vehicle is facing heading 90.0 degrees"
    assert texts_after(bench, 0.1) == ["Mag quick calibration finished"]


def test_calibration_is_refused_while_armed_or_busy() -> None:
    bench = Bench()
    bench.airborne()
    assert calibrate(bench, 1, 0, 0, 0, 0) == TEMPORARILY_REJECTED
    assert bench.command(mavlink.MAV_CMD_FIXED_MAG_CAL_YAW, 0) == TEMPORARILY_REJECTED
    bench = Bench()
    assert calibrate(bench, 0, 0, 1, 0, 0) == ACCEPTED  # barometer: no cancel check in PX4
    assert calibrate(bench, 0, 0, 0, 0, 0, 0, 0) == TEMPORARILY_REJECTED


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_calibration_plugin() -> None:
    async with emulated_drones(api_config(speed=10.0)) as (emulator, [drone]):
        # Until MAVSDK has seen enough of the vehicle to know it is PX4, its calibration plugin
        # answers UNSUPPORTED at once (PX4 SITL likewise): health is a later sign of that.
        await healthy(drone)
        calibration = CalibrationAsync(drone.system)
        updates = [(result, data) async for result, data in calibration.calibrate_gyro()]
        assert updates[-1][0] == Result.SUCCESS
        progress = [data.progress for _, data in updates if data.has_progress]
        assert progress == sorted(progress) and progress[-1] == pytest.approx(1.0)
        results = [result async for result, _ in calibration.calibrate_level_horizon()]
        assert results[-1] == Result.SUCCESS

        with pytest.raises(CalibrationError) as cancelled:
            async for _, data in calibration.calibrate_magnetometer():
                if data.has_status_text and data.status_text == "Rotate vehicle":
                    await calibration.cancel()
        assert cancelled.value.result == Result.CANCELLED

        # Last: MAVSDK gives up at the first of PX4's two "failed" texts, and a calibration
        # started before the second would take it for its own (with real PX4 as well).
        instructions: list[str] = []
        with pytest.raises(CalibrationError) as failed:
            async for _, data in calibration.calibrate_accelerometer():
                if data.has_status_text:
                    instructions.append(data.status_text)
        assert failed.value.result == Result.FAILED
        assert "down side done, rotate to a different side" in instructions
        await emulator.wait_for(lambda: not emulator.autopilot(0).calibrating, timeout_s=2)
        assert not emulator.autopilot(0).calibrating

"""The link's MAVLink numbers, kept as literals so a vehicle process need not import pymavlink's
dialect, are pymavlink's own."""

from __future__ import annotations

import subprocess
import sys

from pymavlink.dialects.v20 import common

from mission_runner.runner import mavlink_ids


def test_every_number_is_pymavlinks() -> None:
    names = [name for name in vars(mavlink_ids) if name.isupper()]
    assert len(names) >= 30
    for name in names:
        assert getattr(mavlink_ids, name) == getattr(common, name), name


def test_a_refusal_is_named_and_an_unknown_result_numbered() -> None:
    assert mavlink_ids.result_name(common.MAV_RESULT_DENIED) == "MAV_RESULT_DENIED"
    assert mavlink_ids.result_name(250) == "250"


def test_the_vehicle_process_does_not_import_pymavlink() -> None:
    code = "import sys, mission_runner.runner.process; print('pymavlink' in sys.modules)"
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert result.stdout.strip() == "False"

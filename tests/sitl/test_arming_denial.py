"""Arm commands refused the way PX4 refuses them when a health check fails after clients saw the
vehicle healthy: COMMAND_ACK TEMPORARILY_REJECTED plus PX4's CRITICAL STATUSTEXT, on every
retransmission, then arming works again. State machine first, then real MAVSDK over UDP."""

from __future__ import annotations

import asyncio

import pytest
from mavsdk.asyncio.plugins.action import ActionError, ActionResult
from mavsdk.asyncio.plugins.telemetry import StatusTextType
from pydantic import ValidationError
from pymavlink.dialects.v20.common import MAV_RESULT_ACCEPTED as ACCEPTED
from pymavlink.dialects.v20.common import MAV_RESULT_TEMPORARILY_REJECTED as TEMPORARILY_REJECTED
from pymavlink.dialects.v20.common import MAV_SEVERITY_CRITICAL as CRITICAL

from sitl import Emulator, EmulatorConfig
from sitl.config import PX4_ARMING_DENIED_TEXT, ClockConfig, DenyArmingFault
from sitl.errors import EmulatorStateError
from tests.sitl.helpers import Bench, free_port_config
from tests.sitl.mavsdk_helpers import first, healthy, mavsdk_connected

ARM = 400
FORCE = 21196


def refusal_texts(bench: Bench) -> list[tuple[int, int, int, bytes]]:
    """(severity, id, chunk_seq, text) of the STATUSTEXTs sent since the last clear."""
    return [
        (m.severity, m.id, m.chunk_seq, m.text.encode() if isinstance(m.text, str) else m.text)
        for m in bench.link.of_type("STATUSTEXT")
    ]


def test_a_refused_arm_is_answered_like_px4() -> None:
    bench = Bench()
    bench.ap.deny_arming(1, PX4_ARMING_DENIED_TEXT, retry_window_s=2.0)
    assert bench.command(ARM, 1) == TEMPORARILY_REJECTED
    assert not bench.ap.armed
    # PX4 appends a tab (its events marker) and splits the 52 bytes into two chunks of one id.
    sent = PX4_ARMING_DENIED_TEXT + "\t"
    texts = refusal_texts(bench)
    assert [(sev, seq) for sev, _, seq, _ in texts] == [(CRITICAL, 0), (CRITICAL, 1)]
    assert texts[0][1] == texts[1][1] != 0
    assert b"".join(text.rstrip(b"\0") for *_, text in texts).decode() == sent
    assert bench.texts()[-1] == PX4_ARMING_DENIED_TEXT
    assert bench.ap.arm_refusals_pending == 0


def test_retransmissions_get_the_same_answer_then_the_next_attempt_arms() -> None:
    bench = Bench()
    bench.ap.deny_arming(1, "Arming denied: battery low", retry_window_s=2.0)
    assert bench.command(ARM, 1) == TEMPORARILY_REJECTED
    for _ in range(3):  # MAVSDK resends 0.5 s apart when an ACK goes missing
        bench.run(0.5)
        bench.link.clear()
        assert bench.command(ARM, 1) == TEMPORARILY_REJECTED
        assert refusal_texts(bench) == [(CRITICAL, 0, 0, b"Arming denied: battery low\t")]
    bench.run(0.6)  # past the attempt's window: a new attempt, and no refusal is left
    assert bench.command(ARM, 1) == ACCEPTED
    assert bench.ap.armed


def test_count_attempts_from_any_client_are_refused_and_force_does_not_help() -> None:
    bench = Bench()
    bench.ap.deny_arming(3, PX4_ARMING_DENIED_TEXT, retry_window_s=2.0)
    assert bench.command(ARM, 1) == TEMPORARILY_REJECTED
    # Another client (or a forced arm) is another attempt; PX4 checks forced arms from MAVLink.
    assert bench.command(ARM, 1, src=(254, 190)) == TEMPORARILY_REJECTED
    assert bench.command(ARM, 1, FORCE) == TEMPORARILY_REJECTED
    assert bench.ap.arm_refusals_pending == 0
    bench.run(2.1)
    assert bench.command(ARM, 1, FORCE) == ACCEPTED
    # Already armed: PX4 answers ACCEPTED without running its checks, nothing is used up.
    bench.ap.deny_arming(1, PX4_ARMING_DENIED_TEXT, retry_window_s=0.0)
    assert bench.command(ARM, 1) == ACCEPTED
    assert bench.ap.arm_refusals_pending == 1


def test_without_a_window_every_arm_command_counts() -> None:
    bench = Bench()
    bench.ap.deny_arming(2, PX4_ARMING_DENIED_TEXT, retry_window_s=0.0)
    assert [bench.command(ARM, 1) for _ in range(3)] == [
        TEMPORARILY_REJECTED,
        TEMPORARILY_REJECTED,
        ACCEPTED,
    ]


def test_preflight_refusals_come_first_and_use_up_nothing() -> None:
    bench = Bench(ready_after_s=1.0)
    bench.ap.deny_arming(1, PX4_ARMING_DENIED_TEXT, retry_window_s=0.0)
    assert bench.command(ARM, 1) == TEMPORARILY_REJECTED
    assert bench.texts()[-1] == "Arming denied: estimator not ready"
    assert bench.ap.arm_refusals_pending == 1


def test_the_fault_in_settings() -> None:
    fault = EmulatorConfig.model_validate(
        {"vehicles": 2, "faults": [{"kind": "deny_arming", "vehicle_index": 1}]}
    ).faults[0]
    assert isinstance(fault, DenyArmingFault)
    assert (fault.count, fault.reason, fault.at_s) == (1, PX4_ARMING_DENIED_TEXT, 0.0)
    with pytest.raises(ValidationError):
        DenyArmingFault(kind="deny_arming", vehicle_index=0, count=0)
    with pytest.raises(ValidationError, match="only 1 vehicle"):
        EmulatorConfig.model_validate({"faults": [{"kind": "deny_arming", "vehicle_index": 1}]})


@pytest.mark.asyncio
async def test_scheduled_refusals_start_at_their_time() -> None:
    cfg = EmulatorConfig(
        vehicles=2,
        ports=free_port_config(2, gcs=False),
        clock=ClockConfig(mode="lockstep"),
        faults=[{"kind": "deny_arming", "vehicle_index": 1, "at_s": 1.0, "count": 2}],  # type: ignore[list-item]
    )
    async with Emulator(cfg) as emulator:
        assert emulator.autopilot(1).arm_refusals_pending == 0
        await emulator.run_for(1.1)
        assert emulator.autopilot(1).arm_refusals_pending == 2
        assert emulator.autopilot(0).arm_refusals_pending == 0
        assert [(i, what) for _, i, what in emulator.events] == [
            (1, f"arming denied x2: {PX4_ARMING_DENIED_TEXT}")
        ]
        with pytest.raises(EmulatorStateError):
            emulator.deny_arming(5)
        with pytest.raises(ValueError, match="count"):
            emulator.deny_arming(0, count=0)


@pytest.mark.mavsdk
@pytest.mark.asyncio
async def test_mavsdk_arm_raises_the_denial_shows_the_text_and_the_next_arm_works() -> None:
    cfg = EmulatorConfig(
        vehicles=1, ports=free_port_config(1, gcs=False), clock=ClockConfig(speed=5.0)
    )
    async with (
        Emulator(cfg) as emulator,
        mavsdk_connected([emulator.endpoints[0].mavsdk_url], 1) as (_, drones, _),
    ):
        drone = drones[0]
        await healthy(drone)  # what a client checks before arming: PX4 can still refuse
        emulator.deny_arming(0)
        status_text = asyncio.create_task(
            first(
                drone.telemetry.subscribe_status_text(),
                lambda s: s.text.startswith("Arming denied"),
                10,
                "the arming refusal",
            )
        )
        await asyncio.sleep(0)  # the subscription registers when the task first runs
        with pytest.raises(ActionError) as refused:
            await drone.action.arm()
        assert refused.value.result == ActionResult.COMMAND_DENIED
        text = await status_text
        assert text.type is StatusTextType.CRITICAL
        assert text.text.rstrip("\t") == PX4_ARMING_DENIED_TEXT
        assert not emulator.vehicle_status(0).armed
        await emulator.run_for(2.5)  # past the retransmission window of the refused attempt
        await drone.action.arm()
        assert emulator.vehicle_status(0).armed

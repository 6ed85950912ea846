"""The MAVLink shell (SERIAL_CONTROL): PX4's texts for a few nsh commands, the SERIAL_CONTROL
exchange, then real clients over UDP (pymavlink as PX4's Tools/mavlink_shell.py drives it, the
MAVSDK shell plugin, and that very script when PX4_SITL_DIR points to a PX4 tree)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from mavsdk.asyncio import System
from mavsdk.asyncio.plugins.shell import Device, ShellAsync
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from sitl.config import EmulatorConfig
from sitl.emulator import Emulator
from sitl.modes import FlightMode
from sitl.params import PARAM_NAMES
from sitl.shell import PROMPT, SerialControl, targets
from tests.sitl.helpers import Bench, FakeLink, free_port_config, roundtrip
from tests.sitl.mavsdk_helpers import mavsdk_connected

RESPOND = mavlink.SERIAL_CONTROL_FLAG_RESPOND | mavlink.SERIAL_CONTROL_FLAG_EXCLUSIVE
N = len(PARAM_NAMES)
TAKEOFF_INDEX = PARAM_NAMES.index("MIS_TAKEOFF_ALT")


def replies(link: FakeLink) -> list[mavlink.MAVLink_message]:
    """The SERIAL_CONTROL replies on ``link`` as a client decodes them (taken off ``link``)."""
    encoder = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    decoder = mavlink.MAVLink(None)
    found = [
        decoder.parse_buffer(m.pack(encoder))[0]
        for m in link.sent
        if m.get_type() == "SERIAL_CONTROL"
    ]
    link.sent[:] = [m for m in link.sent if m.get_type() != "SERIAL_CONTROL"]
    return found


def type_in(
    bench: Bench,
    text: str,
    *,
    flags: int = RESPOND,
    link: FakeLink | None = None,
    target: tuple[int, int] = (1, 1),
    device: int = mavlink.SERIAL_CONTROL_DEV_SHELL,
) -> str:
    """Send ``text`` to the shell (in 70-byte SERIAL_CONTROLs, as clients do); what it printed."""
    link = link or bench.link
    data = text.encode()
    for start in range(0, max(len(data), 1), 70):
        msg = roundtrip(SerialControl(data[start : start + 70], flags, *target, device=device))
        bench.ap.handle_message(msg, link, bench.t)
    return b"".join(bytes(r.data[: r.count]) for r in replies(link)).decode()


def run(bench: Bench, line: str) -> str:
    """The output of one command line, without PX4's echo of the line and the prompt."""
    out = type_in(bench, line + "\n")
    echo = line + "\n"
    assert out.startswith(echo) and out.endswith(PROMPT), out
    return out[len(echo) : -len(PROMPT)]


# ----------------------------------------------------------------- texts as PX4 prints them
def test_the_shell_greets_with_pxhs_prompt_and_ignores_an_empty_line() -> None:
    bench = Bench()
    assert type_in(bench, "\n") == "\n" + PROMPT  # what PX4 SITL answers the first newline
    assert run(bench, "   ") == ""
    assert run(bench, "# a comment") == ""


def test_param_show_prints_px4s_table() -> None:
    bench = Bench()
    assert run(bench, "param show MIS_TAKEOFF_ALT") == (
        "Symbols: x = used, + = saved, * = unsaved\n"
        f"x   MIS_TAKEOFF_ALT [{TAKEOFF_INDEX},{TAKEOFF_INDEX}] : 2.5000\n"
        "\n"
        f" {N}/{N} parameters used.\n"
    )
    listed = run(bench, "param show mpc_xy*")  # case-insensitive, wildcard at the end
    names = [line.split()[1] for line in listed.splitlines()[1:] if line.startswith("x")]
    assert names == sorted(name for name in bench.ap.params if name.startswith("MPC_XY"))
    assert {"MPC_XY_CRUISE", "MPC_XY_VEL_MAX"} <= set(names)
    assert run(bench, "param show MIS") == (  # no wildcard: the whole name must match
        f"Symbols: x = used, + = saved, * = unsaved\n\n {N}/{N} parameters used.\n"
    )
    assert "* symbol only allowed at end of search string" in run(bench, "param show M*X")
    assert "NAV_DLL_ACT [" in run(bench, "param show NAV_DLL_ACT")
    assert run(bench, "param show NAV_DLL_ACT").splitlines()[1].endswith(" : 0")  # an INT32
    assert run(bench, "param show -q MPC_XY_VEL_MAX") == "12.0000\n"
    assert run(bench, "param show -a").endswith(f"\n {N} parameters total, {N} used.\n")
    assert len(run(bench, "param show").splitlines()) == N + 3


def test_param_set_changes_announces_and_prints_like_px4() -> None:
    bench = Bench()
    assert run(bench, "param set MIS_TAKEOFF_ALT 7.5") == (
        "  MIS_TAKEOFF_ALT: curr: 2.5000 -> new: 7.5000\n"
    )
    assert bench.ap.params["MIS_TAKEOFF_ALT"] == 7.5
    bench.link.clear()
    type_in(bench, "param set NAV_DLL_ACT 2\n")
    announced = bench.link.of_type("PARAM_VALUE")
    assert [m.param_id for m in announced] == ["NAV_DLL_ACT"]  # as PX4 announces changes
    bench.link.clear()
    assert bench.ap.params["NAV_DLL_ACT"] == 2
    # A changed value shows "+" (saved; PX4 saves every change at once).
    assert run(bench, "param show MIS_TAKEOFF_ALT").splitlines()[1].startswith("x + ")
    assert run(bench, "param set MIS_TAKEOFF_ALT 3") == (
        "+ MIS_TAKEOFF_ALT: curr: 7.5000 -> new: 3.0000\n"
    )
    assert run(bench, "param set MIS_TAKEOFF_ALT 3.0") == ""  # unchanged: PX4 says nothing
    assert run(bench, "param set NAV_DLL_ACT 1.9") == "+ NAV_DLL_ACT: curr: 2 -> new: 1\n"


def test_param_set_failures_read_as_px4s() -> None:
    bench = Bench()
    assert run(bench, "param set NOPE_PARAM 1") == "ERROR [param] Parameter NOPE_PARAM not found.\n"
    assert run(bench, "param set NOPE_PARAM 1 fail") == (
        "ERROR [param] Parameter NOPE_PARAM not found.\nCommand 'param' failed, returned 1.\n"
    )
    assert run(bench, "param set MIS_TAKEOFF_ALT") == (
        "ERROR [param] not enough arguments.\n"
        "Try 'param set MIS_TAKEOFF_ALT 3 [fail]'\n"
        "Command 'param' failed, returned 1.\n"
    )
    out = run(
        bench, "param set MIS_TAKEOFF_ALT 500"
    )  # PX4 would store it; here it is range-checked
    assert out.startswith("ERROR [param] MIS_TAKEOFF_ALT must be within")
    assert out.endswith("Command 'param' failed, returned 1.\n")
    assert "read-only" in run(bench, "param set MAV_SYS_ID 7")
    assert bench.ap.params["MIS_TAKEOFF_ALT"] == 2.5 and bench.ap.params["MAV_SYS_ID"] == 1
    usage = run(bench, "param")
    assert "Usage: param <command> [arguments...]" in usage
    assert usage.endswith("Command 'param' failed, returned 1.\n")
    assert "not emulated" in run(bench, "param save")


def test_commander_status_follows_the_vehicle() -> None:
    bench = Bench()
    assert run(bench, "commander status") == (
        "INFO  [commander] Disarmed\n"
        "INFO  [commander] prearm safety: Off\n"
        "INFO  [commander] navigation mode: Hold\n"
        "INFO  [commander] user intended navigation mode: Hold\n"
        "INFO  [commander] in failsafe: no\n"
    )
    assert bench.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    assert bench.command(mavlink.MAV_CMD_NAV_TAKEOFF) == 0
    status = run(bench, "commander status")
    assert "INFO  [commander] Armed\n" in status
    assert "navigation mode: Takeoff\n" in status
    bench.ap._state.mode = FlightMode.RTL
    bench.ap._state.failsafe_active = True
    status = run(bench, "commander status")
    assert "navigation mode: Return\n" in status and "in failsafe: yes\n" in status
    assert run(bench, "commander foo").startswith("INFO  [commander] unknown command\n")
    assert run(bench, "commander arm").endswith("Command 'commander' failed, returned 1.\n")


def test_ver_prints_px4s_fields() -> None:
    bench = Bench()
    lines = run(bench, "ver all").splitlines()
    assert [line.split(":")[0] for line in lines] == [
        "HW arch",
        "PX4 git-hash",
        "PX4 version",
        "OS",
        "OS version",
        "Build datetime",
        "Build uri",
        "Build variant",
        "Toolchain",
        "PX4GUID",
        "UNKNOWN MCU",
    ]
    assert "PX4 version: Release 1.15.0 (17760511)" in lines  # what AUTOPILOT_VERSION says
    assert run(bench, "ver hw") == "HW arch: PX4_SITL\n"
    assert run(bench, "ver").startswith("Error, not enough parameters.\n")
    assert run(bench, "ver foo") == (
        "ERROR [ver] unknown command\nCommand 'ver' failed, returned 1.\n"
    )


def test_help_and_unknown_commands() -> None:
    bench = Bench()
    assert run(bench, "help") == ("Builtin Commands:\n  commander\n  failure\n  param\n  ver\n")
    assert run(bench, "reboot") == "Invalid command: reboot\ntype 'help' for a list of commands\n"


# -------------------------------------------------------------------- the SERIAL_CONTROL side
def test_output_comes_in_70_byte_replies_addressed_to_the_requester() -> None:
    bench = Bench()
    msg = roundtrip(SerialControl(b"param show\n", RESPOND, 1, 1), src_system=42, src_component=7)
    bench.ap.handle_message(msg, bench.link, bench.t)
    chunks = replies(bench.link)
    assert len(chunks) > 10
    assert all(c.flags == mavlink.SERIAL_CONTROL_FLAG_REPLY for c in chunks)
    assert all(c.device == mavlink.SERIAL_CONTROL_DEV_SHELL for c in chunks)
    assert all(c.count == 70 for c in chunks[:-1]) and 0 < chunks[-1].count <= 70
    assert {targets(c) for c in chunks} == {(42, 7)}  # the extension fields, as PX4 fills them
    text = b"".join(bytes(c.data[: c.count]) for c in chunks).decode()
    assert text.startswith("param show\nSymbols") and text.endswith(PROMPT)


def test_a_line_may_arrive_in_pieces_and_each_piece_is_echoed() -> None:
    bench = Bench()
    assert type_in(bench, "param sh") == "param sh"
    out = type_in(bench, "ow MIS_TAKEOFF_ALT\n")
    assert out.startswith("ow MIS_TAKEOFF_ALT\nSymbols") and out.endswith(PROMPT)
    long_line = "param show " + "X" * 80 + "\n"  # more than one SERIAL_CONTROL
    assert run(bench, long_line.strip()).endswith(f" {N}/{N} parameters used.\n")


def test_without_respond_the_shell_closes_and_says_nothing() -> None:
    bench = Bench()
    shell = bench.ap._receiver.shell
    assert type_in(bench, "param set MIS_TAKEOFF_ALT 5\n", flags=0) == ""
    assert bench.ap.params["MIS_TAKEOFF_ALT"] == 5.0  # the line was read before it closed
    assert shell.open_sessions == []
    type_in(bench, "param set MIS", flags=0)  # a half line dies with its shell
    out = type_in(bench, "_TAKEOFF_ALT 6\n")
    assert "Invalid command: _TAKEOFF_ALT" in out
    assert shell.open_sessions == ["api"]


def test_replies_other_devices_and_other_vehicles_are_ignored() -> None:
    bench = Bench()
    reply_flag = mavlink.SERIAL_CONTROL_FLAG_REPLY | RESPOND
    assert type_in(bench, "help\n", flags=reply_flag) == ""
    assert type_in(bench, "help\n", device=mavlink.SERIAL_CONTROL_DEV_TELEM1) == ""
    assert type_in(bench, "help\n", target=(2, 1)) == ""
    assert type_in(bench, "help\n", target=(1, 154)) == ""
    assert type_in(bench, "\n", target=(0, 0)) == "\n" + PROMPT  # no target: PX4 takes it


def test_each_link_has_its_own_shell() -> None:
    bench = Bench()
    gcs = FakeLink("gcs")
    type_in(bench, "param show MIS", link=gcs)
    assert type_in(bench, "help\n").startswith("help\nBuiltin Commands:")
    assert type_in(bench, "_TAKEOFF_ALT\n", link=gcs).startswith("_TAKEOFF_ALT\nSymbols")


# ------------------------------------------------------------------------ real clients, UDP
def mavlink_shell_session(port: int, lines: list[str]) -> str:
    """What PX4's Tools/mavlink_shell.py does, with pymavlink: SERIAL_CONTROL to device 10
    with EXCLUSIVE|RESPOND, a first newline to start the shell, and a close (flags 0) at the
    end. Returns everything the shell printed."""
    conn = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{port}", source_system=255, source_component=190
    )
    received = ""

    def write(text: str) -> None:
        data = text.encode()
        for start in range(0, len(data), 70):
            chunk = list(data[start : start + 70])
            padded = chunk + [0] * (70 - len(chunk))
            conn.mav.serial_control_send(10, RESPOND, 0, 0, len(chunk), padded)

    def read_until_prompts(count: int) -> None:
        nonlocal received
        deadline = time.monotonic() + 5.0
        while received.count(PROMPT) < count:
            msg = conn.recv_match(type="SERIAL_CONTROL", blocking=True, timeout=0.5)
            if msg is not None:
                received += bytes(msg.data[: msg.count]).decode()
            if time.monotonic() > deadline:
                raise AssertionError(f"no prompt #{count} in {received!r}")

    try:
        if conn.wait_heartbeat(timeout=5) is None:
            raise AssertionError("no heartbeat from the vehicle")
        write("\n")
        read_until_prompts(1)
        for i, line in enumerate(lines, start=2):
            write(line + "\n")
            read_until_prompts(i)
        conn.mav.serial_control_send(10, 0, 0, 0, 0, [0] * 70)  # close, as the script does
        return received
    finally:
        conn.close()


@contextlib.asynccontextmanager
async def one_vehicle() -> AsyncIterator[tuple[Emulator, int]]:
    ports = free_port_config(1)
    async with Emulator(EmulatorConfig(vehicles=1, ports=ports)) as emulator:
        yield emulator, ports.gcs_remote_port


@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_a_pymavlink_shell_client_like_px4s_tools_script() -> None:
    async with one_vehicle() as (emulator, gcs_port):
        text = await asyncio.to_thread(
            mavlink_shell_session,
            gcs_port,
            ["param set MIS_TAKEOFF_ALT 4.5", "commander status", "ver hw", "nonsense"],
        )
        await emulator.wait_for(
            lambda: emulator.autopilot(0)._receiver.shell.open_sessions == [],
            timeout_s=3.0,
            what="the shell closed",
        )
        assert emulator.autopilot(0).params["MIS_TAKEOFF_ALT"] == 4.5
    assert text.startswith("\npxh> param set MIS_TAKEOFF_ALT 4.5\n")
    assert "  MIS_TAKEOFF_ALT: curr: 2.5000 -> new: 4.5000\npxh> " in text
    assert "INFO  [commander] navigation mode: Hold\n" in text
    assert "ver hw\nHW arch: PX4_SITL\npxh> " in text
    assert "Invalid command: nonsense\n" in text


class MavsdkShellReader:
    """Collects what MAVSDK's shell plugin receives (subscribed before anything is sent, as
    the plugin requires); :meth:`command` sends a line and waits for its prompt."""

    def __init__(self, shell: ShellAsync) -> None:
        self.shell = shell
        self.text = ""
        self._changed = asyncio.Event()

    async def collect(self) -> None:
        async for received in self.shell.subscribe_receive():
            self.text += received.data
            self._changed.set()

    async def wait_subscribed(self, timeout_s: float = 5.0) -> None:
        """``ver hw`` until its prompt comes back: the gRPC subscription is set up some loop
        iterations after ``collect`` starts, and output sent before it is lost (MAVSDK
        sends no empty line)."""
        async with asyncio.timeout(timeout_s):
            while PROMPT not in self.text:
                with contextlib.suppress(TimeoutError):
                    await self.command("ver hw", timeout_s=0.2)

    async def command(self, line: str, timeout_s: float = 5.0) -> str:
        start = len(self.text)
        await self.shell.send(line, Device.SHELL)
        async with asyncio.timeout(timeout_s):
            while PROMPT not in self.text[start:]:
                self._changed.clear()
                await self._changed.wait()
        return self.text[start:]


@contextlib.asynccontextmanager
async def mavsdk_shell(system: System) -> AsyncIterator[MavsdkShellReader]:
    # MAVSDK can list the autopilot (from any of its messages) before its first HEARTBEAT
    # makes it "connected"; until then the shell plugin refuses to send (NO_SYSTEM).
    async with asyncio.timeout(5.0):
        while not await system.is_connected():
            await asyncio.sleep(0.05)
    reader = MavsdkShellReader(ShellAsync(system))
    async with asyncio.TaskGroup() as group:
        collector = group.create_task(reader.collect(), name="mavsdk-shell-receive")
        await reader.wait_subscribed()
        try:
            yield reader
        finally:
            collector.cancel()  # the subscription has no end of its own


@pytest.mark.mavsdk
@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_mavsdk_shell_plugin_runs_commands() -> None:
    async with (
        one_vehicle() as (emulator, _),
        mavsdk_connected([emulator.endpoints[0].mavsdk_url], 1) as (_, drones, _),
        mavsdk_shell(drones[0].system) as shell,
    ):
        out = await shell.command("param show MPC_XY*")
        assert "x   MPC_XY_CRUISE [" in out and "x   MPC_XY_VEL_MAX [" in out
        assert out.endswith(PROMPT)
        out = await shell.command("param set MPC_XY_VEL_MAX 8")
        assert "  MPC_XY_VEL_MAX: curr: 12.0000 -> new: 8.0000\n" in out
        assert await drones[0].param.get_param_float("MPC_XY_VEL_MAX") == 8.0
        out = await shell.command("commander status")
        assert "INFO  [commander] Disarmed\n" in out


def px4_mavlink_shell_script() -> Path | None:
    location = os.environ.get("PX4_SITL_DIR")
    if not location:
        return None
    for base in (Path(location), *Path(location).parents):
        script = base / "Tools" / "mavlink_shell.py"
        if script.is_file():
            return script
    return None


@pytest.mark.px4
@pytest.mark.asyncio
@pytest.mark.timeout(60)
async def test_px4s_own_mavlink_shell_script() -> None:
    script = px4_mavlink_shell_script()
    if script is None:
        pytest.skip("set PX4_SITL_DIR to a PX4 tree to run its Tools/mavlink_shell.py")
    async with one_vehicle() as (_, gcs_port):
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            str(script),
            f"udpin:127.0.0.1:{gcs_port}",
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        # It reads stdin to the end, sends each line, and prints replies for 1 s more.
        out, _ = await asyncio.wait_for(
            process.communicate(b"ver hw\nparam show MIS_TAKEOFF_ALT\n"), timeout=30
        )
    text = out.decode(errors="replace")
    assert "HW arch: PX4_SITL" in text
    assert "x   MIS_TAKEOFF_ALT [" in text and ": 2.5000" in text

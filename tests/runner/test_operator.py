"""The operator's vocabulary and typed commands: one parser for ``control`` and the lines typed
into ``ground`` and ``run``; the console sends what parses, says what is wrong in one line, and
its input ending (stdin at EOF or /dev/null) ends only the console."""

import asyncio
import contextlib
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from mission_runner.bus import BusConnectionError, ControlCommand
from mission_runner.cli.parser import build_parser
from mission_runner.runner.operator import (
    HELP,
    OPERATOR_COMMANDS,
    OperatorCommand,
    OperatorConsole,
    OperatorInputError,
    operator_command,
    parse_line,
    serving,
)

IDS = (1, 2, 3, 4)


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ("hold", OperatorCommand(ControlCommand.HOLD)),
        ("hold 3\n", OperatorCommand(ControlCommand.HOLD, 3)),
        ("  RESUME  ", OperatorCommand(ControlCommand.RESUME)),
        ("land 2", OperatorCommand(ControlCommand.LAND, 2)),
        ("return", OperatorCommand(ControlCommand.RETURN)),
        ("stop 4", OperatorCommand(ControlCommand.STOP, 4)),
        ("", None),
        ("   \n", None),
    ],
)
def test_a_typed_line_is_a_command_for_every_vehicle_or_one(line, expected):
    assert parse_line(line, IDS) == expected


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("fly", "unknown command 'fly'; one of hold, resume, land, return, stop"),
        ("start", "'start' is the ground station's"),
        ("prepare 1", "'prepare' is the ground station's"),
        ("land 7", "vehicle 7 is not in the mission (ids 1, 2, 3, 4)"),
        ("land two", "the vehicle id must be a number"),
        ("land 1 2", "expected COMMAND [VEHICLE_ID]"),
    ],
)
def test_anything_else_is_one_line_saying_what_is_wrong(line, message):
    with pytest.raises(OperatorInputError, match=re.escape(message)) as error:
        parse_line(line, IDS)
    assert "\n" not in str(error.value)


def test_control_takes_the_same_commands_as_typed_lines():
    choices = next(
        action.choices
        for action in build_parser()._subparsers._group_actions[0].choices["control"]._actions
        if action.dest == "command"
    )
    assert list(choices) == [command.value for command in OPERATOR_COMMANDS]
    for name in choices:
        assert operator_command(name, IDS).command.value == name


def lines_of(*lines):
    @contextlib.asynccontextmanager
    async def source():
        async def iterate():
            for line in lines:
                yield line

        yield iterate()

    return source


def test_the_console_sends_what_parses_and_complains_about_the_rest():
    said, complaints, sent = [], [], []

    async def send(command):
        if command.command is ControlCommand.RETURN:
            raise BusConnectionError("127.0.0.1:1883", "the broker is down")
        sent.append(command)

    console = OperatorConsole(
        said.append,
        complaints.append,
        lines_of("hold\n", "bogus\n", "\n", "help\n", "land 2\n", "return\n", "resume 9\n"),
    )
    asyncio.run(console.serve(IDS, send))

    assert sent == [OperatorCommand(ControlCommand.HOLD), OperatorCommand(ControlCommand.LAND, 2)]
    assert said == ["hold sent to every vehicle", HELP, "land sent to vehicle 2"]
    assert len(complaints) == 3
    assert complaints[0].startswith("unknown command 'bogus'")
    assert complaints[1].startswith("return not sent: bus 127.0.0.1:1883: the broker is down")
    assert complaints[2] == "vehicle 9 is not in the mission (ids 1, 2, 3, 4)"


def test_the_end_of_the_input_ends_the_console_not_the_mission():
    async def mission():
        async with serving(OperatorConsole(print, print, lines_of()), IDS, _never_sent):
            for _ in range(10):
                await asyncio.sleep(0)  # the console has long seen the end of its input
            return "flown"

    assert asyncio.run(mission()) == "flown"


async def _never_sent(command):
    raise AssertionError(command)


STDIN_READER = """
import asyncio, os, sys
from mission_runner.runner.operator import stdin_lines

async def main():
    async with stdin_lines() as lines:
        got = [line async for line in lines]
    print(repr(got), os.get_blocking(0), flush=True)

asyncio.run(main())
"""


@pytest.mark.parametrize("stdin", ["devnull", "file", "closed"])
def test_stdin_that_is_no_stream_gives_no_lines(stdin, tmp_path):
    commands = tmp_path / "commands.txt"
    commands.write_text("hold\n")
    with contextlib.ExitStack() as stack:
        kwargs = {
            "devnull": {"stdin": subprocess.DEVNULL},
            "file": {"stdin": stack.enter_context(commands.open())},
            "closed": {"stdin": subprocess.DEVNULL, "preexec_fn": lambda: os.close(0)},
        }[stdin]
        done = subprocess.run(
            [sys.executable, "-c", STDIN_READER.replace("os.get_blocking(0)", "'-'")],
            capture_output=True,
            text=True,
            timeout=30,
            env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
            check=False,
            **kwargs,
        )
    assert done.returncode == 0, done.stderr
    assert done.stdout == "[] -\n"


def test_stdin_lines_from_a_pipe_until_eof_leave_it_blocking():
    done = subprocess.run(
        [sys.executable, "-c", STDIN_READER],
        input="hold 3\nland\n",
        capture_output=True,
        text=True,
        timeout=30,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])},
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout == "['hold 3\\n', 'land\\n'] True\n"

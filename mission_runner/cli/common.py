"""What every command shares: exit codes, where a mission's processes write, JSON output, the
live view's server and the operator's console. Light imports only: the parser imports this."""

from __future__ import annotations

import argparse
import contextlib
import gc
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, ParamSpec

if TYPE_CHECKING:
    from ..config import Scenario
    from ..live import LiveServer
    from ..runner.operator import OperatorConsole

P = ParamSpec("P")

#: A subcommand: parsed arguments in, exit code out.
Handler = Callable[[argparse.Namespace], int]

EXIT_OK, EXIT_EXPECTATION_FAILED, EXIT_BAD_INPUT, EXIT_RUNTIME_FAILURE = 0, 1, 2, 3
#: 128 + the signal's number, as a shell reports a process that signal ended.
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143


def default_mission_dir(scenario: Scenario) -> Path:
    """Where a mission of vehicle processes writes by default: one folder for all of them."""
    return Path("out") / f"{scenario.name}-mission"


@contextlib.contextmanager
def startup_heap() -> Iterator[None]:
    """The collector off while a long-lived process imports and loads its scenario, and what
    that built frozen out of its sight after (:func:`gc.freeze`), even on failure.

    Start-up builds a heap that is never garbage (modules, pydantic's validators, numpy): each
    full collection while it grew walked all of it again (about 30 ms of a vehicle process's
    start), and every one after it too, including :func:`.runner.handshake.freeze_heap`'s
    before k = 0 (another 20-40 ms). What start-up leaves unreachable, a few hundred objects,
    is frozen with the rest rather than paid a collection for."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


def print_json(document: object, out: Path | None) -> int:
    """``document`` as indented JSON on stdout, or written to ``out``."""
    import json  # noqa: PLC0415 - fast `--help`

    text = json.dumps(document, indent=2) + "\n"
    if out is None:
        sys.stdout.write(text)
    else:
        from ..paths import write_atomic  # noqa: PLC0415 - fast `--help`

        write_atomic(out, text)
    return EXIT_OK


def live_server(arguments: argparse.Namespace, scenario: Scenario) -> LiveServer | None:
    """The ``--live`` server, not yet started (None without ``--live``)."""
    if not getattr(arguments, "live", False):
        return None
    from ..live import LiveServer  # noqa: PLC0415 - fast `--help`

    return LiveServer(scenario, host=arguments.live_host, port=arguments.live_port)


def every(callbacks: Sequence[Callable[P, None]]) -> Callable[P, None]:
    """One callback calling each of ``callbacks`` in turn."""

    def call(*args: P.args, **kwargs: P.kwargs) -> None:
        for callback in callbacks:
            callback(*args, **kwargs)

    return call


def operator_console(prefix: str) -> OperatorConsole:
    """The operator's typed commands on stdin: what was sent on stdout, mistakes on stderr."""
    from ..runner.operator import HELP, OperatorConsole  # noqa: PLC0415 - fast `--help`

    def say(text: str) -> None:
        print(f"{prefix}: {text}", flush=True)

    def complain(text: str) -> None:
        print(f"{prefix}: error: {text}", file=sys.stderr, flush=True)

    if sys.stdin is not None and sys.stdin.isatty():
        say(f"type a command and Enter. {HELP}")
    return OperatorConsole(say, complain)


def emulator_errors() -> tuple[type[Exception], ...]:
    """The bundled emulator's error base (a separate package: absent errors match nothing)."""
    try:
        from sitl.errors import SitlError  # noqa: PLC0415 - fast `--help`
    except ImportError:
        return ()
    return (SitlError,)

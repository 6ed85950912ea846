"""How a command stops: SIGINT and SIGTERM cancel its asyncio main task (a flight lands first),
a second signal stops at once; the exit code tells the two signals apart."""

from __future__ import annotations

import contextlib
import logging
import signal
import sys
import threading
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass
from types import FrameType
from typing import Any, TypeVar

T = TypeVar("T")


class _StopSignals:
    """Process-wide, as signal handlers are: which stop signal arrived last, and how to stop
    the asyncio main task that runs (see :func:`run_async`)."""

    def __init__(self) -> None:
        self.received = "SIGINT"
        #: Called (in the signal handler) with the signal's name while an asyncio main runs.
        self.cancel_main: Callable[[str], None] | None = None


signals = _StopSignals()


@dataclass(frozen=True)
class Stopping:
    """What a command says when a stop signal arrives (``{signal}``: its name): the first
    cancels its main task (where a flight lands), ``again`` cancels it a second time (the
    landing is not waited for)."""

    first: str = ""
    again: str = "{signal} again: stopping at once"


#: ``run`` lands its swarm on the first stop signal; on a second the process ends, and so does
#: the emulator in it.
RUN_STOPPING = Stopping(
    "run: {signal}: landing every vehicle ({signal} again: stop at once)",
    "run: {signal} again: stopping at once, vehicles left to PX4's offboard-loss failsafe "
    "(the emulated ones end with this process)",
)
#: ``ground`` sends land on the first; a second does not wait for the send: vehicle processes
#: that did not get it fly on, and PX4's offboard-loss failsafe takes any whose process ends.
GROUND_STOPPING = Stopping(
    "ground: {signal}: telling every vehicle to land ({signal} again: stop at once)",
    "ground: {signal} again: stopping at once; a vehicle that did not get the land flies on "
    "under its own process, PX4's offboard-loss failsafe takes it if that process stops",
)


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM stops a command as Ctrl-C does: a KeyboardInterrupt, or inside :func:`run_async`
    the cancellation of its main task first (a flight lands), noted so that the exit code tells
    the two signals apart."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be set (and only run) in the main thread
        return

    def on_terminate(number: int, frame: FrameType | None) -> None:
        signals.received = "SIGTERM"
        if signals.cancel_main is not None:
            signals.cancel_main("SIGTERM")
        else:
            raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def run_async(coroutine: Coroutine[Any, Any, T], stopping: Stopping = Stopping()) -> T:
    """``asyncio.run(coroutine)``; SIGINT and SIGTERM cancel its main task (so a flight lands),
    then raise KeyboardInterrupt. A second signal cancels it again, which ends the landing
    too, never raising inside the event loop (as asyncio's own second Ctrl-C would). SIGTERM
    also where SIGINT is ignored, as in a background job (SIGINT then stays ignored).
    ``stopping`` says what each signal does, on stderr."""
    import asyncio  # noqa: PLC0415 - simulate does without

    stops = 0
    # The result stays out of the main task: asyncio's Runner formats that task (its result
    # included) while restoring SIGINT's handler, a full repr of a flight's arrays (~2 s).
    outcome: list[T] = []

    async def main() -> None:
        task, loop = asyncio.current_task(), asyncio.get_running_loop()

        def say(text: str) -> None:
            print(text, file=sys.stderr, flush=True)

        def cancel(name: str) -> None:  # may be in a signal handler: only hand work to the loop
            nonlocal stops
            stops += 1
            signals.received = name
            message = stopping.first if stops == 1 else stopping.again
            if message:
                loop.call_soon_threadsafe(say, message.format(signal=name))
            if task is not None:
                loop.call_soon_threadsafe(task.cancel)  # wakes the loop, as asyncio's handler

        # Through the loop: it makes the signal wake it (its wakeup descriptor) whichever thread
        # the kernel hands the signal to. A plain signal.signal handler runs only when the main
        # thread next runs Python, and a loop asleep in epoll for the hour of a landing may not:
        # the process has other threads (numpy's BLAS workers), and one of them may get it.
        handled: list[tuple[signal.Signals, Any]] = []
        if threading.current_thread() is threading.main_thread():
            for number, name in ((signal.SIGINT, "SIGINT"), (signal.SIGTERM, "SIGTERM")):
                previous = signal.getsignal(number)
                if number == signal.SIGINT and previous is signal.SIG_IGN:
                    continue  # a background job's: stays ignored
                loop.add_signal_handler(number, cancel, name)
                handled.append((number, previous))
        signals.cancel_main = cancel
        try:
            outcome.append(await coroutine)
        finally:
            signals.cancel_main = None
            for number, previous in handled:
                loop.remove_signal_handler(number)
                signal.signal(number, previous if previous is not None else signal.SIG_DFL)

    try:
        asyncio.run(main())
    except BaseException as error:
        if not stops:
            raise
        if not isinstance(error, asyncio.CancelledError):  # what went wrong while stopping
            logging.getLogger(__name__).warning("while stopping: %r", error)
        raise KeyboardInterrupt from None
    if stops:  # the coroutine ended on its own terms, but the user asked it to stop
        raise KeyboardInterrupt
    return outcome[0]

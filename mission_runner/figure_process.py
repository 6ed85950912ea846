"""The figures of a run drawn by a process of their own, beside the rest of the results.

matplotlib costs a flight's end about 1.7 s (1 s to import, 0.2 s to draw and encode each of
four PNGs) that nothing else waits on. :meth:`FigureProcess.start` starts a worker (``python -m
mission_runner.figure_process``) that imports it while the vehicles land; :meth:`submit` hands
it the result, and the worker draws while this process writes the recording. The figures are in
once :meth:`collect` has returned: ``summary.json``, written last, names what it returned.

    with FigureProcess() as figures:
        ...fly; figures.start() once the mission phase is over...
        write_results(result, out_dir, figure_process=figures)

The worker is a plain interpreter, not a fork: the flight's process has MAVSDK's threads, which a
fork would copy in whatever state they are, and a multiprocessing spawn would import the command
line's main module (0.7 s) before anything useful. The result goes through a private temporary
pickle file, named on the worker's standard input (a line: it never blocks on the pipe).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import pickle
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Self

from .errors import OutputError

if TYPE_CHECKING:
    from .metrics import SimulationResult
    from .paths import PathName

logger = logging.getLogger(__name__)

#: How long (wall seconds) the figures may take once handed over (about 1 s on an idle machine).
FIGURES_TIMEOUT_S = 120.0
#: How long a worker that was never handed a result may take to leave.
EXIT_TIMEOUT_S = 10.0


class FigureProcess:
    """One worker process that draws one run's figures. Use as ``with``; leaving it ends the
    worker (it draws nothing it was not handed)."""

    def __init__(self) -> None:
        self._process: subprocess.Popen[bytes] | None = None
        self._handed: Path | None = None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        process, self._process = self._process, None
        if process is not None:
            if process.poll() is None:
                try:
                    process.communicate(timeout=EXIT_TIMEOUT_S)  # EOF: it leaves undrawn
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.communicate()
            for pipe in (process.stdin, process.stdout, process.stderr):
                if pipe is not None:
                    with contextlib.suppress(OSError):  # a dead worker's unsent line
                        pipe.close()
        self._forget_handed()

    def start(self) -> None:
        """Start the worker now (once): it imports matplotlib while the caller does other work."""
        if self._process is not None:
            return
        self._process = subprocess.Popen(
            [sys.executable, "-m", __name__],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env={**os.environ, "MPLBACKEND": "Agg"},
        )

    def submit(self, result: SimulationResult, out_dir: PathName) -> None:
        """Hand ``result`` over: its figures are drawn into ``out_dir``; :meth:`collect` them."""
        self.start()
        process = self._process
        assert process is not None and process.stdin is not None
        handle, name = tempfile.mkstemp(prefix="figures-", suffix=".pickle")
        self._handed = Path(name)
        with os.fdopen(handle, "wb") as file:
            pickle.dump((result, os.fspath(out_dir)), file, protocol=pickle.HIGHEST_PROTOCOL)
        # The line, then end of input, straight to the pipe (shorter than PIPE_BUF: one write).
        stdin, process.stdin = process.stdin, None
        try:
            os.write(stdin.fileno(), name.encode() + b"\n")
        except OSError as failure:  # it died already: collect draws here
            logger.warning("figure process not reachable: %s", failure)
        finally:
            stdin.close()

    def collect(self, result: SimulationResult, out_dir: PathName) -> list[str]:
        """The names of the figures written. A worker that failed (killed, out of memory, an
        error) costs the figures' time, not the figures: they are drawn here instead."""
        process = self._process
        if process is None:
            raise OutputError("no figures were handed to the figure process (submit first)")
        try:
            output, errors = process.communicate(timeout=FIGURES_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.communicate()
            raise OutputError(
                f"the figures were not drawn within {FIGURES_TIMEOUT_S:g} s"
            ) from None
        finally:
            self._forget_handed()
        names = _names(output) if process.returncode == 0 else None
        if names is not None:
            return names
        detail = errors.decode(errors="replace").strip().splitlines()[-1:] or ["no message"]
        logger.warning(
            "figure process failed (exit %s: %s); drawing the figures here",
            process.returncode,
            detail[0],
        )
        from .figures import write_figures  # noqa: PLC0415 - matplotlib is slow to import

        return write_figures(result, out_dir)

    def _forget_handed(self) -> None:
        handed, self._handed = self._handed, None
        if handed is not None:
            with contextlib.suppress(FileNotFoundError):
                handed.unlink()


def _names(output: bytes) -> list[str] | None:
    """The worker's answer: a JSON list of file names (None if it is not one)."""
    try:
        names = json.loads(output)
    except ValueError:
        return None
    if not isinstance(names, list) or not all(isinstance(name, str) for name in names):
        return None
    return names


def _main() -> int:
    # Ctrl-C reaches the whole process group: the command decides what becomes of the results.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from .figures import write_figures  # noqa: PLC0415 - imported before the result is in

    line = sys.stdin.readline().strip()
    if not line:
        return 0  # not handed anything: the run ended without results
    with open(line, "rb") as file:
        result, out_dir = pickle.load(file)  # our own private file, written by submit
    sys.stdout.write(json.dumps(write_figures(result, out_dir)))
    return 0


if __name__ == "__main__":
    sys.exit(_main())

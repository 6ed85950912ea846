"""A run's figures and its recording, each written by a process of its own beside the rest of
the results.

matplotlib costs a flight's end about 1.7 s (1 s to import, 0.2 s to draw and encode each of
four PNGs) and the MCAP recording 1.2 s or more of building Foxglove messages, which nothing else
waits on. :meth:`FigureProcess.start` (:meth:`RecordingProcess.start`) starts a worker (``python
-m mission_runner.figure_process figures|recording``) that imports its library while the
mission flies; ``submit`` hands it the result, and the two workers write while this process
writes the rest (on two cores, the end of a run costs the longer of the two, not their sum). A
flight hands the figures its mission's result before the vehicles land: they are drawn during
the landing.
Their files are in once ``collect`` has returned: ``summary.json``, written last, names them.

    with FigureProcess() as figures, RecordingProcess() as recording:
        ...fly; figures.start(), recording.start() as the mission starts...
        write_results(result, out_dir, figure_process=figures, recording_process=recording)

A worker is a plain interpreter, not a fork: the flight's process has MAVSDK's threads, which a
fork would copy in whatever state they are, and a multiprocessing spawn would import the command
line's main module (0.7 s) before anything useful. The job's arguments go through a private
temporary pickle file, named on the worker's standard input (a line: it never blocks on the
pipe). A worker that fails costs its job's time, not its files: ``collect`` does the job here.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import logging
import os
import pickle
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self

from .errors import OutputError

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from .metrics import SimulationResult
    from .paths import PathName
    from .recording import LogLine
    from .records import StepRecord

logger = logging.getLogger(__name__)

#: How long (wall seconds) the figures may take once handed over (about 1 s on an idle machine).
FIGURES_TIMEOUT_S = 120.0
#: How long a worker that was never handed a result may take to leave.
EXIT_TIMEOUT_S = 10.0


class _WorkerProcess:
    """One worker process (``python -m mission_runner.figure_process <job>``) that does one
    job for one run. Use as ``with``; leaving it ends the worker (it does nothing it was not
    handed)."""

    #: What the worker does: a key of :data:`_JOBS`; and its name in messages.
    job = ""
    what = ""
    #: How long (wall seconds) the job may take once handed over.
    timeout_s = FIGURES_TIMEOUT_S

    def __init__(self) -> None:
        self._process: subprocess.Popen[bytes] | None = None
        self._handed: list[Path] = []

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
                    process.communicate(timeout=EXIT_TIMEOUT_S)  # EOF: it leaves undone
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.communicate()
            for pipe in (process.stdin, process.stdout, process.stderr):
                if pipe is not None:
                    with contextlib.suppress(OSError):  # a dead worker's unsent line
                        pipe.close()
        self._forget_handed()

    def start(self) -> None:
        """Start the worker now (once): it imports its libraries while the caller works on."""
        if self._process is not None:
            return
        self._process = subprocess.Popen(
            [sys.executable, "-m", __name__, self.job],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env={**os.environ, "MPLBACKEND": "Agg"},
        )

    def _hand(self, arguments: tuple[Any, ...], *, last: bool = True) -> None:
        """The job's ``arguments``, through a private temporary pickle file named on the
        worker's standard input; then (``last``) the end of its input."""
        self.start()
        process = self._process
        assert process is not None
        stdin = process.stdin
        if stdin is None:  # an earlier part found it dead: collect does the job here
            return
        handle, name = tempfile.mkstemp(prefix=f"{self.job}-", suffix=".pickle")
        self._handed.append(Path(name))
        with os.fdopen(handle, "wb") as file:
            pickle.dump(arguments, file, protocol=pickle.HIGHEST_PROTOCOL)
        # The line straight to the pipe (shorter than PIPE_BUF: one write).
        try:
            os.write(stdin.fileno(), name.encode() + b"\n")
        except OSError as failure:  # it died already: collect does the job here
            logger.warning("%s process not reachable: %s", self.what, failure)
            last = True
        if last:
            process.stdin = None
            stdin.close()

    def _answer(self) -> list[str] | None:
        """The names the worker wrote; None (logged) if it failed: killed, out of memory, an
        error. Raises :class:`OutputError` if it was handed nothing or took too long."""
        process = self._process
        if process is None:
            raise OutputError(f"nothing was handed to the {self.what} process (submit first)")
        try:
            output, errors = process.communicate(timeout=self.timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.communicate()
            raise OutputError(
                f"the {self.job} was not written within {self.timeout_s:g} s"
            ) from None
        finally:
            self._forget_handed()
        names = _names(output) if process.returncode == 0 else None
        if names is None:
            detail = errors.decode(errors="replace").strip().splitlines()[-1:] or ["no message"]
            logger.warning(
                "%s process failed (exit %s: %s); doing its job here",
                self.what,
                process.returncode,
                detail[0],
            )
        return names

    def _forget_handed(self) -> None:
        handed, self._handed = self._handed, []
        for name in handed:
            with contextlib.suppress(FileNotFoundError):
                name.unlink()


class FigureProcess(_WorkerProcess):
    """The run's figures, drawn by a worker process of their own."""

    job = "figures"
    what = "figure"

    def __init__(self) -> None:
        super().__init__()
        self._submitted = False

    def submit(self, result: SimulationResult, out_dir: PathName) -> None:
        """Hand ``result`` over: its figures are drawn into ``out_dir``; :meth:`collect` them.
        Once: a flight hands its mission's result before it lands (the series the figures draw
        are final then) and the same run's final result later, which is not drawn again."""
        if self._submitted:
            return
        self._submitted = True
        self._hand((result, os.fspath(out_dir)))

    def collect(self, result: SimulationResult, out_dir: PathName) -> list[str]:
        """The names of the figures written. A worker that failed costs the figures' time, not
        the figures: they are drawn here instead."""
        names = self._answer()
        if names is not None:
            return names
        from .figures import write_figures  # noqa: PLC0415 - matplotlib is slow to import

        return write_figures(result, out_dir)


class RecordingProcess(_WorkerProcess):
    """The run's MCAP recording, written by a worker process of its own (a flight's 600 steps
    of four vehicles cost the command's end 1.2 s or more of building Foxglove messages)."""

    job = "recording"
    what = "recording"

    def __init__(self) -> None:
        super().__init__()
        self._keywords: dict[str, Any] = {}
        #: How many log lines went with the mission's part (None: no part handed yet).
        self._lines_handed: int | None = None

    def submit_mission(
        self,
        result: SimulationResult,
        path: PathName,
        *,
        records: Mapping[int, Sequence[StepRecord]],
        start_s: float,
        logs: Sequence[LogLine],
    ) -> None:
        """Hand a flight's mission over before it lands: the worker records its steps and the
        ``logs`` so far while the vehicles land (:func:`.recording.recording_of`); the final
        :meth:`submit` of the same run then hands only the lines logged since and the verdict."""
        self._lines_handed = len(logs)
        keywords = {"records": records, "start_s": start_s, "logs": list(logs)}
        self._hand((result, os.fspath(path), keywords, True), last=False)

    def submit(self, result: SimulationResult, path: PathName, **keywords: Any) -> None:
        """Hand ``result`` over: :func:`.recording.write_recording` ``(result, path,
        **keywords)`` in the worker; :meth:`collect` waits for it."""
        self._keywords = keywords
        if self._lines_handed is None:
            self._hand((result, os.fspath(path), keywords, False))
        else:
            later = list(keywords.get("logs", ()))[self._lines_handed :]
            self._hand((later, keywords.get("verdict")))

    def collect(self, result: SimulationResult, path: PathName) -> None:
        """Once the recording is written: by the worker or, if it failed, here."""
        if self._answer() is not None:
            return
        from .recording import recording_of, write_recording  # noqa: PLC0415 - foxglove loads

        keywords = dict(self._keywords)
        if self._lines_handed is None:
            write_recording(result, path, **keywords)
            return
        # As the worker would have: the lines of the landing after the mission's steps
        logs, verdict = list(keywords.pop("logs", ())), keywords.pop("verdict", None)
        mission_lines = logs[: self._lines_handed]
        with recording_of(result, path, **keywords, logs=mission_lines) as finish:
            finish(logs[self._lines_handed :], verdict)


def _names(output: bytes) -> list[str] | None:
    """The worker's answer: a JSON list of file names (None if it is not one)."""
    try:
        names = json.loads(output)
    except ValueError:
        return None
    if not isinstance(names, list) or not all(isinstance(name, str) for name in names):
        return None
    return names


def _draw(result: SimulationResult, out_dir: str) -> list[str]:
    from .figures import write_figures  # noqa: PLC0415 - this job's import, not the other's

    return write_figures(result, out_dir)


def _record(
    result: SimulationResult, path: str, keywords: dict[str, Any], in_two_parts: bool
) -> list[str]:
    """The recording; ``in_two_parts``: a mission's steps first, then (the next line of the
    input) the lines logged since and the verdict. No second part (the run failed while it
    landed): no recording, and no names."""
    from .recording import recording_of, write_recording  # noqa: PLC0415 - this job's import

    if not in_two_parts:
        write_recording(result, path, **keywords)
        return [Path(path).name]
    with contextlib.suppress(_Abandoned), recording_of(result, path, **keywords) as finish:
        later = _handed_arguments()
        if later is None:
            raise _Abandoned
        finish(*later)
        return [Path(path).name]
    return []


class _Abandoned(Exception):
    """The command went without handing the rest of a job over."""


def _handed_arguments() -> tuple[Any, ...] | None:
    """The arguments named on the next line of the input; None at its end."""
    line = sys.stdin.readline().strip()
    if not line:
        return None
    with open(line, "rb") as file:
        arguments: tuple[Any, ...] = pickle.load(file)  # our own private file, written by _hand
    return arguments


#: Each job: the module it imports before anything is handed over, and what it does.
_JOBS: dict[str, tuple[str, Callable[..., list[str]]]] = {
    "figures": ("mission_runner.figures", _draw),
    "recording": ("mission_runner.recording", _record),
}


def _main() -> int:
    # Ctrl-C reaches the whole process group: the command decides what becomes of the results.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    job = sys.argv[1] if len(sys.argv) > 1 else "figures"
    module, work = _JOBS[job]
    importlib.import_module(module)  # imported before the result is in
    arguments = _handed_arguments()
    if arguments is None:
        return 0  # not handed anything: the run ended without results
    sys.stdout.write(json.dumps(work(*arguments)))
    return 0


if __name__ == "__main__":
    sys.exit(_main())

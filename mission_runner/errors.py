"""Errors raised by mission_runner.

Exception tree::

    MissionRunnerError
    ├── ConfigError          a scenario file is unreadable or invalid (names the YAML path)
    ├── OutputError          an output folder cannot be used (a file, not writable)
    ├── SimulationError      the numeric simulator cannot run a valid scenario (e.g. all
    │                        target-sensing vehicles lost)
    ├── RunError             one run of a sweep failed, here or on a cluster's worker (names the
    │                        run: its parameters and seed; the run's own error is its cause)
    ├── ClusterError         a Dask cluster cannot be reached or started (names the address)
    └── ReplayError          a folder cannot be replayed (no recording, or no truth to draw)
"""


class MissionRunnerError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(MissionRunnerError):
    """A scenario file could not be read or did not validate.

    ``problems`` holds one ``(yaml_path, message)`` pair per problem found, e.g.
    ``("algorithm.beta", "must be < 1/T = 8.0")``.
    """

    def __init__(self, source: str, problems: list[tuple[str, str]]) -> None:
        self.source = source
        self.problems = problems
        lines = [f"{source}: invalid scenario ({len(problems)} problem(s))"]
        lines += [f"  {path or '<root>'}: {message}" for path, message in problems]
        super().__init__("\n".join(lines))


class OutputError(MissionRunnerError):
    """An output folder cannot take a run's results; the message names the folder and why."""


class SimulationError(MissionRunnerError):
    """A valid scenario reached a state the simulator cannot continue from."""


class RunError(MissionRunnerError):
    """One run of a sweep failed. ``run`` names it (the combination's values and seed);
    ``__cause__`` is the run's own error, raised where it ran (here or on a worker)."""

    def __init__(self, run: str, error: BaseException) -> None:
        self.run = run
        self.error = error
        super().__init__(f"{run}: {type(error).__name__}: {error}")

    @property
    def bad_input(self) -> bool:
        """Whether the run failed on a scenario it cannot run (an error of ours), not a fault."""
        return isinstance(self.error, MissionRunnerError)


class ClusterError(MissionRunnerError):
    """A Dask cluster cannot be reached or started; the message names the address and what to
    check."""


class ReplayError(MissionRunnerError):
    """A run cannot be replayed: its folder has no ``recording.mcap``, or one without the truth
    to draw (a vehicle process's own)."""


def leaf_errors(error: BaseException) -> list[BaseException]:
    """The errors inside ``error``, exception groups (a task group's failure) opened, in order."""
    if isinstance(error, BaseExceptionGroup):
        return [leaf for inner in error.exceptions for leaf in leaf_errors(inner)]
    return [error]


def error_reason(error: BaseException) -> str:
    """What went wrong, in one line: a group's first error of ours (else its first error), not
    "unhandled errors in a TaskGroup"."""
    leaves = leaf_errors(error)
    leaf = next((e for e in leaves if isinstance(e, MissionRunnerError)), leaves[0])
    return str(leaf) or repr(leaf)

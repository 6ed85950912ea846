"""Errors raised by mission_runner.

Exception tree::

    MissionRunnerError
    ├── ConfigError          a scenario file is unreadable or invalid (names the YAML path)
    ├── OutputError          an output folder cannot be used (a file, not writable)
    ├── SimulationError      the numeric simulator cannot run a valid scenario (e.g. all
    │                        target-sensing vehicles lost)
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

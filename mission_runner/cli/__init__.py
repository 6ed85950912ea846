"""``mission-runner``: the command line.

    mission-runner simulate CONFIG [--out DIR] [--runs N] [--no-figures] [--replay] [--quiet]
    mission-runner sweep CONFIG --set PATH=V1,V2 [--set ...] [--runs N] [--metric NAME]
    mission-runner run CONFIG [--out DIR] [--realtime [--speed F]] [--no-figures] [--replay]
    mission-runner replay OUT_DIR [--every N] [--fps F] [--width PX] [--gif FILE]  animate a run
    mission-runner schema [--out FILE]                   the scenario's JSON Schema
    mission-runner view CONFIG [--port N]                a running mission's bus, live in Foxglove
    mission-runner layout CONFIG [--out FILE]            a Foxglove layout for the scenario's topics
    mission-runner vehicle CONFIG --id N [--url URL] [--out DIR]   one vehicle's controller (MQTT)
    mission-runner ground CONFIG [--start-delay S]       prepare, start and watch vehicle processes
    mission-runner ranges CONFIG [--source sih|gps]      synthesised UWB ranges (simulation aid)
    mission-runner px4-sitl CONFIG --px4-dir DIR         real PX4 SITL (SIH), one per vehicle
    mission-runner emulate CONFIG [sitl options]         emulated vehicles + the scenario's world
    mission-runner control CONFIG hold|resume|land|return|stop [--vehicle N]   operator command
    mission-runner broker-config CONFIG --out DIR        mosquitto config, per-role logins, ACL

Every command that talks on the bus takes ``--bus-key-file FILE`` (the mission's message key;
else ``MISSION_BUS_KEY``, else ``bus.auth.key_file``), ``--bus-credentials FILE`` (broker
logins) and ``--insecure-bus`` (an MQTT bus without a key: closed bench networks only).

Exit codes:

- 0: success (and every ``expect:`` bound met);
- 1: an ``expect:`` bound failed;
- 2: bad input, before any work: the scenario (the message names the YAML path), an option
  (``--speed 0``), ``--out`` (a file, not writable), a batch too large for memory;
- 3: a runtime failure: a vehicle refused, was lost or the mission was aborted, a port is taken
  (the message names the setting that moves it), results could not be written; also an
  unexpected error (its traceback is printed, to be reported);
- 130: interrupted by SIGINT (Ctrl-C), 143: by SIGTERM (the last one received). Both stop the
  same way: a flight lands first (``run``: every vehicle in the air; ``ground``: land sent to
  every vehicle), and ``summary.json`` is written with ``status: interrupted``. A second signal
  stops at once, without waiting for the landing: the vehicles are left to PX4's offboard-loss
  failsafe.

``--out``: a run first removes the earlier run's own files from the folder (summary.json,
timeseries.csv, batch.csv, the figures, tlogs/vehicle_*.tlog: ``outputs.RUN_FILES``), so results
of two runs never mix; any other file there is left alone. ``summary.json`` always says how the run
ended (``status``: running, passed, failed, interrupted or error).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

from ..errors import ClusterError, MissionRunnerError, RunError, leaf_errors
from .common import (
    EXIT_BAD_INPUT,
    EXIT_EXPECTATION_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_RUNTIME_FAILURE,
    EXIT_TERMINATED,
    Handler,
    emulator_errors,
)
from .parser import build_parser, command_named
from .stopping import signals, terminate_as_interrupt

__all__ = [
    "EXIT_BAD_INPUT",
    "EXIT_EXPECTATION_FAILED",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_RUNTIME_FAILURE",
    "EXIT_TERMINATED",
    "main",
]


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser(command_named(sys.argv[1:] if argv is None else argv))
    arguments = parser.parse_args(argv)
    # After parsing: ``--help`` and bad options end above without loading the bus.
    from ..bus.errors import BusConnectionError, BusTimeoutError  # noqa: PLC0415 - fast `--help`
    from ..runner.errors import RunnerError  # noqa: PLC0415 - fast `--help`

    logging.basicConfig(
        level=logging.WARNING if getattr(arguments, "quiet", False) else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    signals.received = "SIGINT"
    try:
        with terminate_as_interrupt():
            return _unwrapped(arguments.handler, arguments)
    except (RunnerError, BusConnectionError, BusTimeoutError) as error:  # link, broker, vehicle
        print(f"error: {error}", file=sys.stderr)
        return EXIT_RUNTIME_FAILURE
    except emulator_errors() as error:  # e.g. a port already taken: one line naming the setting
        print(f"error: {error}", file=sys.stderr)
        return EXIT_RUNTIME_FAILURE
    except ClusterError as error:  # no scheduler at the address: one line naming it
        print(f"error: {error}", file=sys.stderr)
        return EXIT_RUNTIME_FAILURE
    except RunError as error:  # a sweep's run failed, here or on a worker: which, and why
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT if error.bad_input else EXIT_RUNTIME_FAILURE
    except MissionRunnerError as error:
        print(f"error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"interrupted ({signals.received})", file=sys.stderr)
        return EXIT_TERMINATED if signals.received == "SIGTERM" else EXIT_INTERRUPTED
    except OSError as error:  # e.g. the disk filled up while writing results
        print(f"error: {error}", file=sys.stderr)
        return EXIT_RUNTIME_FAILURE
    except Exception:  # a bug: its traceback, but not exit code 1, which means "failed"
        logging.getLogger(__name__).exception("unexpected error; please report it")
        return EXIT_RUNTIME_FAILURE


def _unwrapped(handler: Handler, arguments: argparse.Namespace) -> int:
    """Run ``handler``; an exception group (a task group's failure) is re-raised as its first
    error of ours, so the user reads one line, not a tree of tracebacks."""
    try:
        return handler(arguments)
    except BaseExceptionGroup as group:
        for leaf in leaf_errors(group):
            if isinstance(leaf, (MissionRunnerError, KeyboardInterrupt, *emulator_errors())):
                raise leaf from group
        raise

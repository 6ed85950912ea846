"""``mission-runner replay``."""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import argtypes
from .common import EXIT_OK
from .output import replay_text


def add_parser(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    replay = commands.add_parser(
        "replay",
        help="animate a run (simulate, run or ground output folder) from its recording.mcap: "
        "replay.gif, and replay.mp4 where ffmpeg is on the PATH",
    )
    replay.add_argument("out_dir", type=Path, help="the run's output folder")
    replay.add_argument(
        "--every", type=argtypes.positive_int, default=1, help="one frame every N steps (default 1)"
    )
    replay.add_argument(
        "--fps",
        type=argtypes.at_most(argtypes.positive_float, 100.0),  # GIF frames last >= 10 ms
        default=20.0,
        help="frames per second (default 20, at most 100)",
    )
    replay.add_argument(
        "--width",
        type=argtypes.at_most(argtypes.positive_int, 7680),  # 8K: every frame is held in memory
        default=800,
        help="frame width in pixels (default 800, at most 7680)",
    )
    replay.add_argument(
        "--trail",
        type=argtypes.positive_int,
        default=None,
        help="trail length in steps (default: all)",
    )
    replay.add_argument(
        "--gif", type=Path, default=None, help="where the GIF goes (default OUT_DIR/replay.gif)"
    )
    replay.add_argument("--no-mp4", action="store_true", help="no MP4 even if ffmpeg is there")
    replay.set_defaults(handler=command)


def command(arguments: argparse.Namespace) -> int:
    from ..replay import write_replay  # noqa: PLC0415 - matplotlib is slow to import

    files = write_replay(
        arguments.out_dir,
        gif=arguments.gif,
        every=arguments.every,
        fps=arguments.fps,
        width_px=arguments.width,
        trail_steps=arguments.trail,
        mp4=not arguments.no_mp4,
    )
    print(replay_text(files))
    return EXIT_OK

"""Replay a finished run as an animation: the paper's XY view, step by step.

:func:`load_track` reads an output folder's ``recording.mcap`` (everything: truth, estimates,
slots, circle, states, metrics) into a :class:`Track` of arrays; :class:`Replay` draws one frame
of it with matplotlib (the background once, then only what moves, blitted); :func:`write_replay`
writes the frames to an animated GIF with pillow, and to an MP4 where an ``ffmpeg`` is on the
PATH. Drawn in the paper's XY view: x = north to the right, y = east up (``xy.png`` and
Foxglove's top view are maps, east to the right: the same picture mirrored about the diagonal).
"""

from __future__ import annotations

import csv
import json
import math
import shutil
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib import font_manager
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import NDArray
from PIL import Image, ImageDraw, ImageFont

from .checks import validate_scenario
from .enclosing.shape import desired_offsets
from .errors import ReplayError
from .recording import PALETTE, RECORDING, circle_points, read_recording, recording_metadata
from .scenario import shape_schedule

if TYPE_CHECKING:
    from matplotlib.lines import Line2D

    from .paths import PathName

GIF = "replay.gif"
MP4 = "replay.mp4"


@dataclass
class Track:
    """A run as arrays, K + 1 samples, N vehicles (north/east [m]; NaN where unknown).

    times_s ``(K+1,)`` (mission clock); target_m ``(K+1, 2)``; positions_m ``(K+1, N, 2)``;
    live ``(K+1, N)``; slots_m ``(K+1, N, 2)``; circle_m ``(K+1, P, 2)``; estimates_m
    ``(K+1, N, N+1, 2)``: where vehicle i estimates slot j (0 the target, then the vehicles)
    to be, its true position minus phat_ij; states ``(K+1, N)`` controller states ("" where no
    record); tracking_error_m, localization_error_m, phase_spacing_error_rad ``(K+1,)``.
    """

    name: str
    vehicle_ids: list[int]
    times_s: NDArray[np.float64]
    target_m: NDArray[np.float64]
    positions_m: NDArray[np.float64]
    live: NDArray[np.bool_]
    slots_m: NDArray[np.float64]
    circle_m: NDArray[np.float64]
    estimates_m: NDArray[np.float64]
    states: NDArray[np.str_]
    tracking_error_m: NDArray[np.float64]
    localization_error_m: NDArray[np.float64]
    phase_spacing_error_rad: NDArray[np.float64]
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        """K: the number of steps (samples are k = 0..K)."""
        return len(self.times_s) - 1


def load_track(out_dir: PathName) -> Track:
    """The run in ``out_dir`` (a ``simulate``, ``run`` or ``ground`` folder): from its
    ``recording.mcap``, or, in a folder written before recordings existed, from its
    ``timeseries.csv`` and ``summary.json`` (no estimates nor controller states there)."""
    path = Path(out_dir) / RECORDING
    if path.exists():
        return _track_from_recording(path)
    if (Path(out_dir) / "timeseries.csv").exists() and (Path(out_dir) / "summary.json").exists():
        return _track_from_tables(Path(out_dir))
    raise ReplayError(
        f"{path} not found (nor timeseries.csv and summary.json): replay a folder written by "
        "'mission-runner simulate', 'run' or 'ground' (a vehicle process's own has no truth)"
    )


def _track_from_tables(out_dir: Path) -> Track:
    """A track from ``timeseries.csv``, the circle and slots from the scenario in
    ``summary.json`` (its ``parameters``)."""

    document = json.loads((out_dir / "summary.json").read_text())
    scenario = validate_scenario(document["parameters"], str(out_dir / "summary.json"))
    with open(out_dir / "timeseries.csv", newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    ids = [vehicle.id for vehicle in scenario.vehicles]
    n, samples = len(ids), len(rows)

    def column(name: str) -> NDArray[np.float64]:
        return np.array([float(row[name] or "nan") for row in rows])

    positions = np.stack(
        [np.stack([column(f"v{i}_north_m"), column(f"v{i}_east_m")], -1) for i in ids], 1
    )
    phases = np.stack([column(f"v{i}_phase_rad") for i in ids], 1)
    target = np.stack([column("target_north_m"), column("target_east_m")], -1)
    shape = shape_schedule(scenario)
    radius = scenario.algorithm.radius_m
    return Track(
        name=scenario.name,
        vehicle_ids=ids,
        times_s=column("time_s"),
        target_m=target,
        positions_m=positions,
        live=np.stack([column(f"v{i}_live") == 1 for i in ids], 1),
        slots_m=np.stack(
            [target[k] + desired_offsets(phases[k], radius, shape(k)) for k in range(samples)]
        ),
        circle_m=np.stack([circle_points(target[k], shape(k), radius) for k in range(samples)]),
        estimates_m=np.full((samples, n, n + 1, 2), np.nan),
        states=np.full((samples, n), "", dtype=str),
        tracking_error_m=column("tracking_error_m"),
        localization_error_m=column("localization_error_m"),
        phase_spacing_error_rad=column("phase_spacing_error_rad"),
    )


def _track_from_recording(path: Path) -> Track:
    messages = list(read_recording(path))
    step_of = {
        message.log_time_ns: message.message["step"]
        for message in messages
        if message.topic == "/mission/metrics"
    }
    if not step_of:
        raise ReplayError(f"{path} has no /mission/metrics: not a mission's recording")
    ids = sorted({int(m.topic.split("/")[2]) for m in messages if m.topic.startswith("/vehicles/")})
    name = recording_metadata(path).get("scenario", {}).get("name", path.parent.name)
    builder = _TrackBuilder(_empty_track(name, ids, max(step_of.values()) + 1))
    for message in messages:
        k = step_of.get(message.log_time_ns)
        if k is not None:
            builder.add(k, message.topic, message.message)
    if np.isnan(builder.track.positions_m).all():
        raise ReplayError(f"{path} has no true positions to draw (a vehicle process's own?)")
    return builder.finish()


def _empty_track(name: str, ids: list[int], samples: int) -> Track:
    """A track of ``samples`` samples of the vehicles ``ids``, nothing known yet."""
    n = len(ids)
    return Track(
        name=name,
        vehicle_ids=ids,
        times_s=np.full(samples, np.nan),
        target_m=np.full((samples, 2), np.nan),
        positions_m=np.full((samples, n, 2), np.nan),
        live=np.zeros((samples, n), dtype=bool),
        slots_m=np.full((samples, n, 2), np.nan),
        circle_m=np.full((samples, 0, 2), np.nan),
        estimates_m=np.full((samples, n, n + 1, 2), np.nan),
        states=np.full((samples, n), "", dtype=object),
        tracking_error_m=np.full(samples, np.nan),
        localization_error_m=np.full(samples, np.nan),
        phase_spacing_error_rad=np.full(samples, np.nan),
    )


class _TrackBuilder:
    """Fills a :class:`Track` from a recording's messages, each at its step k: what depends on
    other messages of the step (estimates need the true position; the circle's size is known
    at the first) is kept until :meth:`finish`."""

    def __init__(self, track: Track) -> None:
        self.track = track
        self._column = {vehicle_id: index for index, vehicle_id in enumerate(track.vehicle_ids)}
        self._slot_of = {0: 0, **{vehicle_id: i + 1 for vehicle_id, i in self._column.items()}}
        self._circles: dict[int, NDArray[np.float64]] = {}
        self._relative: list[tuple[int, int, int, float, float]] = []

    def add(self, k: int, topic: str, body: Any) -> None:
        track = self.track
        if topic == "/mission/metrics":
            track.times_s[k] = body["time_s"]
            track.tracking_error_m[k] = _number(body["tracking_error_m"])
            track.localization_error_m[k] = _number(body["localization_error_m"])
            track.phase_spacing_error_rad[k] = _number(body["phase_spacing_error_rad"])
        elif topic == "/target/pose":
            track.target_m[k] = _north_east(body.pose.position)
        elif topic == "/formation/scene":
            for entity in body.entities:
                if entity.id == "circle" and entity.lines:
                    self._circles[k] = np.array([(p.y, p.x) for p in entity.lines[0].points])
        elif topic.startswith("/vehicles/"):
            self._add_vehicle(k, topic, body)

    def _add_vehicle(self, k: int, topic: str, body: Any) -> None:
        track = self.track
        vehicle_id, leaf = int(topic.split("/")[2]), topic.split("/")[3]
        index = self._column[vehicle_id]
        if leaf == "pose":
            track.positions_m[k, index] = _north_east(body.pose.position)
        elif leaf == "slot":
            track.slots_m[k, index] = _north_east(body.pose.position)
        elif leaf == "state":
            track.states[k, index] = body["state"]
            track.live[k, index] = body["live"]
            for estimate in body["estimates"]:
                slot = self._slot_of.get(estimate["peer"])
                if slot is not None:
                    self._relative.append((k, index, slot, estimate["north_m"], estimate["east_m"]))

    def finish(self) -> Track:
        track = self.track
        # A final sample without a state message keeps the step before's membership.
        no_state = (track.states == "").all(axis=1)
        for k in np.flatnonzero(no_state):
            if k > 0:
                track.live[k] = track.live[k - 1]
        for step, index, slot, north, east in self._relative:
            track.estimates_m[step, index, slot] = track.positions_m[step, index] - (north, east)
        if self._circles:
            points = len(next(iter(self._circles.values())))
            track.circle_m = np.full((len(track.times_s), points, 2), np.nan)
            for step, circle in self._circles.items():
                track.circle_m[step] = circle
        track.states = track.states.astype(str)
        return track


class Replay:
    """Draws frames of ``track``: trails, vehicles, slots, the circle, the estimates, the target
    and a time/metric overlay, ``width_px`` wide (height from the run's extent)."""

    def __init__(
        self, track: Track, *, width_px: int = 640, trail_steps: int | None = None
    ) -> None:
        self.track = track
        self.trail_steps = trail_steps
        low, high = _extent(track)
        # The paper's XY view: x (north) to the right, y (east) up.
        centre, span = (low + high) / 2, high - low
        span = np.maximum(span, [span[1] * 0.8, span[0] * 0.3])  # never wider than 10:3, >= 5:4
        low, high = centre - span / 2, centre + span / 2
        dpi = 100
        # Margins in inches (labels and the overlay keep their size whatever the frame's).
        left_in, right_in, bottom_in, top_in = 0.6, 0.15, 0.42, 0.42
        width_in = width_px / dpi
        axes_width_in = width_in - left_in - right_in
        height_in = bottom_in + top_in + axes_width_in * span[1] / span[0]
        self.figure = Figure(figsize=(width_in, height_in), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.figure)
        axes = self.figure.add_axes(
            (
                left_in / width_in,
                bottom_in / height_in,
                axes_width_in / width_in,
                1 - (bottom_in + top_in) / height_in,
            )
        )
        self.axes = axes
        axes.set_xlim(low[0], high[0])
        axes.set_ylim(low[1], high[1])
        axes.set_xlabel(
            "x = north [m]        o slot   x estimate   ^ target   -- circle", fontsize=8
        )
        axes.set_ylabel("y = east [m]", fontsize=8)
        axes.tick_params(labelsize=7)
        axes.grid(alpha=0.3)
        axes.plot(track.target_m[:, 0], track.target_m[:, 1], ":", color="0.75", lw=0.8)
        colours = [PALETTE[i % len(PALETTE)] for i in range(len(track.vehicle_ids))]
        self.colours = colours

        def line(*style: Any, **options: Any) -> Line2D:
            (artist,) = axes.plot([], [], *style, animated=True, **options)
            return artist

        self.circle = line("--", color="0.3", lw=1.1)
        self.target_trail = line("--", color="black", lw=1.2)
        # Trails without anti-aliasing: crisper, and a GIF of flat colours is half the size.
        self.trails = [line("-", color=c, lw=1.0, antialiased=False) for c in colours]
        self.slots = [line("o", mfc="none", mec=c, ms=9, mew=1.2) for c in colours]
        self.estimates = [line("x", color=c, ms=5, mew=1.0) for c in colours]
        self.target = line("^", color="black", ms=9)
        self.vehicles = [line("o", color=c, ms=7, mec="white", mew=0.8) for c in colours]
        # The overlay is drawn by pillow on the finished frame: matplotlib's text layout was
        # more than half of the time per frame.
        self.font = ImageFont.truetype(font_manager.findfont("DejaVu Sans Mono"), 11)
        self.overlay_at = (int(left_in * dpi), 3)
        top = 1 - 0.04 / height_in
        self.figure.text(1 - right_in / width_in, top, track.name, va="top", ha="right", fontsize=8)
        self.canvas.draw()
        self.background = self.canvas.copy_from_bbox(self.figure.bbox)

    @property
    def size_px(self) -> tuple[int, int]:
        width, height = self.canvas.get_width_height()
        return int(width), int(height)

    def draw(self, k: int) -> Image.Image:
        """Frame of step k (RGB)."""
        track = self.track
        first = 0 if self.trail_steps is None else max(0, k - self.trail_steps)
        if track.circle_m.shape[1]:
            circle = np.vstack([track.circle_m[k], track.circle_m[k, :1]])
            self.circle.set_data(circle[:, 0], circle[:, 1])
        self.target_trail.set_data(*track.target_m[first : k + 1].T)
        self.target.set_data([track.target_m[k, 0]], [track.target_m[k, 1]])
        for index in range(len(track.vehicle_ids)):
            trail = track.positions_m[first : k + 1, index]
            self.trails[index].set_data(trail[:, 0], trail[:, 1])
            shown = track.live[k, index] or not track.states[k, index]
            position = track.positions_m[k, index] if shown else np.full(2, np.nan)
            self.vehicles[index].set_data([position[0]], [position[1]])
            self.vehicles[index].set_marker("o" if track.live[k, index] else "X")
            slot = track.slots_m[k, index]
            self.slots[index].set_data([slot[0]], [slot[1]])
            estimates = np.delete(track.estimates_m[k, index], index + 1, axis=0)
            self.estimates[index].set_data(estimates[:, 0], estimates[:, 1])
        self.canvas.restore_region(self.background)
        for artist in (
            *self.trails,
            self.target_trail,
            self.circle,
            *self.slots,
            *self.estimates,
            self.target,
            *self.vehicles,
        ):
            self.figure.draw_artist(artist)
        frame = Image.frombuffer("RGBA", self.size_px, self.canvas.buffer_rgba()).convert("RGB")
        ImageDraw.Draw(frame).text(
            self.overlay_at, self._overlay_text(k), fill=(0, 0, 0), font=self.font, spacing=2
        )
        return frame

    def _overlay_text(self, k: int) -> str:
        track = self.track
        elapsed = track.times_s[k] - track.times_s[0]
        states = track.states[k]
        counts: dict[str, int] = {}
        for index, state in enumerate(states):
            name = state or ("live" if track.live[k, index] else "absent")
            counts[name] = counts.get(name, 0) + 1
        summary = ", ".join(f"{count} {name}" for name, count in sorted(counts.items()))
        return (
            f"t = {elapsed:6.2f} s   k = {k:4d}/{track.steps}   {summary}\n"
            f"tracking {_format(track.tracking_error_m[k])} m   "
            f"estimates {_format(track.localization_error_m[k])} m   "
            f"phase spacing {_format(track.phase_spacing_error_rad[k])} rad"
        )


@dataclass(frozen=True)
class ReplayFiles:
    """What :func:`write_replay` wrote: the files, frames, frame size and seconds spent."""

    gif: Path
    mp4: Path | None
    frames: int
    size_px: tuple[int, int]
    render_s: float


def frame_steps(steps: int, every: int) -> list[int]:
    """The steps drawn: every ``every``-th from 0, and always the last (K)."""
    chosen = list(range(0, steps + 1, every))
    if chosen[-1] != steps:
        chosen.append(steps)
    return chosen


def write_replay(
    out_dir: PathName,
    *,
    gif: PathName | None = None,
    every: int = 1,
    fps: float = 20.0,
    width_px: int = 800,
    trail_steps: int | None = None,
    mp4: bool = True,
) -> ReplayFiles:
    """Render the run in ``out_dir`` to ``replay.gif`` (``gif`` to change), and ``replay.mp4``
    beside it when ``mp4`` and an ffmpeg is on the PATH. One frame per ``every`` steps at ``fps``
    frames per second."""
    started = time.perf_counter()
    track = load_track(out_dir)
    gif_path = Path(gif) if gif is not None else Path(out_dir) / GIF
    replay = Replay(track, width_px=width_px, trail_steps=trail_steps)
    steps = frame_steps(track.steps, every)
    # One palette for every frame, from the first and the last (everything drawn appears in one
    # of them): quantising each frame to its own palette would flicker and cost more.
    first, last = replay.draw(steps[0]), replay.draw(steps[-1])
    both = Image.new("RGB", (first.width, first.height * 2))
    both.paste(first, (0, 0))
    both.paste(last, (0, first.height))
    palette = both.quantize(colors=64, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    ffmpeg = shutil.which("ffmpeg") if mp4 else None
    encoder = _Mp4(ffmpeg, gif_path.with_suffix(".mp4"), replay.size_px, fps) if ffmpeg else None
    frames: list[Image.Image] = []
    try:
        for k in steps:
            frame = replay.draw(k)
            frames.append(frame.quantize(palette=palette, dither=Image.Dither.NONE))
            if encoder is not None:
                encoder.write(frame)
    finally:
        if encoder is not None:
            encoder.close()
    _save_gif(frames, gif_path, fps)
    return ReplayFiles(
        gif=gif_path,
        mp4=encoder.path if encoder is not None else None,
        frames=len(frames),
        size_px=replay.size_px,
        render_s=time.perf_counter() - started,
    )


def _save_gif(frames: Sequence[Image.Image], path: Path, fps: float) -> None:
    temporary = path.with_name(f".{path.name}.partial")
    duration_ms = [round(1000 / fps)] * len(frames)
    duration_ms[-1] = 2000  # hold the final state before the loop starts again
    frames[0].save(
        temporary,
        format="GIF",
        save_all=True,
        append_images=list(frames[1:]),
        duration=duration_ms,
        loop=0,
        optimize=False,
    )
    temporary.replace(path)


class _Mp4:
    """Raw RGB frames piped into ffmpeg (H.264, yuv420p: what browsers and players take)."""

    def __init__(self, ffmpeg: str, path: Path, size_px: tuple[int, int], fps: float) -> None:
        self.path = path
        width, height = size_px
        self.process = subprocess.Popen(
            [
                ffmpeg,
                "-loglevel",
                "error",
                "-y",
                "-f",
                "rawvideo",
                "-pix_fmt",
                "rgb24",
                "-s",
                f"{width}x{height}",
                "-r",
                f"{fps:g}",
                "-i",
                "-",
                "-vf",
                "pad=ceil(iw/2)*2:ceil(ih/2)*2:color=white",  # yuv420p needs even sides
                "-pix_fmt",
                "yuv420p",
                str(path),
            ],
            stdin=subprocess.PIPE,
        )

    def write(self, frame: Image.Image) -> None:
        assert self.process.stdin is not None  # opened with stdin=PIPE
        self.process.stdin.write(frame.tobytes())

    def close(self) -> None:
        assert self.process.stdin is not None
        self.process.stdin.close()
        if self.process.wait(timeout=60) != 0:
            raise ReplayError(f"ffmpeg failed writing {self.path} (exit {self.process.returncode})")


def _extent(track: Track) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """North/east bounds of everything drawn, with a margin."""
    points = [
        track.target_m.reshape(-1, 2),
        track.positions_m.reshape(-1, 2),
        track.circle_m.reshape(-1, 2),
    ]
    stacked = np.vstack(points)
    stacked = stacked[np.all(np.isfinite(stacked), axis=1)]
    low, high = stacked.min(axis=0), stacked.max(axis=0)
    margin = 0.05 * max(float(np.max(high - low)), 1.0)
    return low - margin, high + margin


def _north_east(position: Any) -> tuple[float, float]:
    """A ``world`` (ENU) point as north/east."""
    return float(position.y), float(position.x)


def _number(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _format(value: float) -> str:
    return (
        "   -   "
        if not math.isfinite(value)
        else f"{value:7.4f}"
        if value >= 1e-3
        else f"{value:7.1e}"
    )

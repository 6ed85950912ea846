"""A Foxglove layout for a mission's channels (the recording's and the live view's alike):
the 3D panel looking down on ``world`` with the vehicles, their estimates and the circle; the
tracking and estimate errors; each controller's setpoint lateness and state; the mission's
events. Built with foxglove-sdk's layout types; ``docs/foxglove_layout.json`` is the one for
the bundled scenarios (vehicles 1-4): in Foxglove, Layouts -> Import from file.
"""

from __future__ import annotations

from collections.abc import Sequence

import foxglove.layouts as fl

from .recording import PALETTE, vehicle_topic


def foxglove_layout(vehicle_ids: Sequence[int]) -> fl.Layout:
    """The layout for vehicles ``vehicle_ids``."""
    colours = {i: _hex(PALETTE[index % len(PALETTE)]) for index, i in enumerate(vehicle_ids)}
    topics: dict[str, fl.BaseRendererTopicSettings] = {
        "/formation/scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
        "/target/pose": fl.BaseRendererPoseTopicSettings(
            visible=True, type="arrow", color="#000000"
        ),
    }
    for i in vehicle_ids:
        topics[vehicle_topic(i, "pose")] = fl.BaseRendererPoseTopicSettings(
            visible=True, type="arrow", color=colours[i]
        )
        topics[vehicle_topic(i, "scene")] = fl.BaseRendererSceneUpdateTopicSettings(visible=True)
    scene = fl.ThreeDeePanel(
        title="world (x east, y north)",
        config=fl.ThreeDeeConfig(
            follow_tf="target",
            follow_mode="follow-position",
            camera_state=fl.ThreeDeeCameraState(perspective=False, distance=40.0, phi=0.0),
            topics=topics,
        ),
    )
    errors = fl.PlotPanel(
        title="errors [m]",
        config=fl.PlotConfig(
            paths=[
                fl.PlotSeries(value="/mission/metrics.tracking_error_m", label="tracking"),
                fl.PlotSeries(value="/mission/metrics.localization_error_m", label="estimates"),
            ]
        ),
    )
    lateness = fl.PlotPanel(
        title="setpoint lateness [s]",
        config=fl.PlotConfig(
            paths=[
                fl.PlotSeries(
                    value=f"{vehicle_topic(i, 'state')}.setpoint_lateness_s",
                    label=f"vehicle {i}",
                    color=colours[i],
                )
                for i in vehicle_ids
            ]
        ),
    )
    states = fl.StateTransitionsPanel(
        title="controller states",
        config=fl.StateTransitionsConfig(
            paths=[
                fl.StateTransitionsSeries(
                    value=f"{vehicle_topic(i, 'state')}.state", label=f"vehicle {i}"
                )
                for i in vehicle_ids
            ]
        ),
    )
    events = fl.LogPanel(title="events", config=fl.LogConfig(topic_to_render="/mission/events"))
    side = fl.SplitContainer(
        direction="column",
        items=[fl.SplitItem(content=panel) for panel in (errors, lateness, states, events)],
    )
    return fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[
                fl.SplitItem(proportion=3, content=scene),
                fl.SplitItem(proportion=2, content=side),
            ],
        )
    )


def _hex(rgb: tuple[float, float, float]) -> str:
    return "#" + "".join(f"{round(channel * 255):02x}" for channel in rgb)

"""One place that turns a scenario into what the flying layers need: a vehicle's controller
(its law, settings, shape schedule) and the autopilot parameters every vehicle gets. The in-process
mission (:mod:`.mission`) and the vehicle processes (:mod:`.process`) both build from here, so a
default lives once, in the config model.
"""

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from ..config import Scenario, VehicleConfig
from ..enclosing import VehicleEnclosing
from ..scenario import shape_matrices
from ..sim.simulator import algorithm_params
from .controller import ControllerSettings, StepRecord, VehicleController
from .ports import ControllerBus, ControllerClock, ControllerLink

#: k -> the affine shape matrix ``(3, 3)`` at step k.
ShapeSchedule = Callable[[int], NDArray[np.float64]]

#: PX4's COM_OBL_RC_ACT (offboard-loss failsafe) for each ``flight.on_lost``.
OFFBOARD_LOSS_ACTION = {"return": 3, "land": 4, "hold": 5}


def controller_settings(scenario: Scenario, vehicle: VehicleConfig) -> ControllerSettings:
    """The :class:`ControllerSettings` of ``vehicle`` (a scenario vehicle entry)."""
    flight = scenario.flight
    return ControllerSettings(
        step_s=scenario.timing.step_s,
        step_deadline_s=flight.step_deadline_s,
        wall_deadline_s=flight.lockstep_wait_s,
        silence_timeout_s=flight.silence_timeout_s,
        member_timeout_steps=flight.member_timeout_steps,
        max_horizontal_speed_m_s=vehicle.speed_limit_m_s,
        max_vertical_speed_m_s=flight.max_vertical_speed_m_s,
        velocity_lead_s=flight.velocity_lead_s,
        tracking_gain_1_s=flight.displacement_tracking.gain_1_s,
        tracking_integral_gain_1_s2=flight.displacement_tracking.integral_gain_1_s2,
        tracking_max_correction_m_s=flight.displacement_tracking.max_correction_m_s,
    )


def altitude_of(scenario: Scenario, vehicle: VehicleConfig) -> float:
    """The altitude ``vehicle`` holds [m above home]."""
    return vehicle.altitude_m or scenario.flight.altitude_m


def shape_schedule(scenario: Scenario) -> ShapeSchedule:
    """k -> the affine shape matrix at step k (held after the last step)."""
    steps = scenario.timing.steps
    shapes = shape_matrices(scenario.algorithm.shape, np.arange(steps + 2) * scenario.timing.step_s)
    return lambda k: shapes[min(k, len(shapes) - 1)]


def build_controller(
    scenario: Scenario,
    vehicle: VehicleConfig,
    *,
    link: ControllerLink,
    bus: ControllerBus,
    clock: ControllerClock,
    on_step: Callable[[int, StepRecord], None] | None = None,
    shape: ShapeSchedule | None = None,
) -> VehicleController:
    """The controller of ``vehicle`` flying ``link`` on ``bus`` and ``clock``."""
    ids = [v.id for v in scenario.vehicles]
    law = VehicleEnclosing(
        algorithm_params(scenario),
        vehicle.id,
        ids,
        vehicle.initial_phase_rad,
        vehicle.omega_rad_s or scenario.algorithm.omega_rad_s,
    )
    return VehicleController(
        vehicle_id=vehicle.id,
        vehicle_ids=ids,
        law=law,
        senses_target=vehicle.senses_target,
        link=link,
        bus=bus,
        topics=scenario.bus.topics(scenario.name),
        clock=clock,
        settings=controller_settings(scenario, vehicle),
        shape=shape or shape_schedule(scenario),
        altitude_m=altitude_of(scenario, vehicle),
        on_step=on_step,
    )


def autopilot_params(scenario: Scenario) -> dict[str, float | int]:
    """The parameters every vehicle gets before take-off: the offboard-loss failsafe matching
    ``flight.on_lost``, then ``flight.autopilot_params`` (which win)."""
    return {
        "COM_OBL_RC_ACT": OFFBOARD_LOSS_ACTION[scenario.flight.on_lost],
        **scenario.flight.autopilot_params,
    }

"""Each default lives once, in the scenario model (config.py): the settings built from a scenario
(wiring.py) declare none of their own, so a change of a default cannot miss a copy."""

import dataclasses
import inspect

from pydantic import BaseModel

from mission_runner import config
from mission_runner.enclosing import EnclosingParams
from mission_runner.enclosing.ekf import FilterSettings
from mission_runner.runner.controller import ControllerSettings
from mission_runner.runner.inbox import StepInbox

#: The controller's own tunings: the scenario has no setting for them.
CONTROLLER_TUNINGS = {
    "release_s",
    "odometry_extrapolate_s",
    "odometry_timeout_s",
    "lost_after_missed_steps",
    "altitude_gain_per_s",
}


def scenario_setting_names():
    models = [
        value
        for value in vars(config).values()
        if isinstance(value, type) and issubclass(value, BaseModel)
    ]
    return {name for model in models for name in model.model_fields}


def defaulted(settings):
    return {
        field.name
        for field in dataclasses.fields(settings)
        if field.default is not dataclasses.MISSING
        or field.default_factory is not dataclasses.MISSING
    }


def test_controller_settings_default_only_what_the_scenario_does_not_set():
    assert defaulted(ControllerSettings) == CONTROLLER_TUNINGS
    assert not CONTROLLER_TUNINGS & scenario_setting_names()


def test_the_inbox_takes_the_member_timeout_from_the_scenario():
    parameter = inspect.signature(StepInbox).parameters["member_timeout_steps"]
    assert parameter.default is inspect.Parameter.empty


def test_the_algorithms_parameters_and_filter_settings_have_no_defaults():
    """Built from the scenario (wiring.algorithm_params, wiring.filter_settings): a default of
    their own had already drifted from the model's (handover_std_m 1.0 against 2.0)."""
    assert defaulted(EnclosingParams) == set()
    assert defaulted(FilterSettings) == set()

"""The paper's enclosing algorithm (numpy only): coupled-oscillator pattern, affine shaping, RLSE
relative localization from range + displacement, saturated consensus tracking.

One implementation, two faces: :class:`VehicleEnclosing` (one drone, what the flying controller
calls) and :class:`SwarmEnclosing` (every drone, batched, what the simulator calls), both thin
wrappers over :func:`enclosing_step`.
"""

from .errors import EnclosingError
from .oscillator import splay_spacing_error
from .shape import IDENTITY, affine_matrix, desired_offsets
from .step import (
    TARGET_SLOT,
    EnclosingParams,
    EnclosingState,
    StepInputs,
    StepOutputs,
    enclosing_step,
)
from .swarm import SwarmEnclosing
from .target import LOST, OBSERVED, PREDICTED, TargetEstimate, TargetTrack, track_target
from .vehicle import NeighbourReport, TargetReport, VehicleCommand, VehicleEnclosing

__all__ = [
    "IDENTITY",
    "LOST",
    "OBSERVED",
    "PREDICTED",
    "TARGET_SLOT",
    "EnclosingError",
    "EnclosingParams",
    "EnclosingState",
    "NeighbourReport",
    "StepInputs",
    "StepOutputs",
    "SwarmEnclosing",
    "TargetEstimate",
    "TargetReport",
    "TargetTrack",
    "VehicleCommand",
    "VehicleEnclosing",
    "affine_matrix",
    "desired_offsets",
    "enclosing_step",
    "splay_spacing_error",
    "track_target",
]

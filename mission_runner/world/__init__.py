"""The simulated world a mission flies in: the moving target, UWB ranging between vehicles and
the target tracker (:mod:`.world`), around the bundled emulator's vehicles or, through the range
aid (:mod:`mission_runner.runner.ranges`), around real autopilots' ground truth. Mission code,
not vehicle code: the emulator (``sitl``) knows nothing of it and offers only hooks (a physics-step
listener, ground truth, faults).
"""

from .world import World, step_measurements

__all__ = ["World", "step_measurements"]

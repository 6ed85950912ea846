"""Errors of the enclosing algorithm.

The algorithm package imports numpy only, so its errors derive from the builtin ``ValueError``
and not from :class:`mission_runner.errors.MissionRunnerError`: a handler of the latter does not
catch them; catch :class:`EnclosingError` (or ``ValueError``).
"""


class EnclosingError(ValueError):
    """Invalid algorithm parameters or inputs of the wrong shape."""

"""Errors of the enclosing algorithm.

The algorithm package imports numpy only, so its errors derive from the builtin ``ValueError``;
callers that catch :class:`mission_runner.errors.MissionRunnerError` also catch
:class:`EnclosingError` through ``mission_runner.errors``' re-export.
"""


class EnclosingError(ValueError):
    """Invalid algorithm parameters or inputs of the wrong shape."""

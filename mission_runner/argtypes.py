"""Argument types for the command line: each turns a word into a value or raises
``argparse.ArgumentTypeError`` with what is wrong, which argparse prints beside the option."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None


def positive_int(text: str) -> int:
    value = integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    value = integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def port(text: str) -> int:
    value = positive_int(text)
    if value > 65535:
        raise argparse.ArgumentTypeError(f"not a UDP port: {value}")
    return value


def port_or_zero(text: str) -> int:
    """A UDP port, or 0 for any free one."""
    return 0 if text == "0" else port(text)


def finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return value


def positive_float(text: str) -> float:
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def non_negative_float(text: str) -> float:
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def at_most(parse: Callable[[str], float], limit: float) -> Callable[[str], float]:
    """``parse``, then refuse a value above ``limit``: the option's bound, named in the error."""

    def bounded(text: str) -> float:
        value = parse(text)
        if value > limit:
            raise argparse.ArgumentTypeError(f"must be <= {limit:g}, got {text}")
        return value

    return bounded

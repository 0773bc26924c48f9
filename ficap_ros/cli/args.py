"""Argument types and exit codes shared by the verbs: each type returns the parsed value or raises
``argparse.ArgumentTypeError`` with one line, which argparse prints before exiting with 2.

Every number a verb takes has a range: the memory and time a value implies (frames to render, a
blur kernel, a window in nanoseconds) stay bounded, and no value overflows what it is turned into.
"""

from __future__ import annotations

import argparse
import math
from typing import Callable

__all__ = ["EXIT_FRAMES_LOST", "POSE_METHOD_CHOICES", "ROW_ORDERS", "int_at_least", "positive_int",
           "non_negative_int", "finite_float", "positive_float", "non_negative_float", "duration_ms",
           "offset_ms", "time_window", "float_in", "int_in", "seed", "frame_count", "frame_rate",
           "max_dt_ms", "MAX_FRAMES", "MAX_SEED"]

#: Exit code of a verb that finished but lost frames to a damaged (cut, corrupt) input.
EXIT_FRAMES_LOST = 3
#: ``--method``'s choices: ``ficap_ros.vision.pose.POSE_METHODS`` (named here so that ``--help``
#: does not import the pipeline; a test keeps them equal).
POSE_METHOD_CHOICES = ("joint", "paper", "naive")
#: Most frames a verb renders (``synth``, ``demo``): an hour at 30 fps.
MAX_FRAMES = 108_000
#: Largest random seed (numpy's generators take non-negative seeds; 32 bits are plenty).
MAX_SEED = 2**32 - 1
#: ``--row-order``'s choices: ``geometry.camera.ROW_ORDERS``, named here so that parsing the
#: command line does not import the geometry (and OpenCV).
ROW_ORDERS = ("top_to_bottom", "bottom_to_top")


def int_at_least(text: str, least: int) -> int:
    """An integer >= ``least`` for argparse (``ArgumentTypeError`` with one line otherwise)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"expected at least {least}, got {value}")
    return value


def positive_int(text: str) -> int:
    """argparse type for counts (frames, pairs): an integer >= 1."""
    return int_at_least(text, 1)


def non_negative_int(text: str) -> int:
    """argparse type for a count that may be 0 (retries): an integer >= 0."""
    return int_at_least(text, 0)


def finite_float(text: str) -> float:
    """argparse type for a real number: NaN and infinity are refused (they poison every result)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """argparse type for a rate or a size: a finite number > 0."""
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {value}")
    return value


def non_negative_float(text: str) -> float:
    """argparse type for a size or a duration that may be 0: a finite number >= 0."""
    value = finite_float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {value}")
    return value


def _ms_within(text: str, low: float, high: float) -> float:
    value = finite_float(text)
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"expected a number of ms in [{low:g}, {high:g}], got {value:g}")
    return value


def duration_ms(text: str) -> float:
    """argparse type for a camera's exposure or readout time: ms in [0, 1000]
    (``geometry.camera.CameraTiming``'s range)."""
    return _ms_within(text, 0.0, 1000.0)


def offset_ms(text: str) -> float:
    """argparse type for a stamp offset: ms in [-1000, 1000] (``CameraTiming``'s range)."""
    return _ms_within(text, -1000.0, 1000.0)


def time_window(text: str) -> tuple[float, float]:
    """argparse type for ``START:END`` seconds (``replay.parse_window``)."""
    from ficap_ros.tools.replay import parse_window

    try:
        return parse_window(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def float_in(low: float, high: float, low_open: bool = False,
             high_open: bool = False) -> Callable[[str], float]:
    """argparse type for a finite number in [low, high] (``low_open``/``high_open``: excluded)."""
    def parse(text: str) -> float:
        value = finite_float(text)
        if value < low or value > high or (low_open and value == low) or (
                high_open and value == high):
            raise argparse.ArgumentTypeError(
                f"expected a number in {'(' if low_open else '['}{low:g}, {high:g}"
                f"{')' if high_open else ']'}, got {text}")
        return value

    parse.__name__ = "number"
    return parse


def int_in(low: int, high: int) -> Callable[[str], int]:
    """argparse type for an integer in [low, high]."""
    def parse(text: str) -> int:
        value = int_at_least(text, low)
        if value > high:
            raise argparse.ArgumentTypeError(f"expected at most {high}, got {text}")
        return value

    parse.__name__ = "integer"
    return parse


#: A random seed: 0 to ``MAX_SEED``.
seed = int_in(0, MAX_SEED)
#: Frames to render: 1 to ``MAX_FRAMES``.
frame_count = int_in(1, MAX_FRAMES)
#: A frame rate, Hz: beyond any camera above 1000, and nanosecond stamps need far less.
frame_rate = float_in(0.01, 1000.0)
#: Largest stamp difference of a pair, ms: above 0, at most a minute.
max_dt_ms = float_in(0.0, 60_000.0, low_open=True)

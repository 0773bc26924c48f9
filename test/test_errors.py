"""ficap_ros.errors: one hierarchy (every error a user can cause is a FicapError), and ``one_line``,
the one line of any error that a message quotes."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ficap_ros import errors
from ficap_ros.errors import (
    BagError,
    CalibrationError,
    ConfigError,
    FicapError,
    ImageError,
    IntrinsicsError,
    ModelError,
    OutputError,
    WorkerError,
    one_line,
)

KINDS = (ModelError, ImageError, IntrinsicsError, ConfigError, CalibrationError, BagError,
         OutputError, WorkerError)


def test_every_kind_is_a_ficap_error_and_exported() -> None:
    assert set(errors.__all__) == {k.__name__ for k in KINDS} | {"FicapError", "one_line",
                                                                 "missing_module"}
    for kind in KINDS:
        assert issubclass(kind, FicapError) and issubclass(FicapError, Exception)
        assert kind.__doc__  # each says what it is for
    assert not issubclass(FicapError, (ValueError, OSError))  # caught only on purpose


def test_one_line_of_a_ficap_error_is_its_message() -> None:
    assert one_line(BagError("cut.mcap is truncated")) == "cut.mcap is truncated"
    assert one_line(BagError("cut.mcap is truncated"), typed=True) == "cut.mcap is truncated"
    assert one_line(ConfigError("  padded  ")) == "padded"


def test_one_line_of_another_error() -> None:
    trace = RuntimeError("Task failed: segment 3\n  File 'x.py', line 2\nMemoryError: out of memory")
    assert one_line(trace) == "Task failed: segment 3"
    assert one_line(trace, typed=True) == "RuntimeError: MemoryError: out of memory"
    assert one_line(KeyError()) == "KeyError"  # no message: its type
    assert one_line(KeyError(), typed=True) == "KeyError:"
    assert one_line(OSError(28, "No space left on device")) == "[Errno 28] No space left on device"


@given(st.text(), st.booleans(), st.sampled_from([ValueError, RuntimeError, BagError, OSError]))
def test_one_line_is_one_line(message: str, typed: bool, kind: type[Exception]) -> None:
    line = one_line(kind(message), typed=typed)
    assert not any(c in line for c in "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029")
    assert line == line.strip() or line.endswith(":")
    if message.strip() and not typed:
        assert line == message.strip().splitlines()[0]
    if not message.strip() and not (typed and kind is not BagError):
        assert line == kind.__name__


@pytest.mark.parametrize("kind", KINDS)
def test_a_ficap_error_caught_as_the_root(kind: type[FicapError]) -> None:
    with pytest.raises(FicapError, match="bad"):
        raise kind("bad")


def test_a_missing_module_is_one_line_naming_what_to_install() -> None:
    from ficap_ros.errors import missing_module

    line = missing_module(ModuleNotFoundError("No module named 'rosbags.highlevel'",
                                              name="rosbags.highlevel"))
    assert line == ("the Python module rosbags is not installed (pip install rosbags, or rosdep "
                    "key python3-rosbags-pip)")
    assert "\n" not in missing_module(ModuleNotFoundError("x", name="somethingelse"))
    assert "pip install pupil-apriltags)" in missing_module(
        ModuleNotFoundError("x", name="pupil_apriltags"))

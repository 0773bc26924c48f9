"""ficap_ros.cli.args: the argument types every verb uses (a value or one argparse line, never a
traceback), and the verbs refusing non-finite, huge, negative or zero numbers with exit 2 naming
the flag."""

from __future__ import annotations

import argparse

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ficap_ros.cli.main import main


@pytest.mark.parametrize("argv", [
    ["calibrate", "x.csv", "--frontal", "0:2", "--out", "c.yaml", "--camera-mount", "0", "0",
     "0", "0", "0", "0", "nan"],
    ["calibrate", "x.csv", "--frontal", "0:2", "--out", "c.yaml", "--max-dt-ms", "inf"],
    ["evaluate", "--truth", "a.csv", "--estimate", "b.csv", "--max-dt-ms", "nan"],
    ["synth", "--out", "s", "--resolution", "100000x100000"],
    ["synth", "--out", "s", "--fps", "inf"],
])
def test_non_finite_and_huge_arguments_are_refused(argv: list[str],
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and ("finite" in err or "budget" in err)


@pytest.mark.parametrize("argv", [
    ["evaluate", "--truth", "t.csv", "--estimate", "e.csv", "--max-dt-ms", "-5"],
    ["evaluate", "--truth", "t.csv", "--estimate", "e.csv", "--max-dt-ms", "0"],
    ["calibrate", "l.csv", "--reference", "b:/t", "--out", "c.yaml", "--max-dt-ms", "-5"],
    ["kit", "--out", "k", "--shell-thickness-mm", "nan"],
    ["kit", "--out", "k", "--shell-thickness-mm", "-1"],
])
def test_negative_or_zero_tolerances_are_bad_arguments(argv: list[str],
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """Exit 2 naming the flag, like NaN: a tolerance or a thickness must be positive."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert f"argument {argv[-2]}:" in capsys.readouterr().err


@given(st.integers(-10**6, 10**6), st.integers(-5, 5))
def test_int_at_least_is_the_integer_or_one_line(value: int, least: int) -> None:
    from ficap_ros.cli.args import int_at_least

    if value >= least:
        assert int_at_least(str(value), least) == value
        assert int_at_least(f" {value} ", least) == value  # int() takes surrounding blanks
    else:
        with pytest.raises(argparse.ArgumentTypeError, match=f"expected at least {least}, got {value}"):
            int_at_least(str(value), least)


@pytest.mark.parametrize("text", ["", "1.5", "one", "1e3", "0x10", "nan"])
def test_counts_refuse_what_is_not_an_integer(text: str) -> None:
    from ficap_ros.cli.args import non_negative_int, positive_int

    for kind in (positive_int, non_negative_int):
        with pytest.raises(argparse.ArgumentTypeError, match=f"expected an integer, got {text!r}"):
            kind(text)


def test_positive_and_non_negative_counts() -> None:
    from ficap_ros.cli.args import non_negative_int, positive_int

    assert positive_int("1") == 1 and non_negative_int("0") == 0
    with pytest.raises(argparse.ArgumentTypeError, match="at least 1, got 0"):
        positive_int("0")
    with pytest.raises(argparse.ArgumentTypeError, match="at least 0, got -1"):
        non_negative_int("-1")


@given(st.floats(allow_nan=False, allow_infinity=False))
def test_finite_floats_round_trip_through_their_text(value: float) -> None:
    from ficap_ros.cli.args import finite_float, non_negative_float, positive_float

    assert finite_float(repr(value)) == value
    for kind, ok in ((positive_float, value > 0), (non_negative_float, value >= 0)):
        if ok:
            assert kind(repr(value)) == value
        else:
            with pytest.raises(argparse.ArgumentTypeError, match="expected a"):
                kind(repr(value))


@pytest.mark.parametrize("text", ["nan", "NaN", "inf", "-inf", "Infinity", "1e400"])
def test_non_finite_numbers_are_refused_by_every_float_type(text: str) -> None:
    from ficap_ros.cli.args import finite_float, non_negative_float, positive_float

    for kind in (finite_float, positive_float, non_negative_float):
        with pytest.raises(argparse.ArgumentTypeError, match=f"expected a finite number, got {text!r}"):
            kind(text)
    with pytest.raises(argparse.ArgumentTypeError, match="expected a number, got 'fast'"):
        finite_float("fast")


@given(st.floats(0.0, 1e5), st.floats(0.0, 1e5))
def test_time_windows_parse_start_and_end(a: float, b: float) -> None:
    from ficap_ros.cli.args import time_window

    start, end = min(a, b), max(a, b)
    if end > start:
        assert time_window(f"{start!r}:{end!r}") == (start, end)
    with pytest.raises(argparse.ArgumentTypeError):
        time_window(f"{end!r}")  # no colon: no window


def test_time_window_edges() -> None:
    from ficap_ros.cli.args import time_window

    assert time_window("0:2.9") == (0.0, 2.9)
    assert time_window("2:") == (2.0, float("inf")) and time_window(":3") == (0.0, 3.0)
    for bad in ("3:1", "a:b", "1:1", "-1:2", ":", "nan:1", "0:inf"):
        with pytest.raises(argparse.ArgumentTypeError):
            time_window(bad)


def test_bounded_numbers_and_seeds() -> None:
    """Every numeric flag has a range: the memory or time it implies stays bounded, and no value
    overflows what it is turned into (a seed numpy refuses, a window in nanoseconds)."""
    import argparse

    from ficap_ros.cli.args import (
        MAX_FRAMES,
        float_in,
        frame_count,
        int_in,
        max_dt_ms,
        seed,
        time_window,
    )

    assert float_in(0.0, 20.0, low_open=True)("20") == 20.0
    for text in ("0", "20.5", "nan", "1e308"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"expected"):
            float_in(0.0, 20.0, low_open=True)(text)
    assert int_in(2, 9)("9") == 9
    with pytest.raises(argparse.ArgumentTypeError, match="at most 9"):
        int_in(2, 9)("10")
    assert seed("0") == 0 and seed(str(2**32 - 1)) == 2**32 - 1
    for text in ("-1", str(2**32), "1.5"):
        with pytest.raises(argparse.ArgumentTypeError):
            seed(text)
    assert frame_count(str(MAX_FRAMES)) == MAX_FRAMES
    with pytest.raises(argparse.ArgumentTypeError):
        frame_count("99999999999999999999")
    with pytest.raises(argparse.ArgumentTypeError):
        max_dt_ms("1e308")
    with pytest.raises(argparse.ArgumentTypeError, match="at most 1e"):
        time_window("0:1e308")


def test_camera_timing_arguments_are_the_timings_ranges() -> None:
    """``duration_ms`` and ``offset_ms`` take what ``CameraTiming`` takes; the row orders are
    the geometry's (named in cli.args so parsing needs no OpenCV)."""
    from ficap_ros.cli.args import ROW_ORDERS, duration_ms, offset_ms
    from ficap_ros.geometry import camera

    assert ROW_ORDERS == camera.ROW_ORDERS
    assert duration_ms("0") == 0.0 and duration_ms("1000") == 1000.0 and duration_ms("16.7") == 16.7
    assert offset_ms("-1000") == -1000.0 and offset_ms("19.35") == 19.35
    for fn, bad in ((duration_ms, "-0.1"), (duration_ms, "1000.5"), (duration_ms, "nan"),
                    (offset_ms, "-1001"), (offset_ms, "inf"), (offset_ms, "x")):
        with pytest.raises(argparse.ArgumentTypeError):
            fn(bad)
    for value in ("0", "1000", "16.7"):
        camera.CameraTiming(exposure_ms=duration_ms(value), readout_ms=duration_ms(value))

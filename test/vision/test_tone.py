"""The sRGB curve as the photometric fit models it: its encoding and slope, its clipping and toe, and
its inverse, against the renderer's curves (``tone_curve``, ``srgb_to_linear``)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ficap_ros.errors import ConfigError
from ficap_ros.vision.tone import (
    SRGB_ENCODED_KNEE,
    SRGB_LINEAR_KNEE,
    srgb_encode_slope,
    srgb_to_linear,
    srgb_to_linear_scalar,
    tone_curve,
)


def test_encoding_is_the_renderers_srgb_curve_on_zero_to_one() -> None:
    v = np.concatenate([np.linspace(0.0, 1.0, 10001), [SRGB_LINEAR_KNEE, np.nextafter(SRGB_LINEAR_KNEE, 1.0)]])
    enc, _ = srgb_encode_slope(v)
    np.testing.assert_allclose(enc, tone_curve(v, "srgb"), rtol=0.0, atol=4e-16)
    assert enc[0] == 0.0 and abs(enc[-3] - 1.0) <= 2e-16
    # IEC 61966-2-1 at mid-grey, and continuous at the knee.
    assert srgb_encode_slope(np.array([0.5]))[0][0] == pytest.approx(0.735357, abs=1e-6)
    lo, hi = srgb_encode_slope(np.array([SRGB_LINEAR_KNEE, np.nextafter(SRGB_LINEAR_KNEE, 1.0)]))[0]
    assert hi - lo < 1e-9


def test_slope_is_the_encodings_derivative() -> None:
    v = np.concatenate([np.linspace(0.005, 0.995, 199), np.linspace(-0.1, 0.003, 11)])
    h = 1e-7
    enc_hi, _ = srgb_encode_slope(v + h)
    enc_lo, _ = srgb_encode_slope(v - h)
    _, slope = srgb_encode_slope(v)
    np.testing.assert_allclose(slope, (enc_hi - enc_lo) / (2 * h), rtol=1e-6)


def test_clipped_above_one_and_linear_below_zero() -> None:
    """At and above 1 the encoding is 1's and the slope 0 (a clipped highlight carries no level);
    below 0 the linear toe continues, with its slope 12.92."""
    v = np.array([1.0, 1.2, 7.0, -0.01, -0.5])
    enc, slope = srgb_encode_slope(v)
    assert (enc[:3] == srgb_encode_slope(np.array([1.0]))[0][0]).all() and (slope[:3] == 0.0).all()
    np.testing.assert_array_equal(enc[3:], 12.92 * v[3:])
    np.testing.assert_array_equal(slope[3:], 12.92)


@given(st.floats(0.0, 1.0))
def test_scalar_inverse_undoes_the_encoding(v: float) -> None:
    enc = float(srgb_encode_slope(np.array([v]))[0][0])
    assert srgb_to_linear_scalar(enc) == pytest.approx(v, rel=1e-12, abs=1e-15)


@given(st.floats(-2.0, 3.0))
def test_scalar_inverse_clips_and_agrees_with_the_array_inverse(y: float) -> None:
    got = srgb_to_linear_scalar(y)
    assert isinstance(got, float)
    clipped = min(max(y, 0.0), 1.0)
    assert got == pytest.approx(float(srgb_to_linear(np.array([clipped]))[0]), rel=1e-15, abs=1e-18)
    assert 0.0 <= got <= 1.0
    assert (got == clipped / 12.92) == (clipped <= SRGB_ENCODED_KNEE)


def test_unknown_tone_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="tone"):
        tone_curve(np.array([0.5]), "sepia")


@pytest.mark.parametrize("tone, gamma", [("srgb", 2.2), ("gamma", 1.8), ("gamma", 2.2), ("filmic", 2.2),
                                         ("linear", 2.2)])
def test_tone_curves_monotone_and_fix_black_and_white(tone: str, gamma: float) -> None:
    v = np.linspace(0.0, 1.0, 100_001)
    y = tone_curve(v, tone, gamma)
    assert y[0] == 0.0 and abs(y[-1] - 1.0) < 1e-12
    assert np.all(np.diff(y) > 0.0)  # strictly increasing
    assert np.all(tone_curve(np.array([-0.5, 2.0]), tone, gamma) == [0.0, 1.0])  # clipped
    if tone != "linear":
        assert tone_curve(np.array([0.18]), tone, gamma)[0] > 0.18  # lifts the mid-tones
    if tone == "srgb":
        assert np.allclose(srgb_to_linear(y), v, atol=1e-9)
        assert abs(tone_curve(np.array([0.5]), "srgb")[0] - 0.735357) < 1e-5  # IEC 61966-2-1
    if tone == "filmic":
        # An S-curve on the sRGB value: flatter than sRGB in the toe and the shoulder.
        s = tone_curve(v, "srgb")
        assert np.all(y[1:5000] < s[1:5000]) and np.all(y[-5000:-1] > s[-5000:-1])

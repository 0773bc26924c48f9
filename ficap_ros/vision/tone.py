"""Camera tone curves: how a camera maps linear light to its output values.

A real camera's lens blurs linear light and its tone curve then bends every black/white edge toward
the black; the renderer applies these curves (``tone_curve``, ``srgb_to_linear``) and the
photometric corner fit models the sRGB one (``srgb_encode_slope``, ``srgb_to_linear_scalar``).
Values are in [0, 1] on both sides: 0 -> 0, 1 -> 1, monotone.

The sRGB transfer function (IEC 61966-2-1): encoded = 12.92 linear up to ``SRGB_LINEAR_KNEE``,
1.055 linear^(1 / 2.4) - 0.055 above; its inverse switches at ``SRGB_ENCODED_KNEE``. The variants
here differ in clipping and in how they evaluate the power, and each keeps its own arithmetic: the
renderer's images and the fit's corners depend on it bit for bit.
"""

from __future__ import annotations

import numpy as np

from ficap_ros.errors import ConfigError

__all__ = ["TONES", "FILMIC_CONTRAST", "SRGB_LINEAR_KNEE", "SRGB_ENCODED_KNEE", "srgb_to_linear",
           "srgb_to_linear_scalar", "srgb_encode_slope", "tone_curve"]

#: Tone curves by name (``tone_curve``).
TONES = ("srgb", "gamma", "filmic", "linear")
#: Contrast of the ``filmic`` S-curve (its slope at mid-grey of the sRGB-encoded value).
FILMIC_CONTRAST = 1.5
#: Linear value where the sRGB curve turns from its linear toe to its power segment.
SRGB_LINEAR_KNEE = 0.0031308
#: The same point on the encoded side.
SRGB_ENCODED_KNEE = 0.04045


def srgb_to_linear(value: np.ndarray) -> np.ndarray:
    """Inverse of the sRGB transfer function (IEC 61966-2-1) on values in [0, 1], elementwise in
    the array's dtype (numpy's power)."""
    v = np.asarray(value)
    return np.where(v <= SRGB_ENCODED_KNEE, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(v.dtype, copy=False)


def srgb_to_linear_scalar(value: float) -> float:
    """Inverse of the sRGB transfer function of one value, clipped to [0, 1] first.

    On Python floats, so the power is the C library's ``pow`` (as numpy's scalars use; numpy's
    array power may round differently in the last bit): the photometric fit starts its levels
    from this.
    """
    y = min(max(value, 0.0), 1.0)
    return y / 12.92 if y <= SRGB_ENCODED_KNEE else ((y + 0.055) / 1.055) ** 2.4


def srgb_encode_slope(linear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sRGB encoding of linear values and its slope d encoded / d linear, for a model that is
    differentiated (the photometric fit).

    Values at and above 1 encode as 1 does (1.055 - 0.055: one float below 1.0), with slope 0
    (a clipped highlight says nothing about its level). Values below 0 continue on the linear toe
    (12.92 linear, slope 12.92), so a level fitted slightly below black keeps a gradient.

    Returns:
        (encoded, slope), arrays of ``linear``'s shape.
    """
    v = np.minimum(linear, 1.0)
    pos = np.maximum(v, SRGB_LINEAR_KNEE)
    hi = v > SRGB_LINEAR_KNEE
    enc = np.where(hi, 1.055 * pos ** (1.0 / 2.4) - 0.055, 12.92 * v)
    slope = np.where(hi, (1.055 / 2.4) * pos ** (1.0 / 2.4 - 1.0), 12.92)
    return enc, np.where(linear >= 1.0, 0.0, slope)


def tone_curve(linear: np.ndarray, tone: str = "srgb", gamma: float = 2.2) -> np.ndarray:
    """A camera tone curve on linear values in [0, 1] (clipped there): 0 -> 0, 1 -> 1, monotone.

    Args:
        linear: linear sensor output, 1 = the brightest code.
        tone: ``srgb`` (IEC 61966-2-1), ``gamma`` (``linear ** (1 / gamma)``), ``filmic`` (the
            sRGB value through the S-curve ``s**c / (s**c + (1 - s)**c)``, c = ``FILMIC_CONTRAST``:
            a toe that crushes blacks, a shoulder that rolls off highlights, mid-grey fixed) or
            ``linear``.
        gamma: exponent of ``gamma``.

    Returns:
        Encoded values in [0, 1], float64.
    """
    v = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    if tone == "linear":
        return v
    if tone == "gamma":
        return v ** (1.0 / float(gamma))
    s = np.where(v <= SRGB_LINEAR_KNEE, 12.92 * v, 1.055 * v ** (1.0 / 2.4) - 0.055)
    s = np.where(v >= 1.0, 1.0, np.minimum(s, 1.0))  # exactly 1 at 1 (1.055 - 0.055 is not, in floats)
    if tone == "srgb":
        return s
    if tone == "filmic":
        a, b = s ** FILMIC_CONTRAST, (1.0 - s) ** FILMIC_CONTRAST
        return a / (a + b)
    raise ConfigError(f"tone must be one of {', '.join(TONES)}, got {tone!r}")

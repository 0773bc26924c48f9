"""Camera tone curves: how a camera maps linear light to its output values.

A real camera's lens blurs linear light and its tone curve then bends every black/white edge toward
the black; the renderer applies these curves and the photometric corner fit inverts them.
Values are in [0, 1] on both sides: 0 -> 0, 1 -> 1, monotone.
"""

from __future__ import annotations

import numpy as np

from ficap_ros.errors import ConfigError

__all__ = ["TONES", "FILMIC_CONTRAST", "srgb_to_linear", "tone_curve"]

#: Tone curves by name (``tone_curve``).
TONES = ("srgb", "gamma", "filmic", "linear")
#: Contrast of the ``filmic`` S-curve (its slope at mid-grey of the sRGB-encoded value).
FILMIC_CONTRAST = 1.5


def srgb_to_linear(value: np.ndarray) -> np.ndarray:
    """Inverse of the sRGB transfer function (IEC 61966-2-1) on values in [0, 1]."""
    v = np.asarray(value)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(v.dtype, copy=False)


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
    s = np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1.0 / 2.4) - 0.055)
    s = np.where(v >= 1.0, 1.0, np.minimum(s, 1.0))  # exactly 1 at 1 (1.055 - 0.055 is not, in floats)
    if tone == "srgb":
        return s
    if tone == "filmic":
        a, b = s ** FILMIC_CONTRAST, (1.0 - s) ** FILMIC_CONTRAST
        return a / (a + b)
    raise ConfigError(f"tone must be one of {', '.join(TONES)}, got {tone!r}")

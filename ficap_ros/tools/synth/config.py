"""How a frame is rendered (``RenderConfig``) and what comes out (``RenderedFrame``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import ROW_ORDERS, CameraModel, CameraTiming
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth.lighting import LIGHTINGS, LIGHTS
from ficap_ros.tools.synth.scene import HEAD_CENTRE_M, HEAD_SEMI_AXES_M
from ficap_ros.vision.tone import TONES

__all__ = ["RENDER_VERSION", "PSF_SIGMA_1080P_PX", "REALISTIC", "MAX_BLUR_PX", "MAX_EXPOSURE_MS",
           "MAX_GAIN", "MAX_GAMMA", "default_psf_sigma_px",
           "RenderConfig", "RenderedFrame"]

#: Raise it with every change that moves rendered pixels for the same options: ``ficap demo``'s
#: cached sample drive is keyed on it.
RENDER_VERSION = 3
#: Default lens PSF: Gaussian sigma at 1080p, px; other heights scale with sqrt(height / 1080).
PSF_SIGMA_1080P_PX = 0.7
#: The realistic camera (``RenderConfig(**REALISTIC)``): the default lens PSF and the sRGB tone curve.
REALISTIC: dict[str, object] = {"psf_sigma_px": None, "tone": "srgb"}
#: Largest lens blur (Gaussian sigma, defocus disc radius), px: beyond it a tag of any rendered
#: size is a smudge, and the blur's kernel grows with its square.
MAX_BLUR_PX = 50.0
#: Longest exposure, ms (ten seconds: far beyond a driving camera's).
MAX_EXPOSURE_MS = 10_000.0
#: Largest sensor gain and tone-curve exponent.
MAX_GAIN = 1000.0
MAX_GAMMA = 10.0


def default_psf_sigma_px(height_px: int) -> float:
    """The default lens PSF sigma for an image height: 0.7 px at 1080p, times sqrt(height / 1080).

    A lens blur of a fixed angular size shrinks in pixels with a coarser sensor (linear in the
    height), but cameras with fewer pixels tend to carry cheaper lenses: the square root splits
    the difference (540p: 0.49 px), inside the 0.4-0.9 px that sharp automotive and webcam
    lenses show.
    """
    return PSF_SIGMA_1080P_PX * math.sqrt(max(int(height_px), 1) / 1080.0)


@dataclass(frozen=True)
class RenderConfig:
    """How a frame is rendered (the chain is in ``ficap_ros.tools.synth``'s docstring).

    Attributes:
        lighting: one of ``LIGHTINGS``.
        psf_sigma_px: Gaussian lens PSF sigma, px, applied in linear light; None = the realistic
            default for the image height (``default_psf_sigma_px``, the default), 0 = none.
        defocus_radius_px: radius of a defocus disc (pillbox) PSF, px, convolved with the
            Gaussian; 0 = none.
        exposure_ms: exposure time, ms; None = the lighting's nominal exposure. The collected
            charge scales with it, and with motion (``render`` given a pose function) it is the
            window the pose is integrated over.
        gain: sensor gain (output = gain * charge / full well, clipped at 1); None = auto: the
            lighting's gain times nominal / actual exposure, at least 1 (a shutter-priority
            auto-exposure): a shorter exposure keeps the brightness with more noise, a longer one
            than the light allows at base gain overexposes.
        noise: shot noise (Poisson, Gaussian approximation) and read noise.
        full_well_e: full-well capacity, electrons (8000: a 2-3 um CMOS pixel).
        read_noise_e: read noise, electrons rms.
        tone: tone curve: ``srgb`` (IEC 61966-2-1), ``gamma`` (``value ** (1 / gamma)``),
            ``filmic`` (an S-curve on the sRGB value, ``FILMIC_CONTRAST``) or ``linear`` (none: an
            idealised camera whose grey levels are proportional to light); default ``srgb``.
        gamma: the exponent of the ``gamma`` tone curve (2.2 = ``value ** (1 / 2.2)``).
        motion_subframes: sub-frames averaged over the exposure when rendering motion; 0 = auto
            (odd, enough that no corner moves more than half a pixel between two; at most 31).
            With a rolling shutter: the sub-steps of each row's exposure (auto: as many, not
            necessarily odd), or without motion blur the samples over the readout (auto: a
            quarter pixel of corner travel apart; ``synth.shutter.substeps``).
        readout_ms: rolling shutter (``synth.shutter``, when the pose is a function of time):
            time between the first and the last row's exposure centres, ms; 0 = a global shutter.
        row_order: ``top_to_bottom`` or ``bottom_to_top`` (``geometry.camera.ROW_ORDERS``).
        motion_blur: with a pose function, each row integrates the motion over the exposure;
            False: each row sees the pose at its own instant (a rolling shutter without blur; a
            global shutter then renders the pose at 0).
        jpeg_quality: JPEG round trip at this quality (1..100), or None.
        color: BGR output (hair and interior tinted) instead of grey.
        supersample: supersampling factor per axis for faces (1..8); faces whose tag edge is
            longer than 240/supersample px use less (at least 2), which keeps big faces cheap.
        head: draw the head occluder.
        background: draw the car interior (else a flat grey).
        background_seed: seed of the static background and hair texture (keep it fixed over a video).
        head_centre_m, head_semi_axes_m: head ellipsoid in the cap frame, metres.
    """

    lighting: str = "neutral"
    # The realistic camera by default (lens PSF for the height, sRGB): what real cameras do to
    # corners. ``psf_sigma_px=0, tone="linear"`` is the idealised camera.
    psf_sigma_px: float | None = None
    defocus_radius_px: float = 0.0
    exposure_ms: float | None = None
    gain: float | None = None
    noise: bool = True
    full_well_e: float = 8000.0
    read_noise_e: float = 4.0
    tone: str = "srgb"
    gamma: float = 2.2
    motion_subframes: int = 0
    readout_ms: float = 0.0
    row_order: str = "top_to_bottom"
    motion_blur: bool = True
    jpeg_quality: int | None = None
    color: bool = False
    supersample: int = 4
    head: bool = True
    background: bool = True
    background_seed: int = 0
    head_centre_m: tuple[float, float, float] = HEAD_CENTRE_M
    head_semi_axes_m: tuple[float, float, float] = HEAD_SEMI_AXES_M

    def __post_init__(self) -> None:
        if self.lighting not in LIGHTINGS:
            raise ConfigError(f"lighting must be one of {', '.join(LIGHTINGS)}, got {self.lighting!r}")
        if self.tone not in TONES:
            raise ConfigError(f"tone must be one of {', '.join(TONES)}, got {self.tone!r}")

        def finite(name: str, low: float, strict: bool = False, optional: bool = False,
                   high: float = math.inf) -> None:
            value = getattr(self, name)
            if value is None and optional:
                return
            try:
                v = float(value)
            except (TypeError, ValueError, OverflowError):
                raise ConfigError(f"{name} must be a number, got {value!r}") from None
            if not math.isfinite(v) or v < low or (strict and v == low) or v > high:
                raise ConfigError(f"{name} must be finite, {'>' if strict else '>='} {low}"
                                  f"{f' and <= {high:g}' if math.isfinite(high) else ''}, got {value}")

        finite("psf_sigma_px", 0.0, optional=True, high=MAX_BLUR_PX)
        finite("defocus_radius_px", 0.0, high=MAX_BLUR_PX)
        finite("exposure_ms", 0.0, strict=True, optional=True, high=MAX_EXPOSURE_MS)
        finite("gain", 0.0, strict=True, optional=True, high=MAX_GAIN)
        finite("full_well_e", 0.0, strict=True)
        finite("read_noise_e", 0.0)
        finite("gamma", 0.0, strict=True, high=MAX_GAMMA)
        finite("readout_ms", 0.0, high=1000.0)
        if self.row_order not in ROW_ORDERS:
            raise ConfigError(f"row_order must be one of {', '.join(ROW_ORDERS)}, got {self.row_order!r}")
        if not 0 <= int(self.motion_subframes) <= 255:
            raise ConfigError(f"motion_subframes must be in 0..255, got {self.motion_subframes}")
        if self.jpeg_quality is not None and not 1 <= int(self.jpeg_quality) <= 100:
            raise ConfigError(f"jpeg_quality must be in 1..100, got {self.jpeg_quality}")
        if not 1 <= int(self.supersample) <= 8:
            raise ConfigError(f"supersample must be in 1..8, got {self.supersample}")
        if len(self.head_semi_axes_m) != 3 or min(self.head_semi_axes_m) <= 0.0:
            raise ConfigError("head_semi_axes_m must be three positive lengths")
        if len(self.head_centre_m) != 3:
            raise ConfigError("head_centre_m must have three coordinates")

    def psf_sigma_for(self, height_px: int) -> float:
        """The Gaussian PSF sigma used for an image of this height, px."""
        return default_psf_sigma_px(height_px) if self.psf_sigma_px is None else float(self.psf_sigma_px)

    @property
    def timing(self) -> CameraTiming:
        """The camera timing of frames rendered from a pose function, stamped at the middle row's
        mid-exposure: the exposure (0 without motion blur: rows are instants), the readout and
        the row order."""
        exposure_ms = self.exposure_and_gain()[0] if self.motion_blur else 0.0
        return CameraTiming(exposure_ms, float(self.readout_ms), self.row_order)

    def exposure_and_gain(self) -> tuple[float, float]:
        """(exposure_ms, gain) actually used (auto values resolved)."""
        light = LIGHTS[self.lighting]
        exposure = light.exposure_ms if self.exposure_ms is None else float(self.exposure_ms)
        if self.gain is not None:
            return exposure, float(self.gain)
        # Shutter priority: the gain makes up for a shorter exposure; it cannot go below the
        # sensor's base gain 1, so an exposure longer than the light needs clips the whites.
        return exposure, max(1.0, light.gain * light.exposure_ms / exposure)


@dataclass(frozen=True)
class RenderedFrame:
    """A rendered image with its exact ground truth.

    Attributes:
        image: uint8, (H, W) grey or (H, W, 3) BGR.
        T_cam_cap: the true cap pose in the camera optical frame (metres).
        corners_px: tag id -> (4, 2) exact projected outer corners (OpenCV order and pixel
            convention, distorted image) of every front-facing tag, even if hidden or off-image.
        visible_fraction: tag id -> share of the tag square that is inside the image and not hidden
            by the head or other faces (same keys as ``corners_px``).
        camera: the camera the frame was rendered for.
    """

    image: np.ndarray
    T_cam_cap: Transform
    corners_px: dict[int, np.ndarray]
    visible_fraction: dict[int, float] = field(default_factory=dict)
    camera: CameraModel | None = None

    def visible_ids(self, min_fraction: float = 0.999) -> list[int]:
        """Ids whose visible fraction is at least ``min_fraction``."""
        return sorted(k for k, v in self.visible_fraction.items() if v >= min_fraction)

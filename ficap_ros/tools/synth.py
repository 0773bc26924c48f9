"""Rendered Fi-Cap frames with exact ground truth, and naturalistic driving head motion.

Renderer (``render``): any ``CapModel`` seen by any ``CameraModel`` at a known ``T_cam_cap``,
formed the way a camera forms an image, in this order (``RenderConfig`` holds every knob):

1. **Scene radiance in linear light**, in units of the sensor's full well at the lighting's nominal
   exposure. Every front-facing face (40 mm white square, 32 mm tag36h11 centred, as drawn by
   ``cv2.aruco.generateImageMarker``, upright: image top row along the model's TL->TR edge) is
   drawn by a per-face homography, supersampled (3-8x) over the face's bounding box and
   box-filtered down (``cv2.INTER_AREA``): each pixel integrates linear light over its area, so the
   tag's outer black corners sit exactly at ``camera.project(T_cam_cap.apply(c))`` in OpenCV's
   pixel convention (pixel centres at integers; an edge within 0.03 px at any sub-pixel phase).
   White paper reflects 1, black ink 0.05 of it. Back faces are culled; front faces are painted
   far to near. A dark, hair-textured head ellipsoid (and neck) fixed in the cap frame hides faces
   behind it with a per-pixel depth test; a static seeded car interior behind
   (``RenderConfig.background_seed``). Lighting ``neutral`` (mostly a lamp beside the camera,
   lighting each point of a face by cos(incidence) / distance^2, so an oblique face's near side is
   ~1.1x brighter; plus the cabin's diffuse light: white paper at 45-70 % of full well), ``high``
   (the paper's three spotlights on the cap: whites far past full well, glare lifts blacks) or
   ``low`` (one source at the driver's front-right, 1-10 % of full well, shadows); every preset adds veiling flare and goes through the whole chain.
2. **Lens PSF**, in linear light: a Gaussian (``psf_sigma_px``; realistic: 0.7 px at 1080p times
   sqrt(height/1080), 0.49 px at 540p) and optionally a defocus disc (``defocus_radius_px``).
3. **Motion blur** (optional): given a pose *function* of time instead of a pose, the frame
   averages sub-frames rendered over the exposure (``exposure_ms``); its ground truth is the pose
   at mid-exposure. ``naturalistic_motion(...).around(t)`` gives that function for a drive.
4. **Sensor**: charge = radiance x exposure / nominal exposure x full well (``full_well_e``),
   shot noise (Poisson, Gaussian limit), clipping at full well, read noise (``read_noise_e``),
   then ``gain`` (auto: the lighting's, scaled for a non-nominal exposure) into a 16-bit code
   that clips at 1: ``high`` light saturates, ``low`` light is dark and, with gain 2.5, noisy.
5. **Tone curve** (``tone``): ``srgb``, ``gamma`` (``gamma`` exponent), ``filmic`` (an S-curve
   on sRGB) or ``linear`` (an idealised camera), then **8 bit** by a lookup table.
6. **JPEG** (optional, ``jpeg_quality``; ``ficap synth`` always stores JPEG).

``RenderConfig()`` is the realistic camera (the PSF for the height, sRGB), which is also what
``ficap synth`` renders (``REALISTIC`` names it); ``psf_sigma_px=0, tone="linear"`` gives the
idealised camera.

Distorted cameras: the ideal pinhole with the same K is rendered on a canvas large enough, then
``cv2.remap``-ed (still in linear light, before the PSF) into the distorted image, so
``corners_px`` (``camera.project``) stays exact.

Why the order matters: a lens blurs light, the camera then bends it. After a tone curve the 50 %
grey point of a blurred black/white edge sits on the black side of the true edge (about 0.5-0.8
sigma for sRGB, further where whites clip), which is what corner methods that look for a grey
midpoint or a gradient peak inherit on real images. ``tone="linear", psf_sigma_px=0`` gives the
idealised images the geometry tests want. Cost (measured roughly on a loaded shared machine, one
thread, against the renderer before this chain): 540p about the same (105 vs 125 ms per frame
there), 1080p about 1.5x (289 vs 192 ms: big faces are now supersampled at least 3x); the camera
stages themselves are a few ms. Motion blur renders the scene once per sub-frame (odd count, <= 0.5
px of corner travel between two), so only fast motion costs more (+10 % over a drive at 8 ms).

Motion (``naturalistic_drive``): a list of ``DriveFrame`` with the true head orientation in the
frontal frame F (x forward, y left, z up), the head angles and the true cap pose in the camera, from
a ``DriveScene`` (camera, frontal frame, neck pivot, true cap-on-head rotation). It starts with
``frontal_s`` seconds of looking straight ahead, then mixes frontal driving with glances to the
mirrors and the instrument cluster (minimum-jerk transitions, dwells, small roll and translation).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.geometry.tag36h11 import TAG_CELLS
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.vision.tone import TONES, srgb_to_linear, tone_curve

__all__ = [
    "RENDER_VERSION",
    "LIGHTINGS",
    "HEAD_CENTRE_M",
    "HEAD_SEMI_AXES_M",
    "NECK_CENTRE_M",
    "NECK_SEMI_AXES_M",
    "RenderConfig",
    "RenderedFrame",
    "render",
    "DriveScene",
    "DriveFrame",
    "default_scene",
    "naturalistic_drive",
    "naturalistic_motion",
    "DriveMotion",
    "TONES",
    "tone_curve",
    "srgb_to_linear",
    "default_psf_sigma_px",
    "REALISTIC",
    "RESOLUTIONS",
]

#: Raise it with every change that moves rendered pixels for the same options: ``ficap demo``'s
#: cached sample drive is keyed on it (2: the physically ordered camera chain; 3: the neutral
#: light mostly a lamp beside the camera).
RENDER_VERSION = 3
#: Illumination modes of ``RenderConfig.lighting``.
LIGHTINGS = ("neutral", "high", "low")
#: Head ellipsoid (hair/skull) in the cap frame C, metres: centre and semi-axes along x, y, z.
#: Chosen so every face of the nominal cap lies just outside it (checked in test_synth): the back
#: of the skull is ~5 mm under the centre tag. Geometry note: with every face outside this convex
#: head, no front-facing face gets hidden by it over yaw +-80, 20 deg down to 10 up (faces turn away
#: before the head can cover them); a head that pokes past the cap rim does hide faces.
HEAD_CENTRE_M = (0.0225, 0.0, 0.0)
HEAD_SEMI_AXES_M = (0.11, 0.08, 0.10)
#: Neck (with the hairline) below the head, cap frame, metres: drawn and depth-tested like the head.
NECK_CENTRE_M = (0.02, 0.0, -0.15)
NECK_SEMI_AXES_M = (0.075, 0.075, 0.1)

#: Named resolutions of ``default_scene``.
RESOLUTIONS: dict[str, tuple[int, int]] = {
    "360p": (640, 360),
    "540p": (960, 540),
    "720p": (1280, 720),
    "1080p": (1920, 1080),
}

_CELLS_FACE = 10  # plus the 1-cell white quiet zone each side (40 mm face / 4 mm cells)
_NEAR_M = 0.02
# Reflectances (linear, relative to the white paper): matte black toner or ink reflects about 4-6 %
# of what white paper does; dark hair a few %, the neck (skin and hair) more.
_WHITE_ALBEDO = 1.0
_BLACK_ALBEDO = 0.05
_HAIR_ALBEDO = 0.05
_NECK_ALBEDO = 0.12

#: Default lens PSF: Gaussian sigma at 1080p, px; other heights scale with sqrt(height / 1080).
PSF_SIGMA_1080P_PX = 0.7
#: Levels of the 16-bit linear code the tone curve's lookup table is indexed by.
_CODE_MAX = 65535


@dataclass(frozen=True)
class _Light:
    """Per-mode light, linear, in units of the sensor's full well at the mode's nominal exposure.

    Irradiance on a face with outward normal n is ``ambient + diffuse * max(0, n . l)`` plus, from a
    lamp beside the lens, ``camera_lamp * cos(incidence) * (r_cap / r)^2`` at each point of the face
    (r: its distance from the camera, r_cap: the cap's; the auto-exposure meters on the cap, so the
    lamp's level at the cap's distance is fixed); a white face at that irradiance collects that
    share of the full well. The lamp lights each oblique face unevenly: its near side (nearer the
    camera, met less obliquely) is brighter, ~1.1x across a face seen at 60 deg at 0.6 m.
    ``flare`` is veiling glare (lens and windscreen scatter) added to every pixel; ``background``
    scales the car interior.
    ``exposure_ms`` and ``gain`` are what an auto-exposure settles on in that light.
    """

    toward_light_cam: tuple[float, float, float]  # unit vector toward the light, camera optical frame
    ambient: float
    diffuse: float
    flare: float
    background: float
    exposure_ms: float
    gain: float
    camera_lamp: float = 0.0


# Directions in the camera optical frame (x right, y down, z forward; the camera looks forward at
# the back of the head): neutral light comes from behind the camera, slightly above; the low-light
# source is outside at the driver's front-right, so faces turned away from it are in shadow.
# Neutral: most of the light on the back of the head comes from a lamp beside the camera (a cabin
# light over the rear camera, or the IR illuminator of a driver camera): it falls off with
# distance and incidence across each face, as blender_dev's neutral renders show
# (docs/benchmarks.md, "Uneven light across a face"); the rest is the cabin's diffuse light.
# Levels: neutral puts white paper at 45-70 % of full well (an auto-exposure's usual headroom;
# oblique faces get less of the lamp);
# high is brighter still, and its spotlights (``_spotlights``) push whites well past full well;
# low (night, one street lamp) collects 1-10 % and the camera answers with gain 2.5 and a long
# exposure, so the image is dark and noisy.
_LIGHTS: dict[str, _Light] = {
    "neutral": _Light((0.25, -0.45, -0.86), 0.15, 0.05, 0.004, 0.75, 8.0, 1.0, camera_lamp=0.5),
    "high": _Light((0.3, -0.5, -0.81), 0.62, 0.18, 0.008, 1.1, 4.0, 1.0),
    "low": _Light((0.85, -0.15, 0.5), 0.008, 0.09, 0.0015, 0.05, 20.0, 2.5),
}


#: The realistic camera (``RenderConfig(**REALISTIC)``): the default lens PSF and the sRGB tone curve.
REALISTIC: dict[str, object] = {"psf_sigma_px": None, "tone": "srgb"}


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
    """How a frame is rendered (the chain is in the module docstring).

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

        def finite(name: str, low: float, strict: bool = False, optional: bool = False) -> None:
            value = getattr(self, name)
            if value is None and optional:
                return
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise ConfigError(f"{name} must be a number, got {value!r}") from None
            if not math.isfinite(v) or v < low or (strict and v == low):
                raise ConfigError(f"{name} must be finite and {'>' if strict else '>='} {low}, got {value}")

        finite("psf_sigma_px", 0.0, optional=True)
        finite("defocus_radius_px", 0.0)
        finite("exposure_ms", 0.0, strict=True, optional=True)
        finite("gain", 0.0, strict=True, optional=True)
        finite("full_well_e", 0.0, strict=True)
        finite("read_noise_e", 0.0)
        finite("gamma", 0.0, strict=True)
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

    def exposure_and_gain(self) -> tuple[float, float]:
        """(exposure_ms, gain) actually used (auto values resolved)."""
        light = _LIGHTS[self.lighting]
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


# ------------------------------------------------------------------------------------------------
# Textures and background (cached: deterministic in their arguments)
# ------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=512)
def _face_texture(tag_id: int, cell_px: int) -> np.ndarray:
    """Face texture (10c, 10c, 3) uint8, channels: face coverage, tag-square mask, blackness.

    Texture pixel j covers [j - 0.5, j + 0.5]; the tag's outer edge is at c - 0.5 and 9c - 0.5.
    """
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(dictionary, int(tag_id), TAG_CELLS * cell_px)
    n = _CELLS_FACE * cell_px
    tex = np.zeros((n, n, 3), np.uint8)
    tex[..., 0] = 255
    inner = slice(cell_px, (_CELLS_FACE - 1) * cell_px)
    tex[inner, inner, 1] = 255
    tex[inner, inner, 2] = 255 - marker
    tex.setflags(write=False)
    return tex


def _smooth_noise(rng: np.random.Generator, h: int, w: int, scale_px: float) -> np.ndarray:
    """Zero-mean, unit-ish smooth noise field (h, w) float32 with features of ``scale_px``."""
    sh, sw = max(2, int(h / scale_px) + 2), max(2, int(w / scale_px) + 2)
    small = rng.standard_normal((sh, sw)).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


@functools.lru_cache(maxsize=8)
def _background(width: int, height: int, seed: int, color: bool) -> np.ndarray:
    """Static car-interior albedo (H, W, C) float32 in [0, 1], linear, C = 3 (BGR) or 1.

    Seen from a camera behind the driver looking forward: windscreen with a soft outside scene,
    A-pillars, roof liner, rear-view mirror, dashboard, instrument hood, centre screen and a
    steering-wheel rim; all soft-edged and low-contrast so nothing looks like a tag.
    """
    rng = np.random.default_rng(seed + 7919)
    w, h = width, height
    s = w / 960.0  # drawing scale relative to 540p
    yy = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None]
    xx = np.linspace(0.0, 1.0, w, dtype=np.float32)[None, :]
    horizon = 0.42 + 0.05 * rng.uniform(-1, 1)
    dash = 0.6 + 0.05 * rng.uniform(-1, 1)
    # Windscreen: bright sky gradient, darker landscape band below the horizon.
    img = np.empty((h, w), np.float32)
    sky = 0.78 - 0.18 * yy / horizon + 0.04 * np.sin(6.0 * xx + rng.uniform(0, 6))
    land = 0.45 - 0.1 * (yy - horizon) + 0.05 * _smooth_noise(rng, h, w, 60 * s)
    img[:] = np.where(yy < horizon, sky, land)
    for _ in range(6):  # soft blobs: trees, buildings, clouds
        cx, cy = rng.uniform(0.1, 0.9) * w, (horizon + rng.uniform(-0.12, 0.02)) * h
        ax, ay = rng.uniform(30, 120) * s, rng.uniform(15, 50) * s
        blob = np.zeros((h, w), np.float32)
        cv2.ellipse(blob, (int(cx), int(cy)), (int(ax), int(ay)), 0.0, 0, 360, 1.0, -1)
        img += rng.uniform(-0.15, 0.1) * cv2.GaussianBlur(blob, (0, 0), 12 * s)
    # Roof liner on top, dashboard below.
    roof = 0.08 + 0.03 * rng.uniform(-1, 1)
    img = np.where(yy < roof, 0.55 + 0.05 * (yy / roof), img)
    dash_tone = 0.2 + 0.04 * rng.uniform(-1, 1) - 0.08 * (yy - dash)
    img = np.where(yy > dash, dash_tone, img).astype(np.float32)
    # A-pillars: dark quads along both sides.
    for side in (0, 1):
        x_top, x_bot = (0.1, 0.02) if side == 0 else (0.9, 0.98)
        poly = np.array(
            [[x_top * w, 0], [x_bot * w, dash * h], [(0 if side == 0 else 1) * w, dash * h],
             [(0 if side == 0 else 1) * w, 0]], np.int32)
        cv2.fillConvexPoly(img, poly, 0.16 + 0.03 * rng.uniform(-1, 1))
    # Rear-view mirror, instrument hood, centre screen, steering-wheel rim.
    cv2.rectangle(img, (int(0.55 * w), int(0.1 * h)), (int(0.7 * w), int(0.17 * h)), 0.22, -1)
    cv2.line(img, (int(0.62 * w), int(roof * h)), (int(0.62 * w), int(0.1 * h)), 0.2, max(1, int(4 * s)))
    cv2.ellipse(img, (int(0.3 * w), int((dash + 0.02) * h)), (int(0.14 * w), int(0.06 * h)),
                0.0, 180, 360, 0.1, -1)
    cv2.rectangle(img, (int(0.52 * w), int((dash + 0.06) * h)), (int(0.64 * w), int((dash + 0.2) * h)),
                  0.1, -1)
    cv2.ellipse(img, (int(0.3 * w), int(1.02 * h)), (int(0.17 * w), int(0.2 * h)), 0.0, 180, 360,
                0.08, max(2, int(22 * s)))
    img += 0.025 * _smooth_noise(rng, h, w, 6 * s) + 0.02 * _smooth_noise(rng, h, w, 40 * s)
    img = cv2.GaussianBlur(img, (0, 0), 1.6 * s)
    img = np.clip(img, 0.02, 1.0)
    if color:
        tint_top = np.array([1.08, 1.0, 0.92], np.float32)  # bluish sky
        tint_low = np.array([0.9, 0.97, 1.06], np.float32)  # warm interior
        mix = (yy > horizon).astype(np.float32)[..., None]
        out = img[..., None] * (tint_top * (1 - mix) + tint_low * mix)
    else:
        out = img[..., None]
    # Drawn as it should look on screen; the renderer works in linear light.
    out = np.ascontiguousarray(srgb_to_linear(np.clip(out, 0.0, 1.0)), dtype=np.float32)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=16)
def _hair_waves(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random wave vectors and phases for the hair texture (attached to the head)."""
    rng = np.random.default_rng(seed + 104729)
    k = rng.normal(0.0, 1.0, (6, 3))
    k *= rng.uniform(8.0, 40.0, (6, 1)) / np.linalg.norm(k, axis=1, keepdims=True)
    return k, rng.uniform(0.0, 2 * math.pi, 6)


# ------------------------------------------------------------------------------------------------
# Distortion maps
# ------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=4)
def _distortion_maps(
    width: int, height: int, k_bytes: bytes, d_bytes: bytes, model: str
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int, int]]:
    """(map_x, map_y) float32: ideal-pinhole pixel seen by every distorted pixel, and the canvas
    (offset_x, offset_y, canvas_w, canvas_h) the ideal image must cover."""
    k = np.frombuffer(k_bytes, np.float64).reshape(3, 3)
    d = np.frombuffer(d_bytes, np.float64)
    cam = CameraModel(width, height, k, d, model)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    ideal = cam.undistort_px(np.stack([u.ravel(), v.ravel()], axis=1))
    ideal = np.where(np.isfinite(ideal), ideal, -1e6)
    # Never let a runaway (fisheye edge) blow up the canvas: at most 3x the image each way.
    lo = np.maximum(np.floor(ideal.min(axis=0)) - 2, [-width, -height])
    hi = np.minimum(np.ceil(ideal.max(axis=0)) + 3, [2 * width, 2 * height])
    ox, oy = int(max(0, -lo[0])), int(max(0, -lo[1]))
    cw, ch = int(max(width, hi[0]) + ox), int(max(height, hi[1]) + oy)
    map_x = (ideal[:, 0] + ox).reshape(height, width).astype(np.float32)
    map_y = (ideal[:, 1] + oy).reshape(height, width).astype(np.float32)
    return map_x, map_y, (ox, oy, cw, ch)


# ------------------------------------------------------------------------------------------------
# Rendering
# ------------------------------------------------------------------------------------------------
def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Exact 3x3 homography from 4 point pairs (float64 DLT; getPerspectiveTransform is float32)."""
    a = np.zeros((8, 8))
    b = np.zeros(8)
    for i, ((x, y), (u, v)) in enumerate(zip(src, dst)):
        a[2 * i] = [x, y, 1, 0, 0, 0, -u * x, -u * y]
        a[2 * i + 1] = [0, 0, 0, x, y, 1, -v * x, -v * y]
        b[2 * i], b[2 * i + 1] = u, v
    h = np.linalg.solve(a, b)
    return np.append(h, 1.0).reshape(3, 3)


def _irradiance(light: _Light, normals_cam: np.ndarray) -> np.ndarray:
    l_vec = np.asarray(light.toward_light_cam, np.float64)
    l_vec = l_vec / np.linalg.norm(l_vec)
    return light.ambient + light.diffuse * np.clip(normals_cam @ l_vec, 0.0, None)


@dataclass(frozen=True)
class _HeadMaps:
    """Head coverage and depth over its bounding box (x0, y0) .. (x1, y1) of the image."""

    box: tuple[int, int, int, int]
    alpha: np.ndarray  # (h, w) float32 coverage in [0, 1]
    depth_m: np.ndarray  # (h, w) float32 depth of the near surface, inf where no head

    def crop(self, x0: int, y0: int, x1: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
        """(alpha, depth) over an image ROI (zeros / inf outside the head box)."""
        alpha = np.zeros((y1 - y0, x1 - x0), np.float32)
        depth = np.full((y1 - y0, x1 - x0), np.inf, np.float32)
        hx0, hy0, hx1, hy1 = self.box
        ix0, iy0, ix1, iy1 = max(x0, hx0), max(y0, hy0), min(x1, hx1), min(y1, hy1)
        if ix1 > ix0 and iy1 > iy0:
            alpha[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0] = self.alpha[iy0 - hy0:iy1 - hy0, ix0 - hx0:ix1 - hx0]
            depth[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0] = self.depth_m[iy0 - hy0:iy1 - hy0, ix0 - hx0:ix1 - hx0]
        return alpha, depth


def _render_head(
    img: np.ndarray, k: np.ndarray, T_cam_cap: Transform, cfg: RenderConfig, light: _Light,
    hair_tint: np.ndarray, centre_m: tuple[float, float, float] | None = None,
    semi_axes_m: tuple[float, float, float] | None = None, albedo: float = _HAIR_ALBEDO,
) -> _HeadMaps | None:
    """Draw the head ellipsoid into ``img`` in place; return its coverage and depth maps.

    The silhouette distance, depth and shading are smooth, so they are computed on a half-resolution
    grid and upsampled; the anti-aliased edge comes from the upsampled signed distance (px) to the
    silhouette conic.
    """
    h_img, w_img = img.shape[:2]
    axes = np.asarray(semi_axes_m or cfg.head_semi_axes_m, np.float64)
    centre_cam = T_cam_cap.apply(np.asarray(centre_m or cfg.head_centre_m, np.float64))
    r = T_cam_cap.rotation.as_matrix()
    g = np.linspace(0.0, math.pi, 13)
    th, ph = np.meshgrid(g, np.linspace(0.0, 2 * math.pi, 25))
    sphere = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    pts = centre_cam + (sphere * axes) @ r.T
    if np.any(pts[:, 2] < _NEAR_M):
        x0, y0, x1, y1 = 0, 0, w_img, h_img
    else:
        # Surface samples miss the silhouette by under a few px at these sizes: 6 px margin.
        uv = (pts / pts[:, 2:3]) @ k.T
        x0 = int(max(0, math.floor(uv[:, 0].min()) - 6))
        y0 = int(max(0, math.floor(uv[:, 1].min()) - 6))
        x1 = int(min(w_img, math.ceil(uv[:, 0].max()) + 7))
        y1 = int(min(h_img, math.ceil(uv[:, 1].max()) + 7))
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None
    w, h = x1 - x0, y1 - y0
    wh, hh = (w + 1) // 2, (h + 1) // 2
    # Half-res pixel j covers full-res pixels 2j, 2j + 1 of the box: centre at x0 + 2j + 0.5.
    u = (x0 + 0.5 + 2.0 * np.arange(wh, dtype=np.float32))[None, :]
    v = (y0 + 0.5 + 2.0 * np.arange(hh, dtype=np.float32))[:, None]
    # Ray t * K^-1 [u v 1] (t = depth); in unit-sphere coordinates: o + t * M [u v 1].
    m = np.diag(1.0 / axes) @ r.T @ np.linalg.inv(k)
    o = np.diag(1.0 / axes) @ r.T @ (-centre_cam)
    cc = float(o @ o - 1.0)
    mf = [[float(m[i, j]) for j in range(3)] for i in range(3)]
    of = [float(x) for x in o]
    d = [mf[i][0] * u + mf[i][1] * v + mf[i][2] for i in range(3)]
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    b = of[0] * d[0] + of[1] * d[1] + of[2] * d[2]
    disc = b * b - cc * a
    # Signed distance (px, positive inside) to the silhouette conic disc = 0: disc / |grad disc|.
    db_du, db_dv = float(o @ m[:, 0]), float(o @ m[:, 1])
    da_du = 2.0 * (mf[0][0] * d[0] + mf[1][0] * d[1] + mf[2][0] * d[2])
    da_dv = 2.0 * (mf[0][1] * d[0] + mf[1][1] * d[1] + mf[2][1] * d[2])
    gu = (2.0 * db_du) * b - cc * da_du
    gv = (2.0 * db_dv) * b - cc * da_dv
    dist = disc / np.maximum(np.sqrt(gu * gu + gv * gv), np.float32(1e-12))
    t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    # Shading: the ellipsoid normal is A^-1 x (x on the unit sphere), turned into the camera frame.
    xs = [of[i] + t * d[i] for i in range(3)]
    ne = [xs[i] * float(1.0 / axes[i]) for i in range(3)]
    l_vec = np.asarray(light.toward_light_cam, np.float64)
    l_vec = (r.T @ (l_vec / np.linalg.norm(l_vec)))  # light direction in the cap frame
    dot = float(l_vec[0]) * ne[0] + float(l_vec[1]) * ne[1] + float(l_vec[2]) * ne[2]
    lam = np.maximum(dot / (np.sqrt(ne[0] * ne[0] + ne[1] * ne[1] + ne[2] * ne[2]) + 1e-12), 0.0)
    waves, phases = _hair_waves(cfg.background_seed)
    tex = np.zeros_like(a)
    for kv, ph_ in zip(waves, phases):
        tex += np.sin(float(kv[0]) * xs[0] + float(kv[1]) * xs[1] + float(kv[2]) * xs[2] + float(ph_))
    irradiance = light.ambient + light.diffuse * lam
    if light.camera_lamp > 0.0:
        # The lamp at the camera (``_Light``), metered at the head centre's distance: cos(incidence)
        # = -n . q / (|n| |q|) with q = R^T K^-1 [u v 1] the pixel's ray in the cap frame.
        rk = r.T @ np.linalg.inv(k)
        q = [float(rk[i, 0]) * u + float(rk[i, 1]) * v + float(rk[i, 2]) for i in range(3)]
        qn = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])
        cos_cam = -(ne[0] * q[0] + ne[1] * q[1] + ne[2] * q[2]) / (
            np.sqrt(ne[0] * ne[0] + ne[1] * ne[1] + ne[2] * ne[2]) * qn + 1e-12)
        r_head = float(np.linalg.norm(centre_cam))
        irradiance = irradiance + light.camera_lamp * np.maximum(cos_cam, 0.0) * (
            r_head / np.maximum(t * qn, 1e-3)) ** 2
    rad = (albedo * (1.0 + 0.1 * tex)) * irradiance
    valid = (t > 0) & (b < 0)
    dist = np.where(valid, dist, -10.0)
    t = np.where(valid, t, 1e3)  # 1e3 m: "far", never in front of a face
    fields = cv2.merge([dist.astype(np.float32), t.astype(np.float32), rad.astype(np.float32)])
    # Upsample: half-res sample j sits at full-res coordinate 2j + 0.5, which is what resize's
    # pixel-centre mapping with an exact factor 2 assumes.
    full = cv2.resize(fields, (2 * wh, 2 * hh), interpolation=cv2.INTER_LINEAR)[:h, :w]
    alpha = np.clip(full[..., 0] + 0.5, 0.0, 1.0)
    depth = np.where(alpha > 0, full[..., 1], np.inf).astype(np.float32)
    roi = img[y0:y1, x0:x1]
    al = alpha[..., None]
    roi *= 1.0 - al
    roi += (al * full[..., 2:3]) * hair_tint
    return _HeadMaps((x0, y0, x1, y1), alpha, depth)


def _render_scene(
    model: CapModel, k: np.ndarray, width: int, height: int, T_cam_cap: Transform,
    cfg: RenderConfig,
) -> tuple[np.ndarray, dict[int, float], list[int]]:
    """Float32 (H, W, C) linear radiance (share of the full well at the lighting's nominal
    exposure) of the ideal pinhole (K, no distortion), before flare and spotlights; visible
    fractions; front-facing ids, far to near."""
    light = _LIGHTS[cfg.lighting]
    channels = 3 if cfg.color else 1
    if cfg.background:
        img = _background(width, height, cfg.background_seed, cfg.color) * np.float32(light.background)
    else:
        img = np.full((height, width, channels), 0.06 * light.background, np.float32)
    img = np.ascontiguousarray(img, dtype=np.float32)
    hair_tint = (np.array([0.75, 0.9, 1.15], np.float32) if cfg.color else np.ones(1, np.float32))

    occluders: list[_HeadMaps] = []
    if cfg.head:
        # Neck first (the head is in front of it seen from behind), then the head.
        neck = _render_head(img, k, T_cam_cap, cfg, light, hair_tint * 1.15, NECK_CENTRE_M,
                            NECK_SEMI_AXES_M, albedo=_NECK_ALBEDO)
        head = _render_head(img, k, T_cam_cap, cfg, light, hair_tint)
        occluders = [o for o in (neck, head) if o is not None]

    rot = T_cam_cap.rotation.as_matrix()
    faces_cam = T_cam_cap.apply(model.face_corners_mm().reshape(-1, 3) / 1000.0).reshape(-1, 4, 3)
    tags_cam = T_cam_cap.apply(model.corners_mm.reshape(-1, 3) / 1000.0).reshape(-1, 4, 3)
    normals_cam = model.normals @ rot.T
    centres_cam = tags_cam.mean(axis=1)
    front = (np.einsum("ij,ij->i", normals_cam, centres_cam) < 0.0) & np.all(
        faces_cam[:, :, 2] > _NEAR_M, axis=1
    )
    order = sorted(np.flatnonzero(front), key=lambda i: -np.linalg.norm(centres_cam[i]))
    irr = _irradiance(light, normals_cam)
    # The lamp at the camera is metered on the cap: its irradiance at the cap's distance is fixed.
    r_cap = float(np.linalg.norm(centres_cam.mean(axis=0)))
    k_inv = np.linalg.inv(k)
    s_max = int(cfg.supersample)
    id_buf = np.full((height, width), -1, np.int16)
    tag_cov: dict[int, tuple[tuple[int, int, int, int], np.ndarray]] = {}
    tag_area: dict[int, float] = {}
    for i in order:
        tag_id = model.ids[i]
        pf = faces_cam[i] / faces_cam[i][:, 2:3] @ k.T
        pt = tags_cam[i] / tags_cam[i][:, 2:3] @ k.T
        pf, pt = pf[:, :2], pt[:, :2]
        x_, y_ = pt[:, 0], pt[:, 1]
        tag_area[tag_id] = 0.5 * abs(
            float(np.dot(x_, np.roll(y_, -1)) - np.dot(y_, np.roll(x_, -1)))
        )
        x0 = int(max(0, math.floor(pf[:, 0].min()) - 1))
        y0 = int(max(0, math.floor(pf[:, 1].min()) - 1))
        x1 = int(min(width, math.ceil(pf[:, 0].max()) + 2))
        y1 = int(min(height, math.ceil(pf[:, 1].max()) + 2))
        if x1 <= x0 or y1 <= y0:
            continue
        w, h = x1 - x0, y1 - y0
        sides_px = np.linalg.norm(pt - np.roll(pt, -1, axis=0), axis=1)
        edge_px = max(float(sides_px.max()), 1.0)
        # Big faces cost area: cap the supersampled edge near 320 px, but never below 3x.
        s = int(min(s_max, max(3, round(320.0 / edge_px))))
        # Texture resolution: one texel spans 1-2 supersamples along every side (the shortest
        # sets it). Bilinear lookup then draws each cell edge as a ramp at least one supersample
        # wide, and a ramp that wide, point-sampled and box-filtered, puts the edge within 0.09
        # supersample of the truth at any sub-pixel phase (a sharper texture would be off by up
        # to 0.25 supersample); the ramp is symmetric, so it only adds a little blur.
        texel_px = max(float(sides_px.min()), 1.0) * s / TAG_CELLS
        cell = int(min(64, max(2, 2 ** math.floor(math.log2(max(texel_px, 2.0))))))
        tex = _face_texture(tag_id, cell)
        c = float(cell)
        src = np.array([[c - 0.5, c - 0.5], [9 * c - 0.5, c - 0.5], [9 * c - 0.5, 9 * c - 0.5],
                        [c - 0.5, 9 * c - 0.5]])
        # Image pixel x (centre convention) is supersampled pixel (x - x0 + 0.5) * s - 0.5.
        dst = (pt - [x0, y0] + 0.5) * s - 0.5
        hom = _homography(src, dst)
        big = cv2.warpPerspective(tex, hom, (w * s, h * s), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        small = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) * (1 / 255)
        cov, tsq, blk = small[..., 0], small[..., 1], small[..., 2]
        occl = np.zeros_like(cov)
        lamp = light.camera_lamp > 0.0
        if occluders or lamp:
            # Depth of the face plane along each pixel's ray (t with K^-1 [u v 1], z = 1).
            n = normals_cam[i]
            d0 = float(n @ faces_cam[i][0])
            coef = n @ k_inv
            uu = np.arange(x0, x1, dtype=np.float32)[None, :]
            vv = np.arange(y0, y1, dtype=np.float32)[:, None]
            denom = coef[0] * uu + coef[1] * vv + coef[2]
            with np.errstate(divide="ignore", invalid="ignore"):
                z_face = d0 / denom
            z_face = np.where(z_face > 0, z_face, np.inf)
        irr_i: float | np.ndarray = irr[i]
        if lamp:
            # The lamp at the camera centre, at each pixel's point P of the face plane:
            # cos(incidence) / |P|^2 = |d0| / |P|^3 (d0 = n . P, the plane's distance).
            ray = [k_inv[j, 0] * uu + k_inv[j, 1] * vv + k_inv[j, 2] for j in range(3)]
            norm = np.sqrt(ray[0] ** 2 + ray[1] ** 2 + ray[2] ** 2)
            dist = np.where(np.isfinite(z_face), z_face * norm, np.inf)
            irr_i = (irr[i] + light.camera_lamp * abs(d0) * r_cap**2 / dist**3).astype(np.float32)
        if occluders:
            for occluder in occluders:
                h_alpha, h_depth = occluder.crop(x0, y0, x1, y1)
                occl = np.maximum(occl, h_alpha * (h_depth < z_face))
        keep = 1.0 - occl
        eff = cov * keep
        # Coverage-weighted (premultiplied) radiance: the box filter of the supersampled texture
        # integrates linear light over each pixel, as a sensor pixel does.
        premult = irr_i * (_WHITE_ALBEDO * cov - (_WHITE_ALBEDO - _BLACK_ALBEDO) * blk) * keep
        roi = img[y0:y1, x0:x1]
        roi *= (1.0 - eff)[..., None]
        roi += premult[..., None]
        id_buf[y0:y1, x0:x1][eff > 0.5] = i
        tag_cov[tag_id] = ((x0, y0, x1, y1), tsq)

    visible: dict[int, float] = {}
    front_ids = [model.ids[i] for i in order]
    for i in order:
        tag_id = model.ids[i]
        if tag_id not in tag_cov or tag_area[tag_id] <= 0:
            visible[tag_id] = 0.0
            continue
        (x0, y0, x1, y1), tsq = tag_cov[tag_id]
        seen = float(tsq[id_buf[y0:y1, x0:x1] == i].sum())
        visible[tag_id] = float(min(1.0, seen / tag_area[tag_id]))

    return img, visible, front_ids


def _spotlights(img: np.ndarray, faces_cam: np.ndarray, k: np.ndarray, rng: np.random.Generator) -> None:
    """Add the paper's three spotlights on the cap ("generating highly saturated images"), in
    linear light: extra irradiance (a gain on the scene, which pushes whites past full well) plus
    veiling glare (lifts blacks), computed at low resolution and upsampled."""
    h, w = img.shape[:2]
    if len(faces_cam):
        pts = faces_cam.reshape(-1, 3)
        uv = (pts / pts[:, 2:3]) @ k.T
        lo, hi = uv[:, :2].min(axis=0), uv[:, :2].max(axis=0)
    else:
        lo, hi = np.array([0.3 * w, 0.3 * h]), np.array([0.7 * w, 0.7 * h])
    size = max(float(np.max(hi - lo)), 0.1 * w)
    scale = 8
    hs, ws = max(2, h // scale), max(2, w // scale)
    yy = (np.arange(hs, dtype=np.float32)[:, None] + 0.5) * (h / hs)
    xx = (np.arange(ws, dtype=np.float32)[None, :] + 0.5) * (w / ws)
    gain = np.ones((hs, ws), np.float32)
    glare = np.zeros((hs, ws), np.float32)
    for _ in range(3):
        cx, cy = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
        sigma = rng.uniform(0.15, 0.35) * size
        blob = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma * sigma))
        gain += rng.uniform(1.0, 2.5) * blob
        glare += rng.uniform(0.01, 0.04) * blob
    gain = cv2.resize(gain, (w, h), interpolation=cv2.INTER_LINEAR)
    glare = cv2.resize(glare, (w, h), interpolation=cv2.INTER_LINEAR)
    img *= gain.reshape(h, w, *([1] * (img.ndim - 2)))
    img += glare.reshape(h, w, *([1] * (img.ndim - 2)))


# ------------------------------------------------------------------------------------------------
# The camera: lens PSF, sensor, tone curve (``vision.tone``)
# ------------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=16)
def _tone_lut(tone: str, gamma: float) -> np.ndarray:
    """8-bit output for every 16-bit linear code (the ISP's lookup table)."""
    lut = np.round(255.0 * tone_curve(np.arange(_CODE_MAX + 1) / _CODE_MAX, tone, gamma)).astype(np.uint8)
    lut.setflags(write=False)
    return lut


@functools.lru_cache(maxsize=16)
def _disc_kernel(radius_px: float) -> np.ndarray:
    """Normalised anti-aliased pillbox (defocus) kernel of ``radius_px``."""
    r = int(math.ceil(radius_px + 0.5))
    ss = 8  # sub-samples per pixel per axis
    g = (np.arange((2 * r + 1) * ss) + 0.5) / ss - (r + 0.5)
    inside = (g[None, :] ** 2 + g[:, None] ** 2 <= radius_px ** 2).astype(np.float32)
    kernel = inside.reshape(2 * r + 1, ss, 2 * r + 1, ss).mean(axis=(1, 3))
    return (kernel / kernel.sum()).astype(np.float32)


def _lens_psf(scene: np.ndarray, sigma_px: float, defocus_radius_px: float) -> np.ndarray:
    """The lens blur, in linear light: a defocus disc, then a Gaussian (both symmetric, so the
    blurred edge's 50 % *linear* level stays on the true edge)."""
    shape = scene.shape
    if defocus_radius_px > 0:
        scene = cv2.filter2D(scene, -1, _disc_kernel(float(defocus_radius_px)), borderType=cv2.BORDER_REFLECT)
    if sigma_px > 0:
        scene = cv2.GaussianBlur(scene, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT)
    return scene.reshape(shape)


def _sensor_and_tone(
    scene: np.ndarray, cfg: RenderConfig, exposure_ms: float, gain: float, rng: np.random.Generator,
) -> np.ndarray:
    """Linear scene (share of full well at the nominal exposure) -> charge (exposure, shot noise,
    full-well clipping, read noise) -> gain -> 16-bit code -> tone curve -> uint8."""
    light = _LIGHTS[cfg.lighting]
    full_well = float(cfg.full_well_e)
    charge = scene * np.float32(full_well * exposure_ms / light.exposure_ms)  # electrons
    if cfg.noise:
        # OpenCV's SIMD Gaussian generator (5-10x numpy's), seeded from ``seed`` via ``rng``.
        unit = np.empty(charge.shape, np.float32)
        cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
        cv2.randn(unit, 0.0, 1.0)
        # Shot noise: Poisson, sigma sqrt(electrons) (the Gaussian limit; a few electrons and up).
        charge += unit * np.sqrt(np.maximum(charge, 0.0))
    np.clip(charge, 0.0, full_well, out=charge)  # the well is full
    if cfg.noise and cfg.read_noise_e > 0:
        cv2.randn(unit, 0.0, float(cfg.read_noise_e))
        charge += unit
    code = charge * np.float32(gain / full_well * _CODE_MAX)
    np.clip(code, 0.0, float(_CODE_MAX), out=code)  # the converter's range (gain > 1 clips early)
    code += 0.5
    return _tone_lut(cfg.tone, float(cfg.gamma))[code.astype(np.uint16)]


def _subframe_times_s(
    model: CapModel, camera: CameraModel, pose_at: Callable[[float], Transform], exposure_s: float,
    requested: int,
) -> np.ndarray:
    """Sub-frame times (s from mid-exposure, midpoint rule, odd count so 0 is one of them)."""
    n = int(requested)
    if n <= 0:
        # Enough sub-frames that no corner moves more than half a pixel between two.
        pts = model.corners_mm.reshape(-1, 3) / 1000.0
        uv = [camera.project(pose_at(t).apply(pts)) for t in (-0.5 * exposure_s, 0.0, 0.5 * exposure_s)]
        ok = np.all([np.isfinite(u).all(axis=1) for u in uv], axis=0)
        travel = (np.linalg.norm(uv[1] - uv[0], axis=1) + np.linalg.norm(uv[2] - uv[1], axis=1))[ok]
        n = int(math.ceil(2.0 * float(travel.max()))) if travel.size else 1
    n = min(max(n, 1), 31)
    n += 1 - n % 2
    return exposure_s * ((np.arange(n) + 0.5) / n - 0.5)


def render(
    model: CapModel, camera: CameraModel, T_cam_cap: Transform | Callable[[float], Transform],
    config: RenderConfig | None = None, seed: int = 0,
) -> RenderedFrame:
    """Render ``model`` at pose ``T_cam_cap`` as seen by ``camera``, through the camera chain.

    Args:
        model: cap model (cap frame C, mm).
        camera: intrinsics and lens model; the image has its size.
        T_cam_cap: cap pose in the camera optical frame (metres), or, for motion blur, a function
            of time (s, 0 = mid-exposure) returning the pose then: the frame integrates the pose
            over the exposure (``config.exposure_ms``) and its ground truth is the pose at 0.
            ``DriveMotion.around`` gives one for a naturalistic drive.
        config: rendering options (default ``RenderConfig()``).
        seed: seeds noise and spotlights (the background uses ``config.background_seed``).

    Returns:
        The frame with its exact ground truth (``RenderedFrame``).
    """
    cfg = config or RenderConfig()
    rng = np.random.default_rng(seed)
    exposure_ms, gain = cfg.exposure_and_gain()
    if isinstance(T_cam_cap, Transform):
        pose_at = None
        T_mid = T_cam_cap
    elif callable(T_cam_cap):
        pose_at = T_cam_cap
        T_mid = pose_at(0.0)
        if not isinstance(T_mid, Transform):
            raise ConfigError("a pose function given to render must return a Transform")
    else:
        raise ConfigError(f"T_cam_cap must be a Transform or a function of time, got {type(T_cam_cap).__name__}")
    width, height = camera.width_px, camera.height_px
    k, w_canvas, h_canvas = camera.K, width, height
    if camera.is_distorted:
        map_x, map_y, (ox, oy, w_canvas, h_canvas) = _distortion_maps(
            width, height, camera.K.tobytes(), camera.D.tobytes(), camera.distortion_model
        )
        k = camera.K.copy()
        k[0, 2] += ox
        k[1, 2] += oy
    times = [0.0] if pose_at is None else list(
        _subframe_times_s(model, camera, pose_at, exposure_ms / 1000.0, cfg.motion_subframes))
    scene: np.ndarray | None = None
    for t in times:
        # Linear light adds: the exposure is the mean of the sub-frames' irradiance.
        img, vis, front = _render_scene(model, k, w_canvas, h_canvas, T_mid if t == 0.0 else pose_at(t), cfg)
        if t == 0.0:
            visible, front_ids = vis, front
        if scene is None:
            scene = img
        else:
            scene += img
    assert scene is not None
    if len(times) > 1:
        scene *= np.float32(1.0 / len(times))
    light = _LIGHTS[cfg.lighting]
    spot_rng = np.random.default_rng(rng.integers(0, 2**63 - 1))
    if cfg.lighting == "high":
        idx = [model.index_of(t) for t in front_ids]
        faces = T_mid.apply(model.face_corners_mm()[idx].reshape(-1, 3) / 1000.0).reshape(-1, 4, 3)
        _spotlights(scene, faces, k, spot_rng)
    scene += np.float32(light.flare)
    if scene.shape[2] == 1:
        scene = scene[..., 0]
    if camera.is_distorted:
        scene = cv2.remap(scene, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    scene = _lens_psf(scene, cfg.psf_sigma_for(height), cfg.defocus_radius_px)
    image = _sensor_and_tone(scene, cfg, exposure_ms, gain, rng)
    if cfg.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)])
        image = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    corners_px: dict[int, np.ndarray] = {}
    if front_ids:
        idx = [model.index_of(t) for t in front_ids]
        pts = T_mid.apply(model.corners_mm[idx].reshape(-1, 3) / 1000.0)
        px = camera.project(pts).reshape(-1, 4, 2)
        for n, tag_id in enumerate(front_ids):
            corners_px[tag_id] = px[n]
    image = np.ascontiguousarray(image)
    image.setflags(write=False)
    return RenderedFrame(image=image, T_cam_cap=T_mid, corners_px=corners_px,
                         visible_fraction=visible, camera=camera)


# ------------------------------------------------------------------------------------------------
# Naturalistic driving head motion
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DriveScene:
    """Fixed geometry of a driving recording.

    Attributes:
        camera: the rear camera.
        R_cam_frontal: orientation of the frontal frame F (head zero pose: x forward, y left, z up)
            in the camera optical frame.
        p_cam_neck_m: neck pivot (the head turns about it) in the camera optical frame, m.
        neck_to_cap_m: vector from the neck pivot to the cap origin in the head frame H, m.
        R_cap_head: true orientation of the head frame H in the cap frame C (how the cap sits on
            the head; what the pipeline's calibration must recover).
    """

    camera: CameraModel
    R_cam_frontal: Rotation = field(default_factory=lambda: CAM_FROM_FORWARD)
    p_cam_neck_m: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.15, 0.43]))
    neck_to_cap_m: np.ndarray = field(default_factory=lambda: np.array([-0.04, 0.0, 0.13]))
    R_cap_head: Rotation = field(
        default_factory=lambda: Rotation.from_rotvec(np.radians([2.0, -9.0, 3.0]))
    )

    def __post_init__(self) -> None:
        for name in ("p_cam_neck_m", "neck_to_cap_m"):
            v = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1).copy()
            if v.size != 3 or not np.all(np.isfinite(v)):
                raise ConfigError(f"DriveScene.{name} must be 3 finite numbers")
            v.setflags(write=False)
            object.__setattr__(self, name, v)

    def cap_pose(self, R_frontal_head: Rotation, t_frontal_head_m: np.ndarray | None = None) -> Transform:
        """T_cam_cap for a head orientation in F and a head translation in F (m, default none).

        R_cam_cap = R_cam_frontal R_frontal_head R_cap_head^-1; the cap origin is the neck pivot
        plus ``neck_to_cap_m`` turned with the head, plus the translation.
        """
        shift = np.zeros(3) if t_frontal_head_m is None else np.asarray(t_frontal_head_m, np.float64)
        rotation = self.R_cam_frontal * R_frontal_head * self.R_cap_head.inv()
        p_frontal = shift + R_frontal_head.apply(np.array(self.neck_to_cap_m))
        return Transform(rotation, self.p_cam_neck_m + self.R_cam_frontal.apply(p_frontal))


@dataclass(frozen=True)
class DriveFrame:
    """One frame of a drive with its exact ground truth.

    Attributes:
        index: frame number from 0.
        stamp_ns: ``round(index * 1e9 / fps)``.
        R_frontal_head: true head orientation in the frontal frame F.
        ypr_deg: (yaw, pitch, roll) of ``R_frontal_head``, deg (ficap_ros.geometry.metrics convention).
        t_frontal_head_m: head translation (lean) in F, m.
        T_cam_cap: true cap pose in the camera optical frame, m.
        frontal: inside the initial looking-straight-ahead segment (for calibration).
        target: what the head is looking at or moving to: ``frontal``, ``left_mirror``,
            ``right_mirror``, ``rear_mirror`` or ``cluster``.
    """

    index: int
    stamp_ns: int
    R_frontal_head: Rotation
    ypr_deg: np.ndarray
    t_frontal_head_m: np.ndarray
    T_cam_cap: Transform
    frontal: bool
    target: str


def default_scene(resolution: str | tuple[int, int] = "540p") -> DriveScene:
    """The default rear-camera scene.

    A 60 deg hfov pinhole about 0.45 m behind the back of the cap (0.54 m behind the cap origin)
    and 6 cm above it, looking straight forward; the 32 mm centre tag is about 59 px wide at 540p
    when frontal.

    Args:
        resolution: ``'360p'``, ``'540p'``, ``'720p'``, ``'1080p'`` or (width, height).
    """
    if isinstance(resolution, str):
        if resolution not in RESOLUTIONS:
            raise ConfigError(f"unknown resolution {resolution!r}; use {', '.join(RESOLUTIONS)} or (W, H)")
        width, height = RESOLUTIONS[resolution]
    else:
        width, height = (int(v) for v in resolution)
    camera = CameraModel.pinhole(width, height, hfov_deg=60.0)
    neck_to_cap = np.array([-0.04, 0.0, 0.13])
    # Frontal cap origin in F relative to the camera: ahead by 0.45 m + sphere radius, 6 cm lower.
    p_frontal_cap = np.array([0.542, 0.0, -0.06])
    p_cam_neck = CAM_FROM_FORWARD.apply(p_frontal_cap - neck_to_cap)
    return DriveScene(camera=camera, R_cam_frontal=CAM_FROM_FORWARD, p_cam_neck_m=p_cam_neck,
                      neck_to_cap_m=neck_to_cap)


def _min_jerk(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s)


# Glance targets: (label, sampler of (yaw, pitch, roll deg, tx, ty, tz m)); REP-103 angles: yaw
# positive to the left, pitch positive nose down (the cluster is below: +20), roll positive to the
# right shoulder.
def _glance_target(label: str, rng: np.random.Generator) -> np.ndarray:
    u = rng.uniform
    if label == "left_mirror":
        return np.array([u(45, 60), u(2, 8), u(-4, 0), u(0.0, 0.01), u(0.005, 0.02), 0.0])
    if label == "right_mirror":
        return np.array([u(-60, -45), u(2, 8), u(0, 4), u(0.0, 0.01), u(-0.02, -0.005), 0.0])
    if label == "rear_mirror":
        return np.array([u(-28, -22), u(-7, -3), u(-2, 2), u(0.0, 0.01), u(-0.01, 0.0), u(0.0, 0.01)])
    if label == "cluster":
        return np.array([u(-4, 4), u(17, 23), u(-1.5, 1.5), u(0.005, 0.015), 0.0, u(-0.01, 0.0)])
    raise ConfigError(f"unknown glance target {label!r}")


@dataclass(frozen=True)
class DriveMotion:
    """Naturalistic head motion as a continuous function of time (see ``naturalistic_motion``).

    Attributes:
        scene: the geometry the cap poses are computed in.
        frontal_s: length of the initial looking-straight-ahead segment, s.
        segments: (t_start_s, t_end_s, pose_from, pose_to, label) keyframe segments; a pose is
            (yaw, pitch, roll deg, tx, ty, tz m) in F, interpolated with the minimum-jerk profile.
        sway: (amplitudes (6, 2), frequencies Hz (6, 2), phases rad (6, 2)) of the natural sway
            added to every pose.
    """

    scene: DriveScene
    frontal_s: float
    segments: tuple[tuple[float, float, np.ndarray, np.ndarray, str], ...]
    sway: tuple[np.ndarray, np.ndarray, np.ndarray]

    def pose_vector_at(self, t_s: float) -> tuple[np.ndarray, str]:
        """(yaw, pitch, roll deg, tx, ty, tz m) of the head in F at time ``t_s``, and the label."""
        starts = [seg[0] for seg in self.segments]
        j = int(np.searchsorted(starts, t_s, side="right") - 1)
        t0, t1, p0, p1, label = self.segments[max(j, 0)]
        s = _min_jerk(np.array((t_s - t0) / (t1 - t0) if t1 > t0 else 1.0))
        p = p0 + (p1 - p0) * float(s)
        amps, freqs, phases = self.sway
        return p + np.sum(amps * np.sin(2 * math.pi * freqs * t_s + phases), axis=1), label

    def T_cam_cap_at(self, t_s: float) -> Transform:
        """The true cap pose in the camera at time ``t_s`` (s from the drive's start)."""
        p, _ = self.pose_vector_at(t_s)
        return self.scene.cap_pose(rotation_from_ypr_deg(*p[:3]), p[3:])

    def around(self, t_s: float) -> Callable[[float], Transform]:
        """The pose function ``render`` integrates over an exposure centred on ``t_s``:
        ``dt`` (s from mid-exposure) -> T_cam_cap."""
        return lambda dt_s: self.T_cam_cap_at(t_s + dt_s)

    def frame(self, index: int, fps: float) -> DriveFrame:
        """Frame ``index`` of the drive at ``fps`` (its truth is the pose at ``index / fps``)."""
        ts = index / fps
        p, label = self.pose_vector_at(ts)
        ypr = p[:3].copy()
        R_frontal_head = rotation_from_ypr_deg(*ypr)
        return DriveFrame(
            index=index,
            stamp_ns=int(round(index * 1e9 / fps)),
            R_frontal_head=R_frontal_head,
            ypr_deg=ypr,
            t_frontal_head_m=p[3:].copy(),
            T_cam_cap=self.scene.cap_pose(R_frontal_head, p[3:]),
            frontal=ts < self.frontal_s,
            target=label,
        )


def naturalistic_motion(
    duration_s: float, seed: int = 0, scene: DriveScene | None = None, frontal_s: float = 3.0,
) -> DriveMotion:
    """The continuous head motion behind ``naturalistic_drive`` (same seed, same motion).

    ``naturalistic_drive(n, fps, seed, scene, frontal_s)[i]`` equals
    ``naturalistic_motion(n / fps, seed, scene, frontal_s).frame(i, fps)``; the motion also
    answers between frames (``T_cam_cap_at``, ``around``), which motion blur needs.

    Args:
        duration_s: keyframes are drawn until this time (later times hold the last pose).
        seed: random seed.
        scene: geometry (default ``default_scene()``).
        frontal_s: length of the initial frontal segment, s.
    """
    if not duration_s >= 0 or not frontal_s >= 0:
        raise ConfigError("naturalistic_motion needs duration_s >= 0 and frontal_s >= 0")
    scene = scene or default_scene()
    rng = np.random.default_rng(seed)
    # Natural sway: two slow sinusoids per axis, under 0.3 deg and 2 mm each (drawn first, so a
    # longer drive with the same seed starts with the same frames).
    freqs = rng.uniform(0.08, 0.5, (6, 2))
    phases = rng.uniform(0.0, 2 * math.pi, (6, 2))
    amps = np.concatenate([rng.uniform(0.1, 0.3, (3, 2)), rng.uniform(0.0005, 0.002, (3, 2))])
    # Keyframes: piecewise min-jerk between poses p = (yaw, pitch, roll, tx, ty, tz).
    # Each segment: (t_start, t_end, pose_from, pose_to, label).
    segments: list[tuple[float, float, np.ndarray, np.ndarray, str]] = []
    pose = np.zeros(6)
    t = frontal_s
    segments.append((0.0, t, pose, pose, "frontal"))
    labels = ["left_mirror", "right_mirror", "rear_mirror", "cluster"]
    bag: list[str] = []
    while t < duration_s:
        # Frontal driving: drift to a slightly off-centre frontal pose, dwell.
        wander = np.array([rng.normal(0, 2.0), rng.normal(0, 1.5), rng.normal(0, 1.0),
                           rng.normal(0, 0.004), rng.normal(0, 0.004), rng.normal(0, 0.003)])
        move = 0.35 + 0.006 * float(np.abs(wander[:3] - pose[:3]).max())
        dwell = rng.uniform(1.5, 4.0)
        segments.append((t, t + move, pose, wander, "frontal"))
        segments.append((t + move, t + move + dwell, wander, wander, "frontal"))
        pose, t = wander, t + move + dwell
        if not bag:
            bag = list(rng.permutation(labels))
        label = bag.pop()
        target = _glance_target(label, rng)
        move = 0.35 + 0.006 * float(np.abs(target[:3] - pose[:3]).max())
        dwell = rng.uniform(0.4, 1.2)
        segments.append((t, t + move, pose, target, label))
        segments.append((t + move, t + move + dwell, target, target, label))
        pose, t = target, t + move + dwell
    return DriveMotion(scene=scene, frontal_s=float(frontal_s), segments=tuple(segments),
                       sway=(amps, freqs, phases))


def naturalistic_drive(
    n_frames: int, fps: float = 30.0, seed: int = 0, scene: DriveScene | None = None,
    frontal_s: float = 3.0,
) -> list[DriveFrame]:
    """Naturalistic driver head motion with exact cap poses.

    The first ``frontal_s`` seconds look straight ahead (natural sway under 1 deg). Then frontal
    driving (a few degrees of wander, 1.5-4 s dwells) alternates with glances in random order, each
    block of four glances visiting the left mirror (yaw +45..+60), the right mirror (-45..-60), the
    rear-view mirror (about -25 yaw, 5 deg up: pitch -5, REP-103) and the instrument cluster (20 deg
    down: pitch +20), with small roll and 1-2 cm of lean. Transitions follow the minimum-jerk profile 10s^3 - 15s^4 + 6s^5 and
    take 0.35 s + 6 ms per degree; the head turns about the neck pivot of ``scene``. For motion
    blur, render with ``naturalistic_motion(...).around(frame.stamp_ns / 1e9)`` instead of the
    frame's pose (same seed, same motion).

    Args:
        n_frames: number of frames.
        fps: frame rate, Hz.
        seed: random seed (the whole drive is a function of the arguments).
        scene: geometry (default ``default_scene()``).
        frontal_s: length of the initial frontal segment, s.

    Returns:
        ``n_frames`` ``DriveFrame`` s.
    """
    if n_frames < 0 or not fps > 0 or frontal_s < 0:
        raise ConfigError("naturalistic_drive needs n_frames >= 0, fps > 0 and frontal_s >= 0")
    motion = naturalistic_motion(n_frames / fps, seed, scene, frontal_s)
    return [motion.frame(index, fps) for index in range(n_frames)]

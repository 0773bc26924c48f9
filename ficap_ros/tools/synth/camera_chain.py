"""The renderer's camera, from linear radiance to an 8-bit image: the lens (distortion remap,
PSF), the sensor (exposure, shot noise, full well, read noise, gain) and the ISP (tone curve, 8 bit,
JPEG).

Light stays linear until the tone curve (``ficap_ros.vision.tone``): a lens blurs light, the camera
then bends it. Motion blur, the stage between the lens and the sensor, is ``render``'s (it averages
sub-frames of the scene).
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.tools.synth.config import RenderConfig
from ficap_ros.tools.synth.lighting import LIGHTS
from ficap_ros.vision.tone import tone_curve

__all__ = ["CODE_MAX", "distortion_maps", "tone_lut", "lens_psf", "sensor_and_tone",
           "jpeg_round_trip"]

#: Levels of the 16-bit linear code the tone curve's lookup table is indexed by.
CODE_MAX = 65535


@functools.lru_cache(maxsize=4)
def distortion_maps(
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


@functools.lru_cache(maxsize=16)
def tone_lut(tone: str, gamma: float) -> np.ndarray:
    """8-bit output for every 16-bit linear code (the ISP's lookup table)."""
    lut = np.round(255.0 * tone_curve(np.arange(CODE_MAX + 1) / CODE_MAX, tone, gamma)).astype(np.uint8)
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


def lens_psf(scene: np.ndarray, sigma_px: float, defocus_radius_px: float) -> np.ndarray:
    """The lens blur, in linear light: a defocus disc, then a Gaussian (both symmetric, so the
    blurred edge's 50 % *linear* level stays on the true edge)."""
    shape = scene.shape
    if defocus_radius_px > 0:
        scene = cv2.filter2D(scene, -1, _disc_kernel(float(defocus_radius_px)), borderType=cv2.BORDER_REFLECT)
    if sigma_px > 0:
        scene = cv2.GaussianBlur(scene, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT)
    return scene.reshape(shape)


def sensor_and_tone(
    scene: np.ndarray, cfg: RenderConfig, exposure_ms: float, gain: float, rng: np.random.Generator,
) -> np.ndarray:
    """Linear scene (share of full well at the nominal exposure) -> charge (exposure, shot noise,
    full-well clipping, read noise) -> gain -> 16-bit code -> tone curve -> uint8."""
    light = LIGHTS[cfg.lighting]
    full_well = float(cfg.full_well_e)
    charge = scene * np.float32(full_well * exposure_ms / light.exposure_ms)  # electrons
    if cfg.noise:
        # OpenCV's SIMD Gaussian generator (faster than numpy's), seeded from ``seed`` via ``rng``.
        unit = np.empty(charge.shape, np.float32)
        cv2.setRNGSeed(int(rng.integers(0, 2**31 - 1)))
        cv2.randn(unit, 0.0, 1.0)
        # Shot noise: Poisson, sigma sqrt(electrons) (the Gaussian limit; a few electrons and up).
        charge += unit * np.sqrt(np.maximum(charge, 0.0))
    np.clip(charge, 0.0, full_well, out=charge)  # the well is full
    if cfg.noise and cfg.read_noise_e > 0:
        cv2.randn(unit, 0.0, float(cfg.read_noise_e))
        charge += unit
    code = charge * np.float32(gain / full_well * CODE_MAX)
    np.clip(code, 0.0, float(CODE_MAX), out=code)  # the converter's range (gain > 1 clips early)
    code += 0.5
    return tone_lut(cfg.tone, float(cfg.gamma))[code.astype(np.uint16)]


def jpeg_round_trip(image: np.ndarray, quality: int) -> np.ndarray:
    """The image as a JPEG of ``quality`` (1..100) decodes."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)

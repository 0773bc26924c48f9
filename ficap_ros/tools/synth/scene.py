"""What the renderer draws, before light and camera: the head and neck ellipsoids, the faces'
textures (40 mm white squares with their 32 mm tag36h11), the static car interior and the hair
texture, as albedo (linear reflectance relative to white paper).

Geometry is in the cap frame C (metres); everything here is cached and deterministic in its
arguments (the interior and hair in ``RenderConfig.background_seed``).
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from ficap_ros.geometry.tag36h11 import TAG_CELLS
from ficap_ros.vision.tone import srgb_to_linear

__all__ = ["HEAD_CENTRE_M", "HEAD_SEMI_AXES_M", "NECK_CENTRE_M", "NECK_SEMI_AXES_M", "CELLS_FACE",
           "NEAR_M", "WHITE_ALBEDO", "BLACK_ALBEDO", "HAIR_ALBEDO", "NECK_ALBEDO", "face_texture",
           "background", "hair_waves"]

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

#: Cells across a face: the tag's 8 plus a 1-cell white quiet zone each side (40 mm / 4 mm).
CELLS_FACE = 10
#: Nearest depth drawn, m: a face or head point closer to the camera is outside the view.
NEAR_M = 0.02
# Reflectances (linear, relative to the white paper): matte black toner or ink reflects about 4-6 %
# of what white paper does; dark hair a few %, the neck (skin and hair) more.
WHITE_ALBEDO = 1.0
BLACK_ALBEDO = 0.05
HAIR_ALBEDO = 0.05
NECK_ALBEDO = 0.12


@functools.lru_cache(maxsize=512)
def face_texture(tag_id: int, cell_px: int) -> np.ndarray:
    """Face texture (10c, 10c, 3) uint8, channels: face coverage, tag-square mask, blackness.

    Texture pixel j covers [j - 0.5, j + 0.5]; the tag's outer edge is at c - 0.5 and 9c - 0.5.
    """
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(dictionary, int(tag_id), TAG_CELLS * cell_px)
    n = CELLS_FACE * cell_px
    tex = np.zeros((n, n, 3), np.uint8)
    tex[..., 0] = 255
    inner = slice(cell_px, (CELLS_FACE - 1) * cell_px)
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
def background(width: int, height: int, seed: int, color: bool) -> np.ndarray:
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
def hair_waves(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random wave vectors and phases for the hair texture (attached to the head)."""
    rng = np.random.default_rng(seed + 104729)
    k = rng.normal(0.0, 1.0, (6, 3))
    k *= rng.uniform(8.0, 40.0, (6, 1)) / np.linalg.norm(k, axis=1, keepdims=True)
    return k, rng.uniform(0.0, 2 * math.pi, 6)

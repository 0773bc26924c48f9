"""One tag36h11 tag rendered under a perspective with exact corners, shared by the detector, edge
and tag-family tests (not a test module: no ``test_`` prefix)."""

from __future__ import annotations

import cv2
import numpy as np

DICT = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
SUPERSAMPLE = 8


def tag_image(
    tag_id: int, corners: np.ndarray, size_wh: tuple[int, int], rng: np.random.Generator, *,
    background: int, levels: tuple[float, float], blur: float, noise: float,
) -> np.ndarray:
    """The tag (with its white one-cell margin) drawn so that its outer corners c0..c3 (OpenCV
    order and pixel convention) land on ``corners`` (4, 2), on a ``background`` grey canvas.

    Rendered at 8x by warpPerspective and area-downsampled, so pixel values are the mean over each
    pixel's square; then mapped to grey ``levels`` (black, white), blurred by a Gaussian of sd
    ``blur`` px and given Gaussian noise of sd ``noise`` grey levels drawn from ``rng``.
    """
    w, h = size_wh
    marker = cv2.aruco.generateImageMarker(DICT, tag_id, 8 * 16, borderBits=1)
    p = marker.shape[0]
    pad = p // 8
    face = np.full((p + 2 * pad, p + 2 * pad), 255, np.uint8)
    face[pad:pad + p, pad:pad + p] = marker
    src = np.array([[-0.5, -0.5], [p - 0.5, -0.5], [p - 0.5, p - 0.5], [-0.5, p - 0.5]]) + pad
    dst_hi = (corners + 0.5) * SUPERSAMPLE - 0.5
    hom = cv2.getPerspectiveTransform(src.astype(np.float32), dst_hi.astype(np.float32))
    hi = cv2.warpPerspective(face, hom, (w * SUPERSAMPLE, h * SUPERSAMPLE), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=background)
    img = cv2.resize(hi, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    img = levels[0] + (levels[1] - levels[0]) * img / 255
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img = img + rng.normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def random_tag(rng: np.random.Generator, side_px: float, blur: float = 0.7, noise: float = 2.0,
               tag_id: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """A tag of about ``side_px`` turned by a random angle, each corner moved up to a tenth of the
    side, in the middle of a canvas at least 320 x 240: (image, true corners (4, 2))."""
    w, h = max(320, int(2.5 * side_px)), max(240, int(2.5 * side_px))
    ang = rng.uniform(0, 2 * np.pi)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side_px / 2
    corners = square @ rot.T + rng.uniform(-0.1, 0.1, (4, 2)) * side_px + np.array([w, h]) / 2
    img = tag_image(tag_id, corners, (w, h), rng, background=110, levels=(25, 225), blur=blur, noise=noise)
    return img, corners


def oblique_tag(tag_id: int, side_px: float, angle_deg: float, tilt: float, blur: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A tag of ``side_px`` turned by ``angle_deg`` and drawn as a trapezoid (its top side
    ``1 - tilt`` and its bottom ``1 + tilt`` times as wide: seen obliquely) on a 200 x 200 canvas:
    (image, true corners (4, 2))."""
    w = h = 200
    a = np.radians(angle_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side_px / 2
    square[:, 0] *= np.where(square[:, 1] < 0, 1 - tilt, 1 + tilt)
    corners = square @ rot.T + np.array([w, h]) / 2 + rng.uniform(-0.5, 0.5, 2)
    img = tag_image(tag_id, corners, (w, h), rng, background=120, levels=(30, 220), blur=blur, noise=2.0)
    return img, corners


def moving_tag_image(
    tag_id: int, corners: np.ndarray, motion: np.ndarray, size_wh: tuple[int, int], rng: np.random.Generator,
    *, levels_linear: tuple[float, float] = (0.03, 0.7), blur: float = 0.6, noise: float = 1.5,
    instants: int = 32,
) -> np.ndarray:
    """The tag moving over the exposure, as a camera records it: its corners at ``corners + s
    motion`` (s over ``instants`` midpoints of -1/2..1/2; ``corners`` (4, 2) are the mid-exposure
    ones, ``motion`` (4, 2) each corner's motion over the exposure), the instants' light averaged in
    linear light (black and white ``levels_linear``, the background the white's half), blurred by a
    Gaussian of sd ``blur`` px, then through the sRGB curve to 8 bits with Gaussian noise of sd
    ``noise`` grey levels."""
    from ficap_ros.vision.tone import srgb_encode_slope

    acc = np.zeros(size_wh[::-1])
    for s in (np.arange(instants) + 0.5) / instants - 0.5:
        img = tag_image(tag_id, corners + s * motion, size_wh, rng, background=128, levels=(0, 255),
                        blur=0.0, noise=0.0).astype(np.float64) / 255.0
        acc += levels_linear[0] + (levels_linear[1] - levels_linear[0]) * img
    light = cv2.GaussianBlur(acc / instants, (0, 0), blur)
    grey = 255.0 * srgb_encode_slope(light)[0] + rng.normal(0.0, noise, light.shape)
    return np.clip(np.round(grey), 0, 255).astype(np.uint8)


def two_tag_scene(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A 240 x 320 frame of two tags (one cut by the image's border) on noise: (image, corners)."""
    rng = np.random.default_rng(seed)
    corners = []
    img = np.zeros((240, 320), np.uint8)
    for k, (cx, cy, side) in enumerate(((110.0, 120.0, 70.0), (300.0, 40.0, 50.0))):
        a = rng.uniform(0.0, 2.0 * np.pi)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        c = (np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side / 2.0) @ rot.T + [cx, cy]
        c += rng.normal(0.0, 1.5, c.shape)
        part = tag_image(5 + k, c, (320, 240), rng, background=90, levels=(30.0, 220.0), blur=0.8, noise=3.0)
        img = np.maximum(img, part) if k else part
        corners.append(c)
    return img, np.array(corners)

"""The renderer's lighting: per-mode light levels in units of the sensor's full well, the
irradiance of a face, and the ``high`` mode's spotlights.

Directions are in the camera optical frame (x right, y down, z forward).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["LIGHTINGS", "Light", "LIGHTS", "irradiance", "spotlights"]

#: Illumination modes of ``RenderConfig.lighting``.
LIGHTINGS = ("neutral", "high", "low")


@dataclass(frozen=True)
class Light:
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
# high is brighter still, and its spotlights (``spotlights``) push whites well past full well;
# low (night, one street lamp) collects 1-10 % and the camera answers with gain 2.5 and a long
# exposure, so the image is dark and noisy.
LIGHTS: dict[str, Light] = {
    "neutral": Light((0.25, -0.45, -0.86), 0.15, 0.05, 0.004, 0.75, 8.0, 1.0, camera_lamp=0.5),
    "high": Light((0.3, -0.5, -0.81), 0.62, 0.18, 0.008, 1.1, 4.0, 1.0),
    "low": Light((0.85, -0.15, 0.5), 0.008, 0.09, 0.0015, 0.05, 20.0, 2.5),
}


def irradiance(light: Light, normals_cam: np.ndarray) -> np.ndarray:
    """Irradiance of faces with outward normals (N, 3) from the ambient and directional light
    (the lamp at the camera varies across a face and is added per pixel)."""
    l_vec = np.asarray(light.toward_light_cam, np.float64)
    l_vec = l_vec / np.linalg.norm(l_vec)
    return light.ambient + light.diffuse * np.clip(normals_cam @ l_vec, 0.0, None)


def spotlights(img: np.ndarray, faces_cam: np.ndarray, k: np.ndarray, rng: np.random.Generator) -> None:
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

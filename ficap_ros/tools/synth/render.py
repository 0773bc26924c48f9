"""``render``: a cap model at a known pose through the whole camera chain, with exact ground truth.

The steps, in the order a camera forms an image (``ficap_ros.tools.synth``'s docstring has the
model): the scene's linear radiance by the ideal pinhole (``raster``), averaged over the exposure's
sub-frames when the pose is a function of time (motion blur; each row over its own window with a
rolling shutter: ``shutter``), the lighting's spotlights and flare,
the lens (distortion remap, PSF), the sensor and the ISP (``camera_chain``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth.camera_chain import (
    distortion_maps,
    jpeg_round_trip,
    lens_psf,
    sensor_and_tone,
)
from ficap_ros.tools.synth.config import RenderConfig, RenderedFrame
from ficap_ros.tools.synth.lighting import LIGHTS, spotlights
from ficap_ros.tools.synth.raster import render_scene
from ficap_ros.tools.synth.shutter import rolling_exposure

__all__ = ["render"]


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


def _pose_source(
    T_cam_cap: Transform | Callable[[float], Transform],
) -> tuple[Transform, Callable[[float], Transform] | None]:
    """(the pose at mid-exposure, the pose function or None for a still pose)."""
    if isinstance(T_cam_cap, Transform):
        return T_cam_cap, None
    if callable(T_cam_cap):
        T_mid = T_cam_cap(0.0)
        if not isinstance(T_mid, Transform):
            raise ConfigError("a pose function given to render must return a Transform")
        return T_mid, T_cam_cap
    raise ConfigError(f"T_cam_cap must be a Transform or a function of time, got {type(T_cam_cap).__name__}")


@dataclass(frozen=True)
class _Canvas:
    """Where the ideal pinhole renders: its K (the camera's, principal point shifted by the
    canvas offset) and size; for a distorted camera, the maps that remap it into the image."""

    k: np.ndarray
    width: int
    height: int
    maps: tuple[np.ndarray, np.ndarray] | None


def _canvas(camera: CameraModel) -> _Canvas:
    """The image itself for a pinhole; for a distorted camera an ideal pinhole with the same K on
    a canvas large enough for every distorted pixel to look up (``camera_chain.distortion_maps``)."""
    if not camera.is_distorted:
        return _Canvas(camera.K, camera.width_px, camera.height_px, None)
    map_x, map_y, (ox, oy, w_canvas, h_canvas) = distortion_maps(
        camera.width_px, camera.height_px, camera.K.tobytes(), camera.D.tobytes(),
        camera.distortion_model
    )
    k = camera.K.copy()
    k[0, 2] += ox
    k[1, 2] += oy
    return _Canvas(k, w_canvas, h_canvas, (map_x, map_y))


def _exposure(
    model: CapModel, camera: CameraModel, canvas: _Canvas, T_mid: Transform,
    pose_at: Callable[[float], Transform] | None, cfg: RenderConfig, exposure_ms: float,
) -> tuple[np.ndarray, dict[int, float], list[int]]:
    """The scene's radiance over the exposure (the mean of the sub-frames' when the pose moves;
    each row's own window with a rolling shutter, ``shutter.rolling_exposure``), and the visible
    fractions and front ids at mid-exposure."""
    if pose_at is not None and cfg.readout_ms > 0.0:
        return rolling_exposure(model, camera, pose_at, cfg)
    times = [0.0] if pose_at is None or not cfg.motion_blur else list(
        _subframe_times_s(model, camera, pose_at, exposure_ms / 1000.0, cfg.motion_subframes))
    scene: np.ndarray | None = None
    for t in times:
        # Linear light adds: the exposure is the mean of the sub-frames' irradiance.
        pose = T_mid if t == 0.0 or pose_at is None else pose_at(t)
        img, vis, front = render_scene(model, canvas.k, canvas.width, canvas.height, pose, cfg)
        if t == 0.0:
            visible, front_ids = vis, front
        if scene is None:
            scene = img
        else:
            scene += img
    assert scene is not None
    if len(times) > 1:
        scene *= np.float32(1.0 / len(times))
    return scene, visible, front_ids


def _glare_and_lens(
    scene: np.ndarray, model: CapModel, camera: CameraModel, canvas: _Canvas, T_mid: Transform,
    front_ids: list[int], cfg: RenderConfig, spot_rng: np.random.Generator,
) -> np.ndarray:
    """Spotlights (``high``) and veiling flare on the scene, then the lens: the distortion remap
    and the PSF, in linear light. Returns (H, W) or (H, W, 3) float32."""
    if cfg.lighting == "high":
        idx = [model.index_of(t) for t in front_ids]
        faces = T_mid.apply(model.face_corners_mm()[idx].reshape(-1, 3) / 1000.0).reshape(-1, 4, 3)
        spotlights(scene, faces, canvas.k, spot_rng)
    scene += np.float32(LIGHTS[cfg.lighting].flare)
    if scene.shape[2] == 1:
        scene = scene[..., 0]
    if canvas.maps is not None:
        map_x, map_y = canvas.maps
        scene = cv2.remap(scene, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return lens_psf(scene, cfg.psf_sigma_for(camera.height_px), cfg.defocus_radius_px)


def _corners_px(model: CapModel, camera: CameraModel, T_cam_cap: Transform,
                tag_ids: list[int]) -> dict[int, np.ndarray]:
    """Exact projected outer corners (4, 2) of the tags, in the (distorted) image."""
    corners_px: dict[int, np.ndarray] = {}
    if tag_ids:
        idx = [model.index_of(t) for t in tag_ids]
        pts = T_cam_cap.apply(model.corners_mm[idx].reshape(-1, 3) / 1000.0)
        px = camera.project(pts).reshape(-1, 4, 2)
        for n, tag_id in enumerate(tag_ids):
            corners_px[tag_id] = px[n]
    return corners_px


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
            ``DriveMotion.around`` gives one for a naturalistic drive. With
            ``config.readout_ms`` (a rolling shutter) each row is exposed at its own time
            (``config.timing``; 0 = the middle row's mid-exposure, the truth), and without
            ``config.motion_blur`` each row (or a global shutter's frame) is one instant.
        config: rendering options (default ``RenderConfig()``).
        seed: seeds noise and spotlights (the background uses ``config.background_seed``).

    Returns:
        The frame with its exact ground truth (``RenderedFrame``).
    """
    cfg = config or RenderConfig()
    rng = np.random.default_rng(seed)
    exposure_ms, gain = cfg.exposure_and_gain()
    T_mid, pose_at = _pose_source(T_cam_cap)
    canvas = _canvas(camera)
    scene, visible, front_ids = _exposure(model, camera, canvas, T_mid, pose_at, cfg, exposure_ms)
    spot_rng = np.random.default_rng(rng.integers(0, 2**63 - 1))
    scene = _glare_and_lens(scene, model, camera, canvas, T_mid, front_ids, cfg, spot_rng)
    image = sensor_and_tone(scene, cfg, exposure_ms, gain, rng)
    if cfg.jpeg_quality is not None:
        image = jpeg_round_trip(image, cfg.jpeg_quality)
    image = np.ascontiguousarray(image)
    image.setflags(write=False)
    return RenderedFrame(image=image, T_cam_cap=T_mid,
                         corners_px=_corners_px(model, camera, T_mid, front_ids),
                         visible_fraction=visible, camera=camera)

"""A rolling shutter rendered with motion blur: every image row integrates the scene over its own
exposure window (``geometry.camera.CameraTiming``'s convention).

Row ``y`` of ``H`` is exposed for ``E`` centred on ``t(y) = CameraTiming.row_time_s(y, H)``,
seconds from the stamp (the middle row's mid-exposure): ``(y + 0.5 - H / 2) / H * R`` for rows
read top to bottom over the readout ``R``. The scene is rendered at sub-step times
``tau_j = j * step`` on one grid that every row shares (``sample_weights``):

1. Each row takes ``m`` sub-steps ``t(y) + (k - (m - 1) / 2) * step``, ``k = 0 .. m - 1``: the
   midpoint rule over its window ``E = m * step``, as a global shutter's motion blur averages its
   sub-frames (``m = 1``: the row is one instant, no blur).
2. A sub-step that falls between two grid samples is their linear interpolation, so each row's
   weights sum to 1 and their mean time is exactly ``t(y)``, wherever the row falls on the grid.
3. A sample is rendered only over the band of rows whose weights use it (``raster.render_scene``
   with ``rows``), and the sample at the stamp (``tau = 0``) over the whole image, which gives the
   frame's visible fractions at the stamp. Each row takes ``m + 1`` samples, so a frame costs
   about ``m + 1`` whole images (and the stamp's), however finely its rows' times are spread.

Linear light adds, so a row's radiance is the weighted sum of its samples' radiance; the lens,
sensor and ISP then act on the assembled image (``render``). Undistorted cameras only: the rows'
times are those of the image, which a distortion remap would move.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth.config import RenderConfig
from ficap_ros.tools.synth.raster import render_scene

__all__ = ["MAX_SAMPLES", "sample_weights", "substeps", "rolling_exposure",
           "rolling_corners_px"]

#: Most grid samples a frame renders (a bound on the cost of very slow exposures of fast motion).
MAX_SAMPLES = 256
#: Most sub-steps per row's exposure (as ``render``'s global-shutter sub-frames).
MAX_SUBSTEPS = 31


def sample_weights(row_times_s: np.ndarray, step_s: float,
                   substeps: int) -> tuple[np.ndarray, np.ndarray]:
    """The shared sample grid and each row's weights on it (the module's steps 1 and 2).

    Args:
        row_times_s: (H,) each row's exposure centre, s from the stamp.
        step_s: grid spacing, s (> 0).
        substeps: ``m``, sub-steps per row (its exposure is ``m * step_s``; 1: an instant).

    Returns:
        times_s (J,): the grid, integer multiples of ``step_s`` (0 among them when the rows'
        times span it); weights (H, J): non-negative, each row's summing to 1 with mean time
        exactly its own.
    """
    t = np.asarray(row_times_s, dtype=np.float64).reshape(-1)
    m = int(substeps)
    if not (step_s > 0.0 and m >= 1):
        raise ConfigError(f"a rolling shutter needs a positive step and sub-steps, got {step_s}, {m}")
    first = t - 0.5 * (m - 1) * step_s  # each row's first sub-step
    j_lo = math.floor(float(first.min()) / step_s)
    u = first / step_s - j_lo
    j0 = np.floor(u).astype(np.int64)
    alpha = u - j0
    n_samples = int(j0.max()) + m + 1
    if n_samples > MAX_SAMPLES:
        raise ConfigError(f"a rolling shutter frame of {n_samples} samples (at most {MAX_SAMPLES}): "
                          "use a longer step or fewer sub-steps")
    weights = np.zeros((t.size, n_samples))
    rows = np.arange(t.size)
    for k in range(m):
        np.add.at(weights, (rows, j0 + k), (1.0 - alpha) / m)
        np.add.at(weights, (rows, j0 + k + 1), alpha / m)
    return (j_lo + np.arange(n_samples)) * step_s, weights


def _corner_speed_px_s(model: CapModel, camera: CameraModel,
                       pose_at: Callable[[float], Transform], span_s: float) -> float:
    """The fastest corner's image speed over ``[-span_s / 2, span_s / 2]``, px/s (from five
    poses across it)."""
    pts = model.corners_mm.reshape(-1, 3) / 1000.0
    times = np.linspace(-0.5 * span_s, 0.5 * span_s, 5)
    uv = np.stack([camera.project(pose_at(float(t)).apply(pts)) for t in times])
    ok = np.all(np.isfinite(uv), axis=(0, 2))
    if not ok.any() or span_s <= 0.0:
        return 0.0
    travel = np.linalg.norm(np.diff(uv[:, ok], axis=0), axis=2)
    return float(travel.max() / (times[1] - times[0]))


def substeps(model: CapModel, camera: CameraModel, pose_at: Callable[[float], Transform],
             cfg: RenderConfig, timing: CameraTiming) -> tuple[float, int]:
    """(step_s, m) of a rolling-shutter frame.

    With motion blur, ``m`` sub-steps over the exposure ``E`` (``cfg.motion_subframes``, or
    enough that no corner moves more than half a pixel between two; at most ``MAX_SUBSTEPS``, and
    no more than ``MAX_SAMPLES`` allows), ``step_s = E / m``. A row that needs one sub-step (motion
    too slow to blur, or no blur) is one instant, interpolated between the two samples around it:
    those are ``cfg.motion_subframes`` per readout (one per exposure with blur), or a quarter pixel
    of corner travel apart (each row takes two samples however close they are, so a finer grid
    costs calls, not pixels).
    """
    exposure_s, readout_s = timing.exposure_ms * 1e-3, timing.readout_ms * 1e-3
    span_s = exposure_s + readout_s
    lowest_s = span_s / (MAX_SAMPLES - MAX_SUBSTEPS - 2)
    speed = 0.0 if cfg.motion_subframes else _corner_speed_px_s(model, camera, pose_at, span_s)
    if exposure_s > 0.0:
        m = int(cfg.motion_subframes) or int(math.ceil(2.0 * speed * exposure_s))
        m = min(max(m, 1), MAX_SUBSTEPS, max(int(exposure_s / lowest_s), 1))
        if m > 1:
            return exposure_s / m, m
        if cfg.motion_subframes:
            return max(exposure_s, lowest_s), 1
    elif cfg.motion_subframes:
        return max(readout_s / int(cfg.motion_subframes), lowest_s), 1
    return (max(0.25 / speed, lowest_s) if speed > 0.0 else max(readout_s, lowest_s)), 1


def rolling_exposure(
    model: CapModel, camera: CameraModel, pose_at: Callable[[float], Transform],
    cfg: RenderConfig,
) -> tuple[np.ndarray, dict[int, float], list[int]]:
    """The scene's radiance with each row exposed over its own window (``cfg.timing``), and the
    visible fractions and front ids at the stamp (``raster.render_scene``'s, of the whole image).

    Raises:
        ConfigError: a distorted camera, or more samples than ``MAX_SAMPLES``.
    """
    if camera.is_distorted:
        raise ConfigError("a rolling shutter is rendered for undistorted cameras only")
    timing = cfg.timing
    width, height = camera.width_px, camera.height_px
    step_s, m = substeps(model, camera, pose_at, cfg, timing)
    times, weights = sample_weights(timing.row_time_s(np.arange(height), height), step_s, m)
    used = weights > 0.0
    stamp = int(np.argmin(np.abs(times)))
    scene: np.ndarray | None = None
    visible: dict[int, float] = {}
    front: list[int] = []
    for j, t in enumerate(times):
        rows = np.flatnonzero(used[:, j])
        if j != stamp and not rows.size:
            continue
        r0, r1 = (int(rows[0]), int(rows[-1]) + 1) if rows.size else (0, 0)
        band = (0, height) if j == stamp else (r0, r1)
        img, vis, ids = render_scene(model, camera.K, width, height, pose_at(float(t)), cfg, band)
        if j == stamp:
            visible, front = vis, ids
            img = img[r0:r1]
        if scene is None:
            scene = np.zeros((height, width, img.shape[2]), np.float32)
        scene[r0:r1] += weights[r0:r1, j, None, None].astype(np.float32) * img
    assert scene is not None
    return scene, visible, front


def rolling_corners_px(model: CapModel, camera: CameraModel,
                       pose_at: Callable[[float], Transform], timing: CameraTiming,
                       tag_ids: list[int], iterations: int = 6) -> dict[int, np.ndarray]:
    """Where a rolling shutter shows each tag's outer corners (4, 2): the projection at the
    time of the row it lands on (a fixed point, found by iterating from the stamp's
    projection); the mid-exposure corners of that row (a row's blur is centred there)."""
    out: dict[int, np.ndarray] = {}
    if not tag_ids:
        return out
    idx = [model.index_of(t) for t in tag_ids]
    pts = model.corners_mm[idx].reshape(-1, 3) / 1000.0
    px = camera.project(pose_at(0.0).apply(pts))
    for _ in range(iterations):
        when = timing.row_time_s(px[:, 1], camera.height_px)
        px = np.stack([camera.project(pose_at(float(t)).apply(p[None]))[0]
                       for t, p in zip(when, pts)])
    for n, tag_id in enumerate(tag_ids):
        out[tag_id] = px[4 * n:4 * n + 4]
    return out

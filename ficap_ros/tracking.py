"""Tracking: find the cap's tags where the previous poses say they are, without a search.

Between consecutive frames of a 30-60 fps camera the cap moves little, and it is rigid, so its
pose (extrapolated at constant velocity from the last two) predicts every tag's corners to a few
pixels. The edge refinement (``detection.refine_corners_edge_ok``) pulls the predicted corners
onto the tag's border; then each tag is *verified* by reading its 8x8 cells (black border and
6x6 data bits) through the homography of its refined corners and comparing them with the code
of the id it is expected to be. A tag36h11 code is at least 11 bits from any other, and a wrong
image patch matches one given 64-cell pattern within 2 cells with a chance of about 1e-16 (for
random cells), so a verified tag is as trustworthy as a searched one.

This replaces ArUco's search (the costliest step: adaptive thresholds, contours, candidate
decoding over the whole image) on every tracked frame; the pipeline falls back to the search when
tracking cannot verify enough tags (``pipeline.FrameProcessor``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.camera import CameraModel
from ficap_ros.cap_model import CapModel
from ficap_ros.detection import TAG_CELLS as _CELLS
from ficap_ros.detection import tag_cells, tag_homographies
from ficap_ros.errors import ConfigError
from ficap_ros.transform import Transform

__all__ = ["TrackConfig", "extrapolate_pose", "predict_tags", "verify_tags", "decode_tags", "tag_cells",
           "view_angles_deg"]

@dataclass(frozen=True)
class TrackConfig:
    """Tracking settings.

    Attributes:
        max_view_angle_deg: tags seen more obliquely than this (angle between the tag's normal
            and the line of sight) are not looked for.
        pose_max_view_angle_deg: tags seen more obliquely than this at the predicted pose are
            reported but left out of the pose (their corners are the least accurate), as long as
            ``min_tags`` others remain.
        min_side_px: tags whose predicted shortest side is below this are not looked for (cells
            under about 1 px cannot be read).
        border_px: nor tags with a predicted corner closer than this to the image border.
        max_cell_errors: a tag is verified when at most this many of its 64 cells (border and
            data) read differently from its id's code.
        min_contrast: ... and when its white margin is at least this many grey levels brighter
            than its black border.
        min_tags: fewest verified tags for a tracked frame; with fewer the frame is searched.
    """

    max_view_angle_deg: float = 86.0
    pose_max_view_angle_deg: float = 78.0
    min_side_px: float = 8.0
    border_px: float = 4.0
    max_cell_errors: int = 2
    min_contrast: float = 20.0
    min_tags: int = 2

    def __post_init__(self) -> None:
        if not 0.0 < self.max_view_angle_deg < 90.0:
            raise ConfigError(f"max_view_angle_deg must be in (0, 90), got {self.max_view_angle_deg}")
        if not 0.0 < self.pose_max_view_angle_deg <= 90.0:
            raise ConfigError(f"pose_max_view_angle_deg must be in (0, 90], got {self.pose_max_view_angle_deg}")
        if not self.min_side_px >= 4.0:
            raise ConfigError(f"min_side_px must be >= 4, got {self.min_side_px}")
        if not 0 <= self.max_cell_errors <= 4:
            raise ConfigError(f"max_cell_errors must be in [0, 4], got {self.max_cell_errors}")
        if self.min_tags < 1:
            raise ConfigError(f"min_tags must be >= 1, got {self.min_tags}")


def extrapolate_pose(
    T_prev: Transform, T_prev2: Transform | None, dt_ratio: float = 1.0
) -> Transform:
    """The cap pose one step on at constant velocity.

    Args:
        T_prev: T_cam_cap of the last frame.
        T_prev2: T_cam_cap of the frame before it (None: assume no motion).
        dt_ratio: (t_now - t_prev) / (t_prev - t_prev2); 1 for evenly spaced frames.

    Returns:
        Predicted T_cam_cap: rotation continued about the camera's axes, cap origin continued along
        a straight line.
    """
    if T_prev2 is None:
        return T_prev
    step = (T_prev.rotation * T_prev2.rotation.inv()).as_rotvec() * dt_ratio
    t = T_prev.translation_m + (T_prev.translation_m - T_prev2.translation_m) * dt_ratio
    return Transform(Rotation.from_rotvec(step) * T_prev.rotation, t)


def view_angles_deg(model: CapModel, T_cam_cap: Transform) -> np.ndarray:
    """Angle (model.ids order) between each tag's outward normal and its line of sight to the
    camera, deg: 0 = seen head-on, 90 = edge-on, above 90 = facing away."""
    centres_cam = T_cam_cap.apply(model.centres_mm / 1000.0)
    normals_cam = model.normals @ T_cam_cap.rotation_matrix.T
    dist = np.maximum(np.linalg.norm(centres_cam, axis=1), 1e-9)
    return np.degrees(np.arccos(np.clip(-np.einsum("ij,ij->i", normals_cam, centres_cam) / dist, -1.0, 1.0)))


def predict_tags(
    model: CapModel, camera: CameraModel, T_cam_cap: Transform, config: TrackConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Ids (K,) and distorted-image corners (K, 4, 2) of the tags worth looking for at a pose.

    A tag is worth it when it faces the camera within ``max_view_angle_deg``, lies in front of it,
    has every corner inside the image (``border_px`` in) and a shortest side of ``min_side_px``.
    """
    cfg = config or TrackConfig()
    facing = (view_angles_deg(model, T_cam_cap) < cfg.max_view_angle_deg) & (
        T_cam_cap.apply(model.centres_mm / 1000.0)[:, 2] > 0.05)
    if not facing.any():
        return np.zeros(0, dtype=int), np.zeros((0, 4, 2))
    ids = np.asarray(model.ids)[facing]
    px = camera.project(T_cam_cap.apply(model.corners_mm[facing].reshape(-1, 3) / 1000.0)).reshape(-1, 4, 2)
    side = np.linalg.norm(px - np.roll(px, 1, axis=1), axis=2).min(axis=1)
    b = cfg.border_px
    inside = (
        np.all(np.isfinite(px), axis=(1, 2))
        & np.all(px[..., 0] >= b, axis=1) & np.all(px[..., 0] <= camera.width_px - 1 - b, axis=1)
        & np.all(px[..., 1] >= b, axis=1) & np.all(px[..., 1] <= camera.height_px - 1 - b, axis=1)
    )
    keep = inside & (side >= cfg.min_side_px)
    return ids[keep], px[keep]


def _cell_grid() -> np.ndarray:
    """Centres (100, 2) of the 10x10 cells (white margin ring + 8x8 tag), in cell units from c0."""
    c = np.arange(-1, _CELLS + 1) + 0.5
    gx, gy = np.meshgrid(c, c)
    return np.column_stack([gx.ravel(), gy.ravel()])


_GRID = _cell_grid()
_GRID_H = np.concatenate([_GRID, np.ones((len(_GRID), 1))], axis=1)  # homogeneous (100, 3)
_RING_MARGIN = ((_GRID < 0) | (_GRID > _CELLS)).any(axis=1)  # the white quiet zone
_INNER = ~_RING_MARGIN  # the 8x8 tag cells, row-major
_BORDER = ((_GRID[_INNER] < 1) | (_GRID[_INNER] > _CELLS - 1)).any(axis=1)  # of the 64: the black border


def verify_tags(
    gray: np.ndarray, ids: np.ndarray, corners_px: np.ndarray, config: TrackConfig | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read each tag's cells at its corners and compare them with its id's code.

    Args:
        gray: (H, W) uint8 image.
        ids: (K,) expected ids.
        corners_px: (K, 4, 2) corners, OpenCV order and pixel convention.
        config: acceptance thresholds.

    Returns:
        (verified (K,) bool, cell_errors (K,) int, contrast (K,) grey levels white - black).
    """
    cfg = config or TrackConfig()
    k = len(ids)
    if k == 0:
        return np.zeros(0, dtype=bool), np.zeros(0, dtype=int), np.zeros(0)
    try:
        hom = tag_homographies(np.asarray(corners_px, dtype=np.float64))
    except np.linalg.LinAlgError:
        return np.zeros(k, dtype=bool), np.full(k, 64), np.zeros(k)
    p = np.einsum("kij,gj->kgi", hom, _GRID_H)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = (p[..., :2] / p[..., 2:3]).astype(np.float32)  # (K, 100, 2)
    vals = cv2.remap(gray, xy[..., 0], xy[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(np.float64)  # (K, 100)
    inner = vals[:, _INNER]  # (K, 64)
    expected = np.stack([tag_cells(int(i)).ravel() for i in ids])  # (K, 64) True = black
    # Levels from the cells every tag shares: its black border and the white margin around it.
    white = vals[:, _RING_MARGIN].mean(axis=1)
    black = inner[:, _BORDER].mean(axis=1)
    read_black = inner < 0.5 * (white + black)[:, None]
    errors = (read_black != expected).sum(axis=1)
    contrast = white - black
    ok = (errors <= cfg.max_cell_errors) & (contrast >= cfg.min_contrast) & np.all(np.isfinite(xy), axis=(1, 2))
    return ok, errors, contrast


@lru_cache(maxsize=1)
def _all_codes() -> np.ndarray:
    """(587, 36) the 6x6 data cells of every tag36h11 id (True = black), OpenCV's drawing."""
    n = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11).bytesList.shape[0]
    codes = np.stack([tag_cells(i)[1:-1, 1:-1].ravel() for i in range(n)])
    codes.setflags(write=False)
    return codes


def _pack36(bits: np.ndarray) -> np.ndarray:
    """(N, 36) bool -> (N,) uint64 words."""
    return (bits.astype(np.uint64) << np.arange(36, dtype=np.uint64)).sum(axis=1, dtype=np.uint64)


@lru_cache(maxsize=1)
def _all_words() -> np.ndarray:
    return _pack36(_all_codes())


def decode_tags(
    gray: np.ndarray, corners_px: np.ndarray, max_bit_errors: int = 2, min_contrast: float = 10.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read quads of unknown id as tag36h11 tags (the search's second chance).

    Each quad's cells are read as ``verify_tags`` reads them, in its four corner orders; the
    order and id whose 36 data cells are nearest (Hamming) win. A quad is a tag when at most
    ``max_bit_errors`` data cells and 2 of the 28 border cells disagree and the border is at
    least ``min_contrast`` grey levels darker than the white margin. tag36h11 codes are 11 bits
    apart, so 2 errors are corrected with room to spare (AprilTag 3 corrects 2 by default).

    Args:
        gray: (H, W) uint8 image.
        corners_px: (K, 4, 2) quads (any corner order), refined on ``gray``.

    Returns:
        (ok (K,) bool, ids (K,), bit errors (K,), corners (K, 4, 2) in the id's OpenCV order).
    """
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    k = len(c)
    if k == 0:
        return np.zeros(0, bool), np.zeros(0, int), np.zeros(0, int), c.copy()
    rolled = np.stack([np.roll(c, -r, axis=1) for r in range(4)], axis=1).reshape(-1, 4, 2)  # (4K,)
    try:
        hom = tag_homographies(rolled)
    except np.linalg.LinAlgError:
        return np.zeros(k, bool), np.zeros(k, int), np.full(k, 36), c.copy()
    p = np.einsum("kij,gj->kgi", hom, _GRID_H)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = (p[..., :2] / p[..., 2:3]).astype(np.float32)
    finite = np.all(np.isfinite(xy), axis=(1, 2))
    xy = np.where(np.isfinite(xy), xy, -1.0)
    vals = cv2.remap(gray, xy[..., 0], xy[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(np.float64)
    inner = vals[:, _INNER]
    white = vals[:, _RING_MARGIN].mean(axis=1)
    black = inner[:, _BORDER].mean(axis=1)
    read_black = inner < 0.5 * (white + black)[:, None]
    border_errors = (~read_black[:, _BORDER]).sum(axis=1)
    data = read_black.reshape(-1, _CELLS, _CELLS)[:, 1:-1, 1:-1].reshape(-1, 36)
    # Hamming distances to every code as popcounts of 36-bit words: (4K, 587) in one pass.
    dist = np.bitwise_count(_pack36(data)[:, None] ^ _all_words()[None, :])
    best_id, best_err = dist.argmin(axis=1), dist.min(axis=1)
    good = finite & (border_errors <= 2) & (white - black >= min_contrast)
    score = np.where(good, best_err, 99).reshape(k, 4)
    order = score.argmin(axis=1)
    rows = np.arange(k) * 4 + order
    errors = score[np.arange(k), order]
    ok = errors <= max_bit_errors
    return ok, best_id[rows].astype(int), errors.astype(int), rolled[rows]

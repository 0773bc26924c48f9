"""The tag geometry of the as-built model: rigid tag frames, corners from tag poses, the gauge
alignment, the size of a cap, and the edge offset a border-line detector adds to corners.

Tag frame (local): x along the tag's top edge (TL -> TR), y down (TL -> BL), z = x cross y (into
the cap); local corners (-16, -16, 0), (16, -16, 0), (16, 16, 0), (-16, 16, 0) mm = TL, TR, BR, BL.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.cap_model import TAG_SIDE_MM
from ficap_ros.geometry.transform import Transform

__all__ = ["LOCAL_CORNERS_MM", "tag_frames", "corners_from_params", "align_model", "size_ratio",
           "edge_shift_px", "rms_radius"]

_HALF = TAG_SIDE_MM / 2.0
#: Tag corners in the tag's own frame, mm (TL, TR, BR, BL).
LOCAL_CORNERS_MM = np.array(
    [[-_HALF, -_HALF, 0.0], [_HALF, -_HALF, 0.0], [_HALF, _HALF, 0.0], [-_HALF, _HALF, 0.0]]
)


def tag_frames(corners_mm: np.ndarray) -> tuple[Rotation, np.ndarray]:
    """Best-fit rigid tag frames (R_cap_tag, centre mm) of corner sets (N, 4, 3).

    Each is the rotation that best maps ``LOCAL_CORNERS_MM`` onto the (centred) corners, so a
    slightly non-square measured tag gets its closest rigid square.
    """
    corners = np.asarray(corners_mm, dtype=np.float64)
    centres = corners.mean(axis=1)
    rotations = [Rotation.align_vectors(c - m, LOCAL_CORNERS_MM)[0] for c, m in zip(corners, centres)]
    return Rotation.concatenate(rotations), centres


def corners_from_params(rotvec: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """Corners (N, 4, 3) of rigid 32 mm tags with rotation vectors (N, 3) and centres (N, 3, mm)
    in the cap frame."""
    r = Rotation.from_rotvec(rotvec)
    local = np.broadcast_to(LOCAL_CORNERS_MM, (len(t_mm), 4, 3))
    return np.einsum("nij,nkj->nki", r.as_matrix(), local) + t_mm[:, None, :]


def align_model(corners_mm: np.ndarray, reference_mm: np.ndarray) -> Transform:
    """Rigid ``T_ref_built`` (translation in mm here) that best maps corners onto the reference."""
    a = np.asarray(corners_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(reference_mm, dtype=np.float64).reshape(-1, 3)
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    rotation = Rotation.align_vectors(b - mb, a - ma)[0]
    return Transform(rotation, mb - rotation.apply(ma))


def size_ratio(corners_mm: np.ndarray, reference_mm: np.ndarray) -> float:
    """Size of a cap relative to another: ratio of the RMS distances of their corners from their
    centroids (rotation and translation do not change it)."""
    a = np.asarray(corners_mm, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(reference_mm, dtype=np.float64).reshape(-1, 3)
    return float(np.sqrt(np.sum((a - a.mean(0)) ** 2) / np.sum((b - b.mean(0)) ** 2)))


def edge_shift_px(quads_px: np.ndarray, offset_px: float) -> np.ndarray:
    """Where a border-line detector puts the corners of quads whose edges it finds ``offset_px``
    outside the true ones (negative: inside).

    Args:
        quads_px: (..., 4, 2) true image corners, in order around the quad (either sense).
        offset_px: the edge offset, px, positive outward.
    Returns:
        (..., 4, 2) corners where both lines through each corner are moved by the offset along
        their outward normals (the corners of the offset quad).
    """
    q = np.asarray(quads_px, dtype=np.float64)
    edge = np.roll(q, -1, axis=-2) - q  # edge k runs from corner k to k+1
    normal = np.stack([edge[..., 1], -edge[..., 0]], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    mid = q + 0.5 * edge
    outward = np.sign(np.sum((mid - q.mean(axis=-2, keepdims=True)) * normal, axis=-1))
    normal *= outward[..., None]
    a = normal  # corner k is on edge k ...
    b = np.roll(normal, 1, axis=-2)  # ... and on edge k-1
    det = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    # Solve [a; b] d = [offset, offset] per corner.
    d = np.stack([b[..., 1] - a[..., 1], a[..., 0] - b[..., 0]], axis=-1) / det[..., None]
    return q + float(offset_px) * d


def rms_radius(centres_mm: np.ndarray) -> float:
    """RMS distance of points (N, 3) from their centroid, in their unit."""
    return float(np.sqrt(np.mean(np.sum((centres_mm - centres_mm.mean(axis=0)) ** 2, axis=1))))

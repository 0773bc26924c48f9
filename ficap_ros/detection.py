"""tag36h11 detection: OpenCV ArUco (default) or AprilTag 3 (pupil-apriltags), chosen by name.

Corners are in OpenCV's order (c0..c3 = top-left, top-right, bottom-right, bottom-left of the tag as
``cv2.aruco.generateImageMarker`` draws it, which is the official apriltag-imgs image turned by
180 deg, so c0..c3 = AprilTag's p1, p0, p3, p2) and OpenCV's pixel convention (pixel centres at
integer coordinates), in the image as given (distorted).

Corner refinement ``edge`` (the default) fits a line to each of the tag's four outer border edges
and intersects adjacent lines (``refine_corners_edge``); see docs/detection.md for how it measures
against ``cv2.cornerSubPix`` and OpenCV's AprilTag refinement.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ficap_ros.errors import ConfigError, ImageError

__all__ = [
    "TagDetection",
    "DetectorConfig",
    "TagDetector",
    "as_gray",
    "refine_corners_edge",
    "BACKENDS",
    "CORNER_REFINES",
]

BACKENDS = ("opencv", "apriltag")
CORNER_REFINES = ("edge", "subpix", "apriltag", "none")

#: AprilTag p0..p3 -> OpenCV c0..c3 (c0, c1, c2, c3 = p1, p0, p3, p2).
_APRILTAG_TO_OPENCV = (1, 0, 3, 2)
#: AprilTag puts (0, 0) at the outer corner of the top-left pixel; OpenCV at its centre.
_APRILTAG_PIXEL_OFFSET_PX = -0.5
#: tag36h11's black square is 8 cells wide (6x6 data + 1-cell black border each side).
_CELLS_PER_SIDE = 8


@dataclass(frozen=True)
class TagDetection:
    """One detected tag.

    Attributes:
        tag_id: tag36h11 id.
        corners_px: (4, 2) float64, OpenCV order and pixel convention, distorted image.
        hamming: bit errors corrected while decoding (0 when the backend does not say).
        decision_margin: backend's decoding confidence (NaN when the backend does not say).
    """

    tag_id: int
    corners_px: np.ndarray
    hamming: int = 0
    decision_margin: float = float("nan")

    def __post_init__(self) -> None:
        c = np.asarray(self.corners_px, dtype=np.float64).reshape(4, 2).copy()
        c.setflags(write=False)
        object.__setattr__(self, "corners_px", c)
        object.__setattr__(self, "tag_id", int(self.tag_id))


@dataclass(frozen=True)
class DetectorConfig:
    """Detector settings (see ``TagDetector``).

    The ArUco defaults differ from OpenCV's where the real-photo benchmark in docs/detection.md
    showed a recall gain with no false positive: bits are read from the middle 20 % of each cell
    (``perspective_remove_ignored_margin_per_cell`` 0.4 instead of 0.13, which tolerates blur and
    perspective), at 8 px per cell, with adaptive-threshold constant 5.

    Attributes:
        backend: ``opencv`` (cv2.aruco ArucoDetector, DICT_APRILTAG_36h11) or ``apriltag``
            (pupil-apriltags, the AprilTag 3 C library).
        corner_refine: ``edge`` (our edge fit of the four border lines, sub-pixel),
            ``subpix`` (cv2.cornerSubPix, the naive peer), ``apriltag`` (OpenCV's
            CORNER_REFINE_APRILTAG; with the apriltag backend: the library's own corners) or
            ``none`` (the search's corners: ArUco contour polygon, or AprilTag's own).
        adaptive_thresh_win_size_min/max/step, adaptive_thresh_constant, min_marker_perimeter_rate,
        max_marker_perimeter_rate, polygonal_approx_accuracy_rate, min_corner_distance_rate,
        min_distance_to_border_px, perspective_remove_pixel_per_cell,
        perspective_remove_ignored_margin_per_cell, max_erroneous_bits_in_border_rate,
        error_correction_rate, use_aruco3, min_marker_length_ratio_original_img,
        min_side_length_canonical_img: cv2.aruco.DetectorParameters of the same (camelCase)
            names, opencv backend only.
        quad_decimate: AprilTag's quad_decimate (apriltag backend only): 1 = full resolution.
        search_decimate: search (ArUco or AprilTag) a box-averaged image this many times
            smaller, then map the corners back and refine them on the full image (``edge``
            refine needs the search corners within ``edge_max_shift_px``); 1 = no decimation;
            0 (default) = the largest factor (up to 4) that keeps the searched image's longer
            side at least ``search_min_side_px`` (1080p: 2, 4K: 4, 720p and below: 1), where
            the cap's tags stay large enough for ArUco (a fourth of the pixels to search);
            AprilTag 3 has its own ``quad_decimate``, so 0 is 1 there.
        decimated_thresh_win_size_px: a decimated ArUco search thresholds once, with this
            window (px of the searched image), instead of over the adaptive_thresh_win_size
            range: a third of the search's cost. The tags of a frame large enough to decimate
            are 10-50 px there, which one window covers, and the pipeline reads the tags a
            search misses at the pose of those it found. 0: the full range.
        decode_rejected, decode_max_bit_errors: the search's second chance (opencv backend with
            ``edge`` refine): the quads ArUco rejected are edge-refined at full size and read
            again (``tracking.decode_tags``, at most this many of 36 bits corrected). ArUco's
            own reading at its polygon corners loses small, blurred or oblique tags.
        edge_search_px: half-length of the search along each side's normal (``edge`` refine);
            capped at 0.8 of a tag cell so the search stays on the black border and white margin.
        edge_profile_samples: samples across each side's window (odd; ``edge`` refine): their
            spacing is the window's length / (samples - 1).
        edge_samples_per_side: samples along each side (``edge`` refine).
        edge_corner_skip: fraction of each side left out next to each corner (``edge`` refine).
        edge_iterations: search-and-fit passes, each from the previous pass's corners.
        edge_max_shift_px: a refined corner further than this from the search's corner is
            rejected (the unrefined corner is kept); also capped at a quarter of the tag side.
    """

    backend: str = "opencv"
    corner_refine: str = "edge"
    # ArUco search and decoding (opencv backend).
    adaptive_thresh_win_size_min: int = 3
    adaptive_thresh_win_size_max: int = 23
    adaptive_thresh_win_size_step: int = 10
    adaptive_thresh_constant: float = 5.0
    min_marker_perimeter_rate: float = 0.03
    max_marker_perimeter_rate: float = 4.0
    polygonal_approx_accuracy_rate: float = 0.03
    min_corner_distance_rate: float = 0.05
    min_distance_to_border_px: int = 3
    perspective_remove_pixel_per_cell: int = 8
    perspective_remove_ignored_margin_per_cell: float = 0.4
    max_erroneous_bits_in_border_rate: float = 0.35
    error_correction_rate: float = 0.6
    use_aruco3: bool = False
    min_marker_length_ratio_original_img: float = 0.0
    min_side_length_canonical_img: int = 32
    # AprilTag 3 (apriltag backend).
    quad_decimate: float = 1.0
    # Both backends: search an image decimated by this factor (box average), refine at full size;
    # 0 = by image size (see search_min_side_px).
    search_decimate: int = 0
    search_min_side_px: int = 960
    decimated_thresh_win_size_px: int = 13
    # ArUco: read the quads it rejected once more at their edge-refined corners.
    decode_rejected: bool = True
    decode_max_bit_errors: int = 2
    # Edge refinement.
    edge_search_px: float = 4.0
    edge_profile_samples: int = 17
    edge_window_cells: float = 0.6
    edge_samples_per_side: int = 24
    edge_corner_skip: float = 0.15
    edge_iterations: int = 2
    edge_max_shift_px: float = 4.0

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ConfigError(f"detector backend {self.backend!r} is not one of {', '.join(BACKENDS)}")
        if self.corner_refine not in CORNER_REFINES:
            raise ConfigError(
                f"corner_refine {self.corner_refine!r} is not one of {', '.join(CORNER_REFINES)}"
            )
        if not self.quad_decimate >= 1.0:
            raise ConfigError(f"quad_decimate must be >= 1, got {self.quad_decimate}")
        if self.search_decimate not in (0, 1, 2, 3, 4):
            raise ConfigError(f"search_decimate must be 0 (auto), 1, 2, 3 or 4, got {self.search_decimate}")
        if self.decimated_thresh_win_size_px and not 3 <= self.decimated_thresh_win_size_px <= 99:
            raise ConfigError("decimated_thresh_win_size_px must be 0 or in [3, 99], "
                              f"got {self.decimated_thresh_win_size_px}")
        if self.search_min_side_px < 64:
            raise ConfigError(f"search_min_side_px must be >= 64, got {self.search_min_side_px}")
        if not 0 <= self.decode_max_bit_errors <= 3:
            raise ConfigError(f"decode_max_bit_errors must be in 0..3, got {self.decode_max_bit_errors}")
        if not 3 <= self.adaptive_thresh_win_size_min <= self.adaptive_thresh_win_size_max:
            raise ConfigError("adaptive threshold window sizes must satisfy 3 <= min <= max")
        if self.adaptive_thresh_win_size_step < 1:
            raise ConfigError("adaptive_thresh_win_size_step must be >= 1")
        if not 0.0 < self.edge_search_px <= 10.0:
            raise ConfigError(f"edge_search_px must be in (0, 10], got {self.edge_search_px}")
        if not (5 <= self.edge_profile_samples <= 65 and self.edge_profile_samples % 2 == 1):
            raise ConfigError(f"edge_profile_samples must be odd, in [5, 65], got {self.edge_profile_samples}")
        if not 4 <= self.edge_samples_per_side <= 256:
            raise ConfigError("edge_samples_per_side must be in [4, 256]")
        if not 0.0 <= self.edge_corner_skip < 0.45:
            raise ConfigError("edge_corner_skip must be in [0, 0.45)")
        if not 1 <= self.edge_iterations <= 10:
            raise ConfigError("edge_iterations must be in [1, 10]")
        if not self.edge_max_shift_px > 0.0:
            raise ConfigError("edge_max_shift_px must be > 0")


class TagDetector:
    """Finds every tag36h11 tag in a grey image (not filtered by a cap model).

    The backend's detector objects are built once here and reused for every frame.
    """

    def __init__(self, config: DetectorConfig | None = None) -> None:
        self.config = config or DetectorConfig()
        cfg = self.config
        self._search_scale = 1.0
        self._one_window = False
        if cfg.backend == "opencv":
            self._aruco = _make_aruco(cfg)
            self._apriltag = None
        else:
            import pupil_apriltags

            self._aruco = None
            self._apriltag = pupil_apriltags.Detector(
                families="tag36h11",
                nthreads=1,
                quad_decimate=float(cfg.quad_decimate),
                quad_sigma=0.0,
                refine_edges=True,
                decode_sharpening=0.25,
            )

    def detect(
        self, image: np.ndarray, roi: tuple[int, int, int, int] | None = None
    ) -> list[TagDetection]:
        """Detect every tag36h11 tag.

        Args:
            image: grey or colour image (see ``as_gray``).
            roi: optional (x, y, w, h) in pixels: search only this region (clipped to the
                image); corners are returned in full-image coordinates.

        Returns:
            All detections, duplicates included, in the backend's order.

        Raises:
            ImageError: invalid image or ROI.
        """
        full = as_gray(image)
        dec = int(self.config.search_decimate) or (
            1 if self._apriltag is not None else _auto_decimate(full.shape, self.config.search_min_side_px))
        x0, y0, x1, y1 = (0, 0, full.shape[1], full.shape[0]) if roi is None else _clip_roi(roi, full.shape)
        if dec > 1:
            # Decimation cells aligned with the full image's, so a ROI search sees the same pixels.
            x0, y0 = x0 - x0 % dec, y0 - y0 % dec
            x1, y1 = x0 + (x1 - x0) // dec * dec, y0 + (y1 - y0) // dec * dec
        gray = full if (x0, y0, x1, y1) == (0, 0, full.shape[1], full.shape[0]) else np.ascontiguousarray(
            full[y0:y1, x0:x1])
        if dec > 1:
            import cv2

            # dec x dec box average: small pixel j covers full pixels dec*j .. dec*j + dec - 1.
            gray = cv2.resize(gray, ((x1 - x0) // dec, (y1 - y0) // dec), interpolation=cv2.INTER_AREA)
        # ArUco's perimeter limits are rates of the searched image's larger side: scale them so a
        # ROI (or decimated) search keeps the full frame's limits in full-image pixels.
        self._set_search_scale(max(full.shape) / (dec * max(gray.shape)), dec > 1)
        ids, corners, hamming, margin, rejected = self._search(gray)
        # Corners in full-image coordinates, refined on the full image: a tag found in a ROI gets
        # exactly the corners a full-frame search gives it (the refinement may look past the ROI).
        offset = np.array([x0, y0], dtype=np.float64)
        if dec > 1:
            corners, rejected = corners * dec + 0.5 * (dec - 1), rejected * dec + 0.5 * (dec - 1)
        corners = corners + offset
        if len(ids) and self.config.corner_refine == "edge":
            corners = self._refine(full, corners, dec)
        if len(rejected) and self.config.corner_refine == "edge" and self.config.decode_rejected:
            ids, corners, hamming, margin = self._second_chance(
                full, rejected + offset, ids, corners, hamming, margin)
        elif len(ids) and self.config.corner_refine == "subpix" and self._apriltag is not None:
            corners = _subpix(full, corners)
        return [
            TagDetection(int(i), c, int(h), float(m))
            for i, c, h, m in zip(ids, corners, hamming, margin)
        ]

    def _set_search_scale(self, scale: float, decimated: bool = False) -> None:
        """Perimeter-rate limits for a search image ``scale`` times smaller than the full frame,
        and the threshold windows of a decimated search."""
        cfg = self.config
        one_window = decimated and cfg.decimated_thresh_win_size_px > 0
        if self._aruco is None or (scale, one_window) == (self._search_scale, self._one_window):
            return
        params = self._aruco.getDetectorParameters()
        params.minMarkerPerimeterRate = float(cfg.min_marker_perimeter_rate) * scale
        params.maxMarkerPerimeterRate = float(cfg.max_marker_perimeter_rate) * scale
        lo, hi = ((cfg.decimated_thresh_win_size_px,) * 2 if one_window else
                  (cfg.adaptive_thresh_win_size_min, cfg.adaptive_thresh_win_size_max))
        params.adaptiveThreshWinSizeMin, params.adaptiveThreshWinSizeMax = int(lo), int(hi)
        self._aruco.setDetectorParameters(params)
        self._search_scale, self._one_window = scale, one_window

    def _refine(self, full: np.ndarray, corners: np.ndarray, dec: int) -> np.ndarray:
        """Edge-refined corners; from a decimated search, a tag the refinement cannot reach (its
        polygon corners up to ``dec`` times further off) gets a wide coarse pass, then the fine one."""
        refined, ok = refine_corners_edge_ok(full, corners, self.config)
        if dec > 1 and not ok.all():
            from dataclasses import replace

            coarse = replace(self.config, edge_search_px=8.0, edge_max_shift_px=8.0, edge_iterations=1,
                             edge_samples_per_side=12, edge_profile_samples=9)
            lost = ~ok
            c, ok1 = refine_corners_edge_ok(full, corners[lost], coarse)
            c, ok2 = refine_corners_edge_ok(full, c, self.config)
            refined[lost] = np.where((ok1 & ok2)[:, None, None], c, refined[lost])
        return refined

    def _second_chance(
        self, full: np.ndarray, quads: np.ndarray, ids: np.ndarray, corners: np.ndarray,
        hamming: np.ndarray, margin: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Detections plus the rejected ``quads`` that read as tags of ids not yet found."""
        from ficap_ros.tracking import decode_tags

        # A loose read at the polygon corners first, so only plausible quads pay for the refinement.
        maybe, _, _, _ = decode_tags(full, quads, max_bit_errors=8)
        if not maybe.any():
            return ids, corners, hamming, margin
        refined = self._refine(full, quads[maybe], 2)  # polygon corners: a coarse pass may be needed
        ok, new_ids, errors, ordered = decode_tags(full, refined, self.config.decode_max_bit_errors)
        seen = {int(i) for i in ids}
        keep = []
        for k in np.flatnonzero(ok):  # one detection per id: the inner contours of a tag repeat it
            if int(new_ids[k]) not in seen:
                seen.add(int(new_ids[k]))
                keep.append(k)
        if not keep:
            return ids, corners, hamming, margin
        return (np.concatenate([ids, new_ids[keep]]), np.concatenate([corners, ordered[keep]]),
                np.concatenate([hamming, errors[keep]]), np.concatenate([margin, np.full(len(keep), np.nan)]))

    def _search(self, gray: np.ndarray) -> tuple[np.ndarray, ...]:
        """(ids (N,), corners (N,4,2) OpenCV order/convention, hamming (N,), margin (N,),
        rejected quads (R,4,2))."""
        if self._aruco is not None:
            corners, ids, rejected = self._aruco.detectMarkers(gray)
            rej = np.asarray(rejected, dtype=np.float64).reshape(-1, 4, 2)
            if ids is None or len(ids) == 0:
                return (*_empty(), rej)
            c = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 2)
            if self.config.corner_refine == "apriltag":
                # OpenCV's port of AprilTag's refinement returns AprilTag's pixel convention
                # (measured: +0.5 px in x and y on rendered tags and on the swarmathon labels).
                c += _APRILTAG_PIXEL_OFFSET_PX
            n = len(c)
            return ids.reshape(-1), c, np.zeros(n, int), np.full(n, np.nan), rej
        dets = self._apriltag.detect(gray)  # type: ignore[union-attr]
        if not dets:
            return (*_empty(), np.zeros((0, 4, 2)))
        c = np.array([d.corners for d in dets], dtype=np.float64)[:, _APRILTAG_TO_OPENCV]
        c += _APRILTAG_PIXEL_OFFSET_PX
        return (
            np.array([d.tag_id for d in dets], dtype=int),
            c,
            np.array([d.hamming for d in dets], dtype=int),
            np.array([d.decision_margin for d in dets], dtype=np.float64),
            np.zeros((0, 4, 2)),
        )


def _auto_decimate(shape: tuple[int, ...], min_side_px: int) -> int:
    """The largest search decimation (<= 4) leaving the longer side at least ``min_side_px``."""
    return max(1, min(4, max(shape[:2]) // max(int(min_side_px), 1)))


def _empty() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(0, int), np.zeros((0, 4, 2)), np.zeros(0, int), np.zeros(0)


def _clip_roi(roi: Any, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    try:
        x, y, w, h = (int(round(float(v))) for v in roi)
    except (TypeError, ValueError) as err:
        raise ImageError(f"roi must be (x, y, w, h) in pixels, got {roi!r}") from err
    x0, y0 = max(x, 0), max(y, 0)
    x1, y1 = min(x + w, shape[1]), min(y + h, shape[0])
    if x1 - x0 < 8 or y1 - y0 < 8:
        raise ImageError(f"roi {roi!r} leaves less than 8x8 px of the {shape[1]}x{shape[0]} image")
    return x0, y0, x1, y1


def _make_aruco(cfg: DetectorConfig) -> Any:
    import cv2

    p = cv2.aruco.DetectorParameters()
    p.adaptiveThreshWinSizeMin = int(cfg.adaptive_thresh_win_size_min)
    p.adaptiveThreshWinSizeMax = int(cfg.adaptive_thresh_win_size_max)
    p.adaptiveThreshWinSizeStep = int(cfg.adaptive_thresh_win_size_step)
    p.adaptiveThreshConstant = float(cfg.adaptive_thresh_constant)
    p.minMarkerPerimeterRate = float(cfg.min_marker_perimeter_rate)
    p.maxMarkerPerimeterRate = float(cfg.max_marker_perimeter_rate)
    p.polygonalApproxAccuracyRate = float(cfg.polygonal_approx_accuracy_rate)
    p.minCornerDistanceRate = float(cfg.min_corner_distance_rate)
    p.minDistanceToBorder = int(cfg.min_distance_to_border_px)
    p.perspectiveRemovePixelPerCell = int(cfg.perspective_remove_pixel_per_cell)
    p.perspectiveRemoveIgnoredMarginPerCell = float(cfg.perspective_remove_ignored_margin_per_cell)
    p.maxErroneousBitsInBorderRate = float(cfg.max_erroneous_bits_in_border_rate)
    p.errorCorrectionRate = float(cfg.error_correction_rate)
    p.useAruco3Detection = bool(cfg.use_aruco3)
    p.minMarkerLengthRatioOriginalImg = float(cfg.min_marker_length_ratio_original_img)
    p.minSideLengthCanonicalImg = int(cfg.min_side_length_canonical_img)
    p.cornerRefinementMethod = {
        "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
        "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
    }.get(cfg.corner_refine, cv2.aruco.CORNER_REFINE_NONE)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    return cv2.aruco.ArucoDetector(dictionary, p)


def _subpix(gray: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """cv2.cornerSubPix with ArUco's default window, for the apriltag backend's ``subpix``."""
    import cv2

    pts = corners.reshape(-1, 1, 2).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.1)
    cv2.cornerSubPix(gray, pts, (5, 5), (-1, -1), crit)
    return pts.reshape(-1, 4, 2).astype(np.float64)


#: Corner/side index tables: side k runs from corner k to corner k+1; corner k joins sides k-1, k.
_NEXT = np.array([1, 2, 3, 0])
_OPPOSITE = (np.array([2, 3, 0, 1]), np.array([3, 0, 1, 2]))
_PREV = np.array([3, 0, 1, 2])


def refine_corners_edge(
    gray: np.ndarray, corners_px: np.ndarray, config: DetectorConfig | None = None
) -> np.ndarray:
    """Sub-pixel corners from line fits to the tag's four outer border edges.

    For every side of every tag, points along the side (leaving out ``edge_corner_skip`` at each
    end) are searched along the side's normal for the dark-to-light step between the black border
    and the white margin. The step's position is its *area* location: with dark level d and light
    level l at the ends of the profile, the edge sits at s_out - integral((I - d) / (l - d)) ds,
    which is exact for an area-sampled step under any symmetric or asymmetric blur that fits in the
    window, and is the 50 % crossing for a symmetric one. A weighted line is fitted per side
    (weights = local contrast; samples further than 3 robust sigmas dropped and the line refitted)
    and adjacent lines are intersected. Everything is vectorised across tags, and the number of
    numpy calls per pass is kept small: with few tags their fixed cost is what the refinement costs.

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) initial corners, OpenCV order and pixel convention.
        config: search settings (``edge_*`` fields).

    Returns:
        (N, 4, 2) float64 refined corners; a tag whose fit is implausible keeps its input corners.
    """
    return refine_corners_edge_ok(gray, corners_px, config)[0]


def refine_corners_edge_ok(
    gray: np.ndarray, corners_px: np.ndarray, config: DetectorConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``refine_corners_edge`` that also says which tags were refined: (corners (N,4,2), ok (N,))."""
    cfg = config or DetectorConfig()
    c_init = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c_init) == 0:
        return c_init.copy(), np.zeros(0, dtype=bool)
    side_len = np.linalg.norm(c_init[:, _NEXT] - c_init, axis=2)  # (N, 4)
    cell_px = np.repeat(side_len.mean(axis=1) / _CELLS_PER_SIDE, 4)  # (4N,) one per side
    corners = c_init
    ok = np.ones(len(c_init), dtype=bool)
    for _ in range(cfg.edge_iterations):
        corners, it_ok = _edge_pass(gray, corners, cell_px, cfg)
        ok &= it_ok
    shift = np.linalg.norm(corners - c_init, axis=2).max(axis=1)
    max_shift = np.minimum(cfg.edge_max_shift_px, 0.25 * side_len.min(axis=1))
    ok &= np.isfinite(corners).all(axis=(1, 2)) & (shift <= max_shift)
    return np.where(ok[:, None, None], corners, c_init), ok


def _edge_pass(
    img: np.ndarray, corners: np.ndarray, cell_px: np.ndarray, cfg: DetectorConfig
) -> tuple[np.ndarray, np.ndarray]:
    """One search-and-fit pass; returns (corners (N,4,2), ok (N,)).

    Works on the 4N sides as rows r: samples (r, along the side, along the normal).
    """
    import cv2

    n, m = len(corners), cfg.edge_samples_per_side
    a = corners.reshape(-1, 2)  # (R,2) side start
    d = corners[:, _NEXT].reshape(-1, 2) - a  # (R,2) side vector
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    u = d / length[:, None]
    nrm = np.column_stack([u[:, 1], -u[:, 0]])
    # Point the normal outward (away from the tag centre), whatever the corner order's handedness.
    centre = np.repeat(corners.mean(axis=1), 4, axis=0)
    nrm *= np.where(np.einsum("ij,ij->i", a + 0.5 * d - centre, nrm) < 0, -1.0, 1.0)[:, None]

    # The search must stay between the data bits (one cell inside) and whatever lies beyond the
    # white margin (one cell outside). The cell that matters is the one across this side: on a tag
    # seen obliquely it is much narrower than the mean side / 8, so measure the tag's width along
    # this side's normal (distance of the two opposite corners from the side's line).
    opp = corners[:, _OPPOSITE[0]].reshape(-1, 2) + corners[:, _OPPOSITE[1]].reshape(-1, 2) - 2 * a
    width = np.abs(np.einsum("ij,ij->i", opp, nrm)) / 2.0
    cell_side = np.minimum(width / _CELLS_PER_SIDE, cell_px)
    half = np.clip(np.minimum(cfg.edge_search_px, cfg.edge_window_cells * cell_side), 0.75, None)  # (R,)
    # Every side's window [-half, half] holds the same number of samples, so their spacing
    # follows the window (0.1 px on a small tag's side, 0.5 px on a large one's): the same
    # relative resolution everywhere and one array shape for all sides.
    k = (cfg.edge_profile_samples - 1) // 2
    step = half / k  # (R,)
    j = np.arange(-k, k + 1, dtype=np.float32)  # (S,) sample index along the normal

    t = np.linspace(cfg.edge_corner_skip, 1.0 - cfg.edge_corner_skip, m)  # (M,)
    base = (a[:, None, :] + d[:, None, :] * t[None, :, None]).astype(np.float32)  # (R,M,2)
    dn = (nrm * step[:, None]).astype(np.float32)  # (R,2) one sample step along the normal
    map_x = base[..., 0, None] + dn[:, None, 0:1] * j  # (R,M,S)
    map_y = base[..., 1, None] + dn[:, None, 1:2] * j
    s_len = len(j)
    # cv2.remap: bilinear in C++ (positions to 1/32 px, values to 1 grey level; both average out
    # over a profile and a side: measured 0.001 px on the median corner error).
    vals = cv2.remap(img, map_x.reshape(-1, s_len), map_y.reshape(-1, s_len), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).reshape(map_x.shape).astype(np.float32)

    # Dark level: the window's inner end (black border); light level: its outer end (white
    # margin); the edge: the window's outer end minus the trapezoid integral of the normalised
    # profile over the window.
    dark = 0.5 * (vals[..., 0] + vals[..., 1])  # (R,M)
    contrast = 0.5 * (vals[..., -1] + vals[..., -2]) - dark
    frac = (vals - dark[..., None]) / np.where(contrast > 0, contrast, 1.0)[..., None]
    np.clip(frac, 0.0, 1.0, out=frac)
    trap = np.ones(s_len, dtype=np.float32)
    trap[[0, -1]] = 0.5
    s_edge = half[:, None] - (frac @ trap).astype(np.float64) * step[:, None]  # (R,M)
    contrast = contrast.astype(np.float64)

    # Weights: contrast, with weak or inverted profiles dropped (occlusion, glare, the wrong edge),
    # samples whose edge sits at the window's end, and samples off the image.
    med_c = _masked_median(contrast, contrast > 0)
    w = np.where((contrast > 0.3 * med_c[:, None]) & (contrast > 8.0)
                 & (np.abs(s_edge) < half[:, None] - np.maximum(step, 0.25)[:, None]), contrast, 0.0)
    h_img, w_img = img.shape
    reach = float(half.max()) + 1.0
    if not (corners.min() >= reach and np.all(corners.max(axis=(0, 1)) <= (w_img - 1 - reach, h_img - 1 - reach))):
        inside = (map_x >= 0) & (map_y >= 0) & (map_x <= w_img - 1) & (map_y <= h_img - 1)
        w = w * np.all(inside, axis=2)

    # Line per side in the side's own coordinates: edge offset s = alpha + beta * (along - mean).
    along = t[None, :] * length[:, None]  # (R,M) px along the side
    alpha, beta, keep_n = _fit_side_lines(along, s_edge, w)
    # Back to the image: a point and a unit normal per side, then rho = normal . point.
    along0 = (w * along).sum(axis=1) / np.maximum(w.sum(axis=1), 1e-12)
    point = a + u * along0[:, None] + nrm * alpha[:, None]
    normal = nrm - u * beta[:, None]
    normal /= np.hypot(normal[:, 0], normal[:, 1])[:, None]
    rho = np.einsum("ij,ij->i", normal, point)
    lines = np.column_stack([normal, rho]).reshape(n, 4, 3)
    # Corner k is where side k-1 meets side k.
    l_prev = lines[:, _PREV]
    a11, a12, r1 = l_prev[..., 0], l_prev[..., 1], l_prev[..., 2]
    a21, a22, r2 = lines[..., 0], lines[..., 1], lines[..., 2]
    det = a11 * a22 - a12 * a21
    good_det = np.abs(det) > 0.2  # sides at least ~12 deg apart
    det = np.where(good_det, det, 1.0)
    new = np.stack([(r1 * a22 - a12 * r2) / det, (a11 * r2 - a21 * r1) / det], axis=-1)
    ok = np.all(good_det, axis=1) & np.all(keep_n.reshape(n, 4) >= max(3, m // 4), axis=1)
    return np.where(ok[:, None, None], new, corners), ok


def _fit_side_lines(x: np.ndarray, s: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted straight-line fits s = alpha + beta (x - x_mean) per row, one round of 3-sigma
    (MAD) outlier rejection; returns (alpha, beta, samples kept) per row.

    A fit in the side's own frame (x along the side, s across it) equals the total-least-squares
    line to first order in the slope, which the previous pass has already made small.
    """
    for round_ in range(2):
        sw = np.maximum(w.sum(axis=1), 1e-12)
        xm = (w * x).sum(axis=1) / sw
        dx = x - xm[:, None]
        alpha = (w * s).sum(axis=1) / sw
        beta = (w * dx * s).sum(axis=1) / np.maximum((w * dx * dx).sum(axis=1), 1e-12)
        if round_ == 1:
            break
        r = np.abs(s - alpha[:, None] - beta[:, None] * dx)
        mad = 1.4826 * _masked_median(r, w > 0)
        w = np.where(r <= np.maximum(3.0 * mad, 0.05)[:, None], w, 0.0)
    return alpha, beta, (w > 0).sum(axis=1)


def _masked_median(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Median per row (R, M) of the entries where ``mask`` (0 where none); nanmedian is slow."""
    srt = np.sort(np.where(mask, x, np.inf), axis=1)
    cnt = mask.sum(axis=1)
    rows = np.arange(len(x))
    lo = srt[rows, np.maximum((cnt - 1) // 2, 0)]
    hi = srt[rows, np.maximum(cnt // 2, 0)]
    return np.where(cnt > 0, 0.5 * (lo + hi), 0.0)


def as_gray(image: np.ndarray) -> np.ndarray:
    """Validate an image and return it as a contiguous uint8 grey array (no copy when it is one).

    Accepts (H, W) or (H, W, 1) grey, (H, W, 3) BGR and (H, W, 4) BGRA, uint8 or uint16
    (scaled to 8 bits).

    Raises:
        ImageError: not an array, empty, of an unsupported dtype or shape.
    """
    if not isinstance(image, np.ndarray):
        raise ImageError(f"image must be a numpy array, got {type(image).__name__}")
    if image.size == 0:
        raise ImageError(f"image is empty (shape {image.shape})")
    if image.dtype not in (np.uint8, np.uint16):
        raise ImageError(f"image dtype must be uint8 or uint16, got {image.dtype}")
    import cv2  # local: keep module import light for type-only users

    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        gray = image
    elif image.ndim == 3 and image.shape[2] == 3:
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif image.ndim == 3 and image.shape[2] == 4:
        gray = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    else:
        raise ImageError(f"image shape {image.shape} is neither grey (H, W) nor colour (H, W, 3|4)")
    if gray.shape[0] < 8 or gray.shape[1] < 8:
        raise ImageError(f"image {gray.shape[1]}x{gray.shape[0]} is too small to hold a tag")
    if gray.dtype == np.uint16:
        gray = (gray >> 8).astype(np.uint8)
    return np.ascontiguousarray(gray)

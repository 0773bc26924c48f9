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

from collections.abc import Callable, Container
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import numpy as np

from ficap_ros.errors import ConfigError, ImageError
from ficap_ros.geometry.tag36h11 import (
    CELL_CENTRES,
    CELL_CENTRES_H,
    TAG_AREA,
    TAG_CELLS,
    apply_homographies,
    decode_tags,
    read_tag_cells,
    stacked_tag_cells,
    tag_cells,
    tag_homographies,
)
from ficap_ros.vision.photometric import fit_tags

__all__ = [
    "TagDetection",
    "DetectorConfig",
    "TagDetector",
    "opencv_without_ipp",
    "as_gray",
    "refine_corners_edge",
    "refine_corners_edge_ok",
    "unbias_corners_edge",
    "fit_tag_edges",
    "fit_tags_photometric",
    "refine_tag_corners",
    "shift_tag_edges",
    "partly_hidden",
    "BACKENDS",
    "CORNER_REFINES",
]

BACKENDS = ("opencv", "apriltag")
CORNER_REFINES = ("edge", "subpix", "apriltag", "none")

#: AprilTag p0..p3 -> OpenCV c0..c3 (c0, c1, c2, c3 = p1, p0, p3, p2).
_APRILTAG_TO_OPENCV = (1, 0, 3, 2)
#: AprilTag puts (0, 0) at the outer corner of the top-left pixel; OpenCV at its centre.
_APRILTAG_PIXEL_OFFSET_PX = -0.5


@dataclass(frozen=True)
class TagDetection:
    """One detected tag.

    Attributes:
        tag_id: tag36h11 id.
        corners_px: (4, 2) float64, OpenCV order and pixel convention, distorted image.
        hamming: bit errors corrected while decoding (0 when the backend does not say).
        decision_margin: backend's decoding confidence (NaN when the backend does not say).
        edge_shift_px: how far the camera's tone curve moved this tag's black/white edges toward
            the black, px, as its cell-edge fit measured and removed (``fit_tag_edges``); NaN
            when the tag was not fitted (too small or oblique: ``refine_tag_corners`` corrects it
            with what the fitted tags measured; or another corner refinement).
    """

    tag_id: int
    corners_px: np.ndarray
    hamming: int = 0
    decision_margin: float = float("nan")
    edge_shift_px: float = float("nan")

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
            AprilTag 3 has its own ``quad_decimate``, and ArUco's own corner refinements
            (``subpix``, ``apriltag``) would refine on the decimated image, so 0 is 1 for those.
        decimated_thresh_win_size_px: a decimated ArUco search thresholds once, with this
            window (px of the searched image), instead of over the adaptive_thresh_win_size
            range: a third of the search's cost. The tags of a frame large enough to decimate
            are 10-50 px there, which one window covers, and the pipeline reads the tags a
            search misses at the pose of those it found. 0: the full range.
        decode_rejected, decode_max_bit_errors: the search's second chance (opencv backend with
            ``edge`` refine): the quads ArUco rejected are edge-refined at full size and read
            again (``decode_tags``, at most this many of 36 bits corrected). ArUco's
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
        edge_unbias: remove the tone-curve bias of the edge-fitted corners from each tag's own
            black border (``unbias_corners_edge``); ``edge`` refine only.
        edge_fit: then fit each tag's homography to all its cell edges at once, with the
            tone-curve shift as a free parameter (``fit_tag_edges``); ``edge`` refine only.
        edge_fit_iterations: sample-and-solve rounds of that fit.
        hidden_check: tell the pose which tags something partly covers (``partly_hidden``: hair,
            the head, a headrest, the image border over their white quiet zone), which it drops
            at a lower residual (``PoseConfig.hidden_ratio``); ``edge`` refine only. The tags are
            still detected and reported.
        edge_photometric: then fit each fitted tag once more, as a whole, to its pixels near the
            cell boundaries: the printed pattern blurred in linear light (blur fitted per tag)
            through an sRGB tone curve (``fit_tags_photometric``, ``ficap_ros.vision.photometric``); more
            accurate on noisy frames (issue 10), at ~0.9 ms of CPU a tag, ~20 ms a tracked 1080p
            frame (docs/detection.md "A tag-level photometric fit", docs/benchmarks.md); ``edge`` refine
            with ``edge_fit`` only (else ``ConfigError``). Off by default.
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
    edge_unbias: bool = True
    edge_fit: bool = True
    edge_fit_iterations: int = 2
    # Pose input: name the partly hidden tags (pipeline.FrameProcessor).
    hidden_check: bool = True
    edge_photometric: bool = False

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
        if not 1 <= self.edge_fit_iterations <= 5:
            raise ConfigError(f"edge_fit_iterations must be in [1, 5], got {self.edge_fit_iterations}")
        if self.edge_photometric and not (self.corner_refine == "edge" and self.edge_fit):
            # It refines the cell-edge fit's corners: without that fit it would do nothing.
            raise ConfigError("the photometric corner fit (edge_photometric, --photometric, "
                              "detector.photometric) needs corner_refine 'edge' with edge_fit, "
                              f"got corner_refine {self.corner_refine!r}, edge_fit {self.edge_fit}")


def opencv_without_ipp() -> None:
    """Turn OpenCV's Intel IPP dispatch off for the calling thread (``cv2.ipp.setUseIPP(False)``).

    OpenCV's IPP path runs ``cpuid`` on every call it dispatches, and in a virtual machine every
    ``cpuid`` traps to the hypervisor: measured on the benchmark VM (Firecracker, AMD EPYC),
    ``cv2.countNonZero`` of an 8x8 block takes 5.1 us with IPP and 0.6 us without. ArUco reads each
    candidate's cells with such calls, so IPP made its search 3.6x slower there (9.0 -> 2.5 ms per
    1080p frame decimated by 2), for bit-identical detections and poses (docs/detection.md, "Speed").
    The switch is OpenCV's and per thread, so ``TagDetector`` sets it in the thread that detects.
    """
    import cv2

    if cv2.ipp.useIPP():
        cv2.ipp.setUseIPP(False)


class TagDetector:
    """Finds every tag36h11 tag in a grey image (not filtered by a cap model).

    The backend's detector objects are built once here and reused for every frame. Detecting
    turns OpenCV's IPP off in the calling thread (``opencv_without_ipp``): same results, faster in a
    virtual machine.
    """

    def __init__(self, config: DetectorConfig | None = None) -> None:
        self.config = config or DetectorConfig()
        cfg = self.config
        opencv_without_ipp()
        self._search_scale = 1.0
        self._one_window = False
        if cfg.backend == "opencv":
            self._aruco = _make_aruco(cfg)
            self._apriltag = None
        else:
            self._aruco = None
            self._apriltag = _apriltag_detector_class()(
                families="tag36h11",
                nthreads=1,
                quad_decimate=float(cfg.quad_decimate),
                quad_sigma=0.0,
                refine_edges=True,
                decode_sharpening=0.25,
            )

    def detect(
        self, image: np.ndarray, roi: tuple[int, int, int, int] | None = None, *,
        wanted_ids: Container[int] | None = None, enough_tags: int = 0,
    ) -> list[TagDetection]:
        """Detect every tag36h11 tag.

        Args:
            image: grey or colour image (see ``as_gray``).
            roi: optional (x, y, w, h) in pixels: search only this region (clipped to the
                image); corners are returned in full-image coordinates.
            wanted_ids, enough_tags: on a decimated search, skip the second reading of the
                rejected quads (``decode_rejected``) when the search itself found at least
                ``enough_tags`` distinct ids of ``wanted_ids``: for a caller that reads the rest
                of its tags at the pose of those (the tracker's search completion). A
                full-resolution search always reads them again: there the second reading finds
                small tags the completion's prediction leaves out (blender_dev 540p: 1-2 frames
                per set with a tag fewer). None / 0: never skip.

        Returns:
            All detections, duplicates included, in the backend's order.

        Raises:
            ImageError: invalid image or ROI.
        """
        full = as_gray(image)
        opencv_without_ipp()  # per thread: the node and the workers detect in their own threads
        # Auto decimation only where the corners are refined on the full image afterwards (``edge``):
        # ArUco's own refinements (``subpix``, ``apriltag``) would run on the decimated image.
        dec = int(self.config.search_decimate) or (
            1 if self._apriltag is not None or self.config.corner_refine != "edge"
            else _auto_decimate(full.shape, self.config.search_min_side_px))
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
        searched = corners  # the search's own corners: a second start for the cell-edge fit
        if len(ids) and self.config.corner_refine == "edge":
            corners = self._refine(full, corners, dec)
        enough = (dec > 1 and wanted_ids is not None and enough_tags > 0
                  and len({int(i) for i in ids if int(i) in wanted_ids}) >= enough_tags)
        if len(rejected) and self.config.corner_refine == "edge" and self.config.decode_rejected and not enough:
            ids, corners, hamming, margin = self._second_chance(
                full, rejected + offset, ids, corners, hamming, margin)
        shift = np.full(len(ids), np.nan)
        if len(ids) and self.config.corner_refine == "edge":
            # Free of the tone-curve bias, every tag found (searched or read again). A tag whose
            # fit failed or reads its own cells wrong (a corner a cell off: at low light a search
            # polygon or a line side latches onto a neighbouring edge) is fitted again from the
            # search's corners and from each corner rebuilt from the other three.
            starts = np.full((len(ids), 4, 2), np.nan)
            starts[:len(searched)] = searched
            corners, shift = refine_tag_corners(full, corners, ids, self.config, retry_px=starts)
        elif len(ids) and self.config.corner_refine == "subpix" and self._apriltag is not None:
            corners = _subpix(full, corners)
        return [
            TagDetection(int(i), c, int(h), float(m), float(e))
            for i, c, h, m, e in zip(ids, corners, hamming, margin, shift)
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
            lost = ~ok
            refined[lost] = _coarse_then_fine(full, corners[lost], self.config)
        return refined

    def _second_chance(
        self, full: np.ndarray, quads: np.ndarray, ids: np.ndarray, corners: np.ndarray,
        hamming: np.ndarray, margin: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Detections plus the rejected ``quads`` that read as tags of ids not yet found."""
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


@lru_cache(maxsize=None)
def _apriltag_detector_class() -> type:
    """pupil-apriltags' Detector, freed in the right order.

    pupil-apriltags 1.0.4's ``Detector.__del__`` destroys the tag families first and then the
    detector, whose destroy still releases each family's decode table: a use after free that
    corrupts the heap and, now and then, kills the process long after (seen as "malloc():
    mismatching next->prev_size" in a test worker). Here the detector goes first.
    """
    import pupil_apriltags

    class Detector(pupil_apriltags.Detector):  # type: ignore[misc]
        def __del__(self) -> None:
            ptr = getattr(self, "tag_detector_ptr", None)
            if ptr is None:
                return
            self.libc.apriltag_detector_destroy.restype = None
            self.libc.apriltag_detector_destroy(ptr)
            self.tag_detector_ptr = None
            for family, tf in self.tag_families.items():
                destroy = getattr(self.libc, f"{family}_destroy")
                destroy.restype = None
                destroy(tf)

    return Detector


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


def _norm(x: np.ndarray, keepdims: bool = False) -> np.ndarray:
    """``np.linalg.norm(x, axis=-1)`` of a float array, bit for bit (its own arithmetic for a
    vector norm along an axis), without its ~3 us of checks: the corner stages take ~20 a frame."""
    return np.sqrt(np.add.reduce(x * x, axis=-1, keepdims=keepdims))


def refine_corners_edge_ok(
    gray: np.ndarray, corners_px: np.ndarray, config: DetectorConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``refine_corners_edge`` that also says which tags were refined: (corners (N,4,2), ok (N,))."""
    cfg = config or DetectorConfig()
    c_init = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c_init) == 0:
        return c_init.copy(), np.zeros(0, dtype=bool)
    side_len = _norm(c_init[:, _NEXT] - c_init)  # (N, 4)
    cell_px = np.repeat(side_len.mean(axis=1) / TAG_CELLS, 4)  # (4N,) one per side
    corners = c_init
    ok = np.ones(len(c_init), dtype=bool)
    for _ in range(cfg.edge_iterations):
        corners, it_ok = _edge_pass(gray, corners, cell_px, cfg)
        ok &= it_ok
    shift = _norm(corners - c_init).max(axis=1)
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
    cell_side = np.minimum(width / TAG_CELLS, cell_px)
    half = np.maximum(np.minimum(cfg.edge_search_px, cfg.edge_window_cells * cell_side), 0.75)  # (R,)
    # Every side's window [-half, half] holds the same number of samples, so their spacing
    # follows the window (0.1 px on a small tag's side, 0.5 px on a large one's): the same
    # relative resolution everywhere and one array shape for all sides.
    k = (cfg.edge_profile_samples - 1) // 2
    step = half / k  # (R,)
    j, t, trap = _edge_pass_grid(k, cfg.edge_corner_skip, m)
    dn = (nrm * step[:, None]).astype(np.float32)  # (R,2) one sample step along the normal
    # Sample grid (R,M,S): the side's points (float64, then float32) plus the steps along the normal.
    map_x = (a[:, 0:1] + d[:, 0:1] * t).astype(np.float32)[..., None] + dn[:, None, 0:1] * j
    map_y = (a[:, 1:2] + d[:, 1:2] * t).astype(np.float32)[..., None] + dn[:, None, 1:2] * j
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
    # In place: the samples are not needed again, and each (R, M, S) temporary is ~0.1 MB.
    frac = np.subtract(vals, dark[..., None], out=vals)
    frac /= np.where(contrast > 0, contrast, 1.0)[..., None]
    np.clip(frac, 0.0, 1.0, out=frac)
    s_edge = half[:, None] - (frac @ trap).astype(np.float64) * step[:, None]  # (R,M)
    contrast = contrast.astype(np.float64)

    # Weights: contrast, with weak or inverted profiles dropped (occlusion, glare, the wrong edge),
    # samples whose edge sits at the window's end, and samples off the image.
    med_c = _masked_median(contrast, contrast > 0)
    w = np.where((contrast > 0.3 * med_c[:, None]) & (contrast > 8.0)
                 & (np.abs(s_edge) < half[:, None] - np.maximum(step, 0.25)[:, None]), contrast, 0.0)
    h_img, w_img = img.shape
    reach = float(half.max()) + 1.0
    if not (corners.min() >= reach and (corners.max(axis=(0, 1)) <= (w_img - 1 - reach, h_img - 1 - reach)).all()):
        inside = (map_x >= 0) & (map_y >= 0) & (map_x <= w_img - 1) & (map_y <= h_img - 1)
        w = w * inside.all(axis=2)

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
    ok = good_det.all(axis=1) & (keep_n.reshape(n, 4) >= max(3, m // 4)).all(axis=1)
    return np.where(ok[:, None, None], new, corners), ok


@lru_cache(maxsize=8)
def _sample_index(k: int) -> np.ndarray:
    """(2k + 1,) float32 -k..k: a profile's sample index along its normal (built once per size)."""
    j = np.arange(-k, k + 1, dtype=np.float32)
    j.setflags(write=False)
    return j


@lru_cache(maxsize=8)
def _edge_pass_grid(k: int, corner_skip: float, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``_edge_pass``'s constants, built once per setting: the sample index along the normal (S,),
    the positions along a side (M,) and the trapezoid rule's weights (S,)."""
    j = _sample_index(k)
    t = np.linspace(corner_skip, 1.0 - corner_skip, m)
    trap = np.ones(len(j), dtype=np.float32)
    trap[[0, -1]] = 0.5
    for a in (t, trap):
        a.setflags(write=False)
    return j, t, trap


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


# ------------------------------------------------------------------------------------------------
# Tone-curve bias: the black border's two edges
# ------------------------------------------------------------------------------------------------
#: Where the inner edge of the border is sampled across a white data cell (fractions of the cell
#: along the side): away from the cell's ends, where the neighbouring black cells blur in.
_INNER_FRACTIONS = (0.35, 0.5, 0.65)


@lru_cache(maxsize=None)
def _inner_edge_samples(tag_id: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample points on the inner edge of the black border, where a white data cell borders it.

    Returns (side (S,) int, uv (S, 2) in tag cell units, c0 at (0, 0), x right, y down). Side k
    runs from corner k to corner k + 1: 0 top (inner edge y = 1), 1 right (x = 7), 2 bottom
    (y = 7), 3 left (x = 1).
    """
    cells = tag_cells(tag_id)
    sides, uv = [], []
    for j in range(1, TAG_CELLS - 1):
        for f in _INNER_FRACTIONS:
            t = j + f
            for side, white, point in (
                (0, not cells[1, j], (t, 1.0)),
                (1, not cells[j, TAG_CELLS - 2], (TAG_CELLS - 1.0, t)),
                (2, not cells[TAG_CELLS - 2, j], (t, TAG_CELLS - 1.0)),
                (3, not cells[j, 1], (1.0, t)),
            ):
                if white:
                    sides.append(side)
                    uv.append(point)
    out = np.array(sides, dtype=np.int64), np.array(uv, dtype=np.float64).reshape(-1, 2)
    for a in out:
        a.setflags(write=False)
    return out


@lru_cache(maxsize=256)
def _stacked(
    table: Callable[[int], tuple[np.ndarray, ...]], ids: tuple[int, ...],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """The per-tag sample ``table`` of each id stacked tag after tag: (counts (N,), tag of each
    sample (T,), first sample of each tag (N,), the tables' columns concatenated). Cached: a
    tracked cap shows the same ids frame after frame."""
    tables = [table(i) for i in ids]
    counts = np.array([len(t[0]) for t in tables])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    columns = [np.concatenate([t[k] for t in tables]) for k in range(len(tables[0]))]
    out = counts, np.repeat(np.arange(len(tables)), counts), starts, columns
    for a in (*out[:3], *columns):
        a.setflags(write=False)
    return out


def _side_lines(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals (N, 4, 2) and offsets rho (N, 4) of the lines through corners k, k+1
    (a point p is on side k's line when normal . p = rho; larger = further out)."""
    d = corners[:, _NEXT] - corners
    u = d / np.maximum(_norm(d, keepdims=True), 1e-12)
    nrm = np.stack([u[..., 1], -u[..., 0]], axis=-1)
    centre = corners.mean(axis=1, keepdims=True)
    flip = np.einsum("nkd,nkd->nk", corners + 0.5 * d - centre, nrm) < 0
    nrm = np.where(flip[..., None], -nrm, nrm)
    return nrm, np.einsum("nkd,nkd->nk", nrm, corners)


def _intersect_sides(nrm: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """Corners (N, 4, 2) where side k-1's line meets side k's."""
    n1, r1 = nrm[:, _PREV], rho[:, _PREV]
    det = n1[..., 0] * nrm[..., 1] - n1[..., 1] * nrm[..., 0]
    det = np.where(np.abs(det) > 1e-9, det, 1e-9)
    x = (r1 * nrm[..., 1] - n1[..., 1] * rho) / det
    y = (n1[..., 0] * rho - r1 * nrm[..., 0]) / det
    return np.stack([x, y], axis=-1)


def _margin_cycle() -> np.ndarray:
    """Indices into ``CELL_CENTRES`` of the 36 quiet-zone samples in order around the tag (c0, c1, c2,
    c3), so that neighbours along the margin are neighbours in the array (cyclically)."""
    n = TAG_CELLS + 2
    top = [c for c in range(n)]
    right = [r * n + n - 1 for r in range(1, n)]
    bottom = [(n - 1) * n + c for c in range(n - 2, -1, -1)]
    left = [r * n for r in range(n - 2, 0, -1)]
    return np.array(top + right + bottom + left)


_MARGIN_CYCLE = _margin_cycle()
#: A stretch of ``_HIDDEN_MARGIN_RUN`` neighbouring quiet-zone samples (about half a side) whose
#: mean reads at least ``_HIDDEN_MARGIN_DARKNESS`` of the way from the tag's white to its black is
#: covered: 0.5 is where ``read_tag_cells`` calls a cell black. Chosen on ``ficap synth`` frames:
#: over three samples, low light's noise and cast shadows crossed it on 8 % of fully visible tags
#: (540p and 1080p), over five on none, while a head over a tag's corner still crosses it.
_HIDDEN_MARGIN_DARKNESS = 0.5
_HIDDEN_MARGIN_RUN = 5


@lru_cache(maxsize=None)
def _black_samples(tag_id: int) -> np.ndarray:
    """(100,) which of ``CELL_CENTRES``'s samples of this tag are black (its cells; the margin is white)."""
    black = np.zeros(len(CELL_CENTRES), dtype=bool)
    black[TAG_AREA] = tag_cells(tag_id).ravel()
    black.setflags(write=False)
    return black


def _masked_lower_median(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per row of ``x`` (K, N), the lower median of the entries where ``mask``: one sort, not
    ``np.nanmedian`` (a tenth of the time on a frame's tags)."""
    count = mask.sum(axis=1)
    ordered = np.sort(np.where(mask, x, np.inf), axis=1)
    return ordered[np.arange(len(x)), np.maximum(count - 1, 0) // 2]


def partly_hidden(gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(K,) which tags something covers in part, read from their white quiet zone.

    Every tag is framed by a one-cell white quiet zone (the face's margin). Where hair, the head
    or a headrest passes in front of a tag, or the tag runs off the image, a stretch of that
    margin reads dark (a sample off the image reads 0). Such a tag's corners are often off as a
    whole, not only the hidden one: its line and cell-edge fits may take the occluder's edge for
    the tag's and bend every side they share with it (blender_dev 1080p: partly hidden tags'
    corners median 0.3 px off, fully visible ones within 50 deg 0.1 px). Read like
    ``read_tag_cells``: each of the 36 margin samples (cell centres half a cell outside the black
    border) against the tag's own levels (the median of its white cells and margin, of its black
    cells); a tag is partly hidden when ``_HIDDEN_MARGIN_RUN`` neighbouring margin samples read on
    average at least ``_HIDDEN_MARGIN_DARKNESS`` of the way from white to black. Uneven light and
    highlights move the levels smoothly or brighten; a cast shadow or a dark background beyond
    the margin counts only where it darkens half a side's margin by half the contrast.

    Args:
        gray: (H, W) uint8 image.
        corners_px: (K, 4, 2) corners, OpenCV order and pixel convention.
        ids: (K,) their ids (the code says which cells are white).

    Returns:
        (K,) bool; True also for corners that give no usable homography.
    """
    import cv2

    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    k = len(c)
    usable = _usable_quads(c)
    ids = np.asarray(ids).reshape(-1)
    if not usable.all():  # each tag is read alone: one bad quadrilateral flags itself only
        out = np.ones(k, dtype=bool)
        if usable.any():
            out[usable] = partly_hidden(gray, c[usable], ids[usable])
        return out
    if k == 0:
        return np.zeros(0, dtype=bool)
    hom = tag_homographies(c)
    p = hom @ CELL_CENTRES_H.T  # (K, 3, 100); a matmul, not einsum: a tenth of the time
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (p[:, 0] / p[:, 2]).astype(np.float32)
        y = (p[:, 1] / p[:, 2]).astype(np.float32)
    finite = np.all(np.isfinite(x) & np.isfinite(y), axis=1)
    x = np.where(np.isfinite(x), x, -1.0).astype(np.float32)
    y = np.where(np.isfinite(y), y, -1.0).astype(np.float32)
    vals = cv2.remap(gray, x, y, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(np.float64)  # (K, 100)
    black = _black_samples_of(tuple(int(i) for i in ids))
    white_level = _masked_lower_median(vals, ~black)
    black_level = _masked_lower_median(vals, black)
    contrast = np.maximum(white_level - black_level, 1.0)
    dark = (white_level[:, None] - vals[:, _MARGIN_CYCLE]) / contrast[:, None]  # 0 white, 1 black
    # The run's mean around the cycle: np.roll(dark, j) for j = -half..half, summed in that order,
    # as windows of the cycle padded by half a run at each end (the same sums, 5 calls fewer).
    half = _HIDDEN_MARGIN_RUN // 2
    size = dark.shape[1]
    ring = np.concatenate([dark[:, size - half:], dark, dark[:, :half]], axis=1)
    stretch = sum(ring[:, 2 * half - i:2 * half - i + size] for i in range(2 * half + 1)) / (2 * half + 1)
    return ~finite | (stretch.max(axis=1) >= _HIDDEN_MARGIN_DARKNESS)


@lru_cache(maxsize=256)
def _black_samples_of(ids: tuple[int, ...]) -> np.ndarray:
    """(K, 100) ``_black_samples`` of each id, stacked; cached (a tracked cap shows the same ids
    frame after frame)."""
    out = np.stack([_black_samples(i) for i in ids])
    out.setflags(write=False)
    return out


#: Cells of its own code (of 64) a fitted tag may read wrong at its fitted corners (noise at
#: low light); more, and a corner is off by about a cell.
_MAX_FIT_CELL_ERRORS = 1


def _cell_errors(gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """(N,) how many of each tag's 64 cells, read at ``corners_px`` (``read_tag_cells``), differ
    from its id's code (64 where the corners give no usable homography)."""
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c) == 0:
        return np.zeros(0, dtype=int)
    try:
        hom = tag_homographies(c)
    except np.linalg.LinAlgError:
        return np.full(len(c), 64)
    read_black, _, _, finite = read_tag_cells(gray, hom)
    expected = stacked_tag_cells(tuple(int(i) for i in ids)).reshape(len(c), -1)
    return np.where(finite, (read_black != expected).sum(axis=1), 64)


def _fittable(corners_px: np.ndarray, lines: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """(N,) which tags' cells span ``_MIN_TAG_CELL_PX`` both ways (those ``refine_tag_corners``
    unbiases and fits with their own cells). ``lines``: ``_side_lines(corners_px)`` when the
    caller has them."""
    corners = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(corners) == 0:
        return np.zeros(0, dtype=bool)
    nrm, rho = _side_lines(corners) if lines is None else lines
    # Width of the tag across each side (opposite corners from the side's line), in cells.
    across = rho[:, :, None] - np.einsum("nkd,njd->nkj", nrm, corners)
    return across.max(axis=2).min(axis=1) / TAG_CELLS >= _MIN_TAG_CELL_PX


def refine_tag_corners(
    gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray, config: DetectorConfig | None = None,
    retry_px: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The tag-aware stage after the line fit: ``unbias_corners_edge`` then ``fit_tag_edges``
    (each as ``config`` enables it) on every tag whose cells span ``_MIN_TAG_CELL_PX`` both ways.
    A smaller (or oblique) tag keeps its line-fit corners, each side moved out by the bias the
    line estimator has with that side's window, measured on the outer edges of the tags fitted in
    the same call (``_line_bias``); without a fitted tag they keep their line corners.
    A fitted tag's corners depend on its own pixels only (a region search gives the full frame's
    corners); a small tag's also on the fitted tags of the call.
    With ``retry_px``, a fittable tag the fit refused, or whose 64 cells read at its fitted
    corners disagree with its code in more than ``_MAX_FIT_CELL_ERRORS`` (a corner about a cell
    off, which the fit, moving at most a third of a cell, cannot undo), is fitted again from other
    starts (``_refit``); where none reads right it keeps its corners (and its fit's shift).

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) corners from ``refine_corners_edge``.
        ids: (N,) their ids.
        config: detector settings.
        retry_px: (N, 4, 2) other starting corners (the search's; rows of NaN = none), or None:
            no second look (the tracker, whose tags are verified by their cells afterwards).

    Returns:
        (corners (N, 4, 2), edge shift px (N,): ``fit_tag_edges``'s delta, NaN where not fitted:
        a small tag's correction was measured on other tags, not on it).
    """
    cfg = config or DetectorConfig()
    corners = np.array(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    delta = np.full(len(corners), np.nan)
    if len(corners) == 0 or cfg.corner_refine != "edge" or not (cfg.edge_unbias or cfg.edge_fit):
        return corners, delta
    ids = np.asarray(ids).reshape(-1)
    nrm, rho = _side_lines(corners)
    good = _fittable(corners, (nrm, rho))
    corners_in = corners.copy()
    if good.any():
        c = corners[good]
        if cfg.edge_unbias:
            # The fittable tags' lines are rows of these (each row's arithmetic is its own).
            c = unbias_corners_edge(gray, c, ids[good], cfg, _lines=(nrm[good], rho[good]))
        if cfg.edge_fit:
            c, delta[good] = fit_tag_edges(gray, c, ids[good], cfg, cfg.edge_fit_iterations)
        corners[good] = c
    if cfg.edge_fit and retry_px is not None:
        # Fittable tags the fit refused (it would move a corner beyond a third of a cell: the
        # start was off), fitted again from other starts: the given corners, and each corner
        # replaced by the parallelogram of the other three (one corner led astray is how a
        # search or a line pass fails: a side pulled onto a neighbouring edge in a dark corner).
        # A fit that converged from a corner a cell off (it moves at most a third of a cell) reads
        # the tag's own cells wrong next to that corner: those are fitted again too.
        done = np.flatnonzero(np.isfinite(delta))
        wrong = np.zeros(len(corners), dtype=bool)
        wrong[done] = _cell_errors(gray, corners[done], ids[done]) > _MAX_FIT_CELL_ERRORS
        again = np.flatnonzero(good & (~np.isfinite(delta) | wrong))
        if len(again):
            c, d = _refit(gray, corners[again], retry_px[again], ids[again], cfg)
            # Where no other start reads right either, a fitted tag keeps its fit (its cells may
            # just read badly: small cells under glare read 2-3 wrong at the right corners).
            corners[again], delta[again] = c, np.where(np.isfinite(d), d, delta[again])
    if cfg.edge_fit and cfg.edge_photometric and np.isfinite(delta).any():
        done = np.flatnonzero(np.isfinite(delta))
        corners[done] = fit_tags_photometric(gray, corners[done], ids[done])[0]
    fitted = np.isfinite(delta)
    # Line-fit corners only (too small to unbias or fit, or both failed): no tone-curve correction yet.
    line_only = ~fitted & np.all(corners == corners_in, axis=(1, 2))
    if cfg.edge_fit and fitted.any() and line_only.any():
        # Tags too small (or oblique) to measure their own shift keep line-fit corners, which the
        # tone curve pulled inward by what the line estimator measures *with their windows*: a
        # small tag's window is a fraction of a px, and a window that cuts the blurred step's
        # tails sees less of the shift than the fit's delta on larger tags. Measure exactly that
        # on the frame's fitted tags, whose outer edges are now known: the line estimator with
        # each small side's window on those edges; its mean offset is that side's bias.
        # The bias changes slowly with the window: measured on a 1/8 px grid of the windows
        # needed, on at most _BIAS_TAGS of the fitted tags.
        halves = np.round(_line_windows(corners[line_only], cfg) * 8.0) / 8.0
        grid, where = np.unique(halves, return_inverse=True)
        ref = np.flatnonzero(fitted)
        ref = ref[np.linspace(0, len(ref) - 1, min(len(ref), _BIAS_TAGS)).round().astype(int)]
        bias = _line_bias(gray, corners[ref], grid, cfg)[where.reshape(halves.shape)]
        ok = np.isfinite(bias).all(axis=1)
        todo = np.flatnonzero(line_only)[ok]
        if len(todo):
            corners[todo] = _intersect_sides(nrm[todo], rho[todo] + bias[ok])
    return corners, delta


def _coarse_then_fine(gray: np.ndarray, corners: np.ndarray, cfg: DetectorConfig) -> np.ndarray:
    """Corners up to ~8 px off (a decimated search's polygon, a corner guessed from the other
    three): a wide coarse line pass, then the fine one; a tag either pass fails keeps its input."""
    coarse = replace(cfg, edge_search_px=8.0, edge_max_shift_px=8.0, edge_iterations=1,
                     edge_samples_per_side=12, edge_profile_samples=9)
    c, ok1 = refine_corners_edge_ok(gray, corners, coarse)
    c, ok2 = refine_corners_edge_ok(gray, c, cfg)
    return np.where((ok1 & ok2)[:, None, None], c, corners)


def _refit(
    gray: np.ndarray, corners: np.ndarray, other: np.ndarray, ids: np.ndarray, cfg: DetectorConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Tags whose cell-edge fit failed from ``corners`` (M, 4, 2), fitted from other starts: ``other``
    (M, 4, 2, rows of NaN = none) and ``corners`` and ``other`` with each corner k replaced by the
    parallelogram c[k-1] + c[k+1] - c[k+2]; each start line-refined, unbiased and fitted. A tag
    takes the start whose fit succeeds and moves least (its corners and delta, NaN where none did;
    such tags keep ``corners``)."""
    m = len(corners)
    bases = [corners, np.asarray(other, dtype=np.float64).reshape(m, 4, 2)]
    starts = [bases[1]]
    for base in bases:
        for k in range(4):
            c = base.copy()
            c[:, k] = base[:, _PREV[k]] + base[:, _NEXT[k]] - base[:, _OPPOSITE[0][k]]
            starts.append(c)
    cand = np.concatenate(starts)  # (S * M, 4, 2), start after start
    tag = np.tile(np.arange(m), len(starts))
    usable = np.isfinite(cand).all(axis=(1, 2))
    best_c, best_d = corners.copy(), np.full(m, np.nan)
    if not usable.any():
        return best_c, best_d
    cand, tag = cand[usable], tag[usable]
    lines, ok = refine_corners_edge_ok(gray, cand, cfg)
    if not ok.all():
        lines[~ok] = _coarse_then_fine(gray, cand[~ok], cfg)
    c = unbias_corners_edge(gray, lines, ids[tag], cfg) if cfg.edge_unbias else lines
    fitted, d = fit_tag_edges(gray, c, ids[tag], cfg, cfg.edge_fit_iterations + 1)
    right = np.isfinite(d)
    right[right] = _cell_errors(gray, fitted[right], ids[tag][right]) <= _MAX_FIT_CELL_ERRORS
    moved = np.where(right, np.linalg.norm(fitted - c, axis=2).max(axis=1), np.inf)
    for j in range(m):
        mine = np.flatnonzero((tag == j) & np.isfinite(moved))
        if len(mine):
            k = mine[np.argmin(moved[mine])]
            best_c[j], best_d[j] = fitted[k], d[k]
    return best_c, best_d


def _line_windows(corners: np.ndarray, cfg: DetectorConfig) -> np.ndarray:
    """(N, 4) half-length, px, of ``_edge_pass``'s window across each side of these corners."""
    side_len = np.linalg.norm(corners[:, _NEXT] - corners, axis=2)
    cell_px = side_len.mean(axis=1, keepdims=True) / TAG_CELLS
    nrm, rho = _side_lines(corners)
    width = (rho[:, :, None] - np.einsum("nkd,njd->nkj", nrm, corners)).max(axis=2)
    cell_side = np.minimum(width / TAG_CELLS, cell_px)
    return np.clip(np.minimum(cfg.edge_search_px, cfg.edge_window_cells * cell_side), 0.75, None)


#: Points per side of a fitted tag where ``_line_bias`` measures its outer edge, and the most
#: fitted tags it uses (spread over the call's order).
_BIAS_POINTS = np.linspace(0.2, 0.8, 7)
_BIAS_TAGS = 8


def _line_bias(gray: np.ndarray, fitted_px: np.ndarray, halves: np.ndarray, cfg: DetectorConfig) -> np.ndarray:
    """How far inside a true black/white edge ``_edge_pass``'s estimator puts it, px, with each
    window half-length of ``halves`` (any shape): the median over the outer border edges of the
    tags with fitted (true) corners ``fitted_px`` (NaN where too few edges were clean)."""
    nrm, _ = _side_lines(fitted_px)
    a, d = fitted_px, fitted_px[:, _NEXT] - fitted_px
    pts = (a[:, :, None, :] + d[:, :, None, :] * _BIAS_POINTS[None, None, :, None]).reshape(-1, 2)
    out_n = np.repeat(nrm.reshape(-1, 2), len(_BIAS_POINTS), axis=0)
    h = np.asarray(halves, dtype=np.float64).ravel()
    p_n, h_n = len(pts), len(h)
    s, contrast = _step_offset(gray, np.tile(pts, (h_n, 1)), np.tile(out_n, (h_n, 1)), np.repeat(h, p_n),
                               cfg.edge_profile_samples)
    s, contrast = s.reshape(h_n, p_n), contrast.reshape(h_n, p_n)
    # As the line pass weighs its samples: weak or inverted profiles and edges at the window's end out.
    med_c = _masked_median(contrast, contrast > 0)
    step = h / ((cfg.edge_profile_samples - 1) // 2)
    use = ((contrast > 0.3 * med_c[:, None]) & (contrast > 8.0)
           & (np.abs(s) < (h - np.maximum(step, 0.25))[:, None]))
    bias = -_masked_median(s, use)
    return np.where(use.sum(axis=1) >= 8, bias, np.nan).reshape(np.shape(halves))


def shift_tag_edges(corners_px: np.ndarray, shift_px: float) -> np.ndarray:
    """Line-fit corners (N, 4, 2) with every side moved out by ``shift_px``: the frame's tone-curve
    shift applied to tags too small or oblique to measure their own (the shift is the camera's
    blur and tone curve, so it is shared by the tags of a frame)."""
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    if len(c) == 0 or not np.isfinite(shift_px):
        return c.copy()
    nrm, rho = _side_lines(c)
    return _intersect_sides(nrm, rho + float(shift_px))


def unbias_corners_edge(
    gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray, config: DetectorConfig | None = None,
    _lines: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Remove the tone-curve bias from edge-fitted corners, using each tag's own black border.

    A lens blurs *linear* light; the camera's tone curve (sRGB, gamma, an S-curve) and clipping
    then move the grey-level midpoint of every black/white edge toward the black, by an amount
    delta that depends on the curve, the blur and the contrast, none of which we know. The fitted
    outer edge of the border therefore sits delta *inside* the tag. The border's inner edge, where
    a white data cell meets it, has black on its outer side, so the same estimator puts it delta
    *outside* its true place: the measured border is 2 delta thinner than one cell. The tag's
    geometry (the homography of its corners) says how wide one cell is at each point, so

        delta = (cell width - measured border width) / 2

    per side, from the samples across the white cells of the first data ring (known from the id),
    with no model of the camera's response. Each side's line is then moved out by its delta and
    the corners re-intersected; the cell width is re-read from the corrected corners (it
    converges in two rounds). A side with few samples leans on its tag's mean; a tag with none
    is left as it is. Samples where the two edges are too close to resolve (cells under 2 px
    across) are not used.

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) corners from ``refine_corners_edge`` (OpenCV order and convention).
        ids: (N,) the tags' ids (their data cells say where the border's inner edge is).
        config: window settings (``edge_search_px``, ``edge_window_cells``, ``edge_profile_samples``).
        _lines: ``_side_lines(corners_px)`` when the caller has them (``refine_tag_corners``).

    Returns:
        (N, 4, 2) corrected corners (a tag keeps its input corners when no estimate is possible
        or the correction is implausibly large).
    """
    cfg = config or DetectorConfig()
    c_in = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    n = len(c_in)
    if n == 0:
        return c_in.copy()
    counts, tag_of, starts, (side, uv) = _stacked(_inner_edge_samples, tuple(int(i) for i in ids))
    # uv on the outer edge straight across from each inner sample (one cell out).
    uv_out = uv + _SIDE_OUT[side]
    nrm, rho = _side_lines(c_in) if _lines is None else _lines
    nk = nrm[tag_of, side]  # (T, 2)

    # Measure both edges of the border straight across each white data cell, with the same
    # window: the inner edge around where the fitted corners put it (then again around what was
    # found, so the window sits on the edge), the outer edge around the fitted line.
    try:
        hom = tag_homographies(c_in)
    except np.linalg.LinAlgError:
        return c_in.copy()
    hom_t = hom[tag_of]
    p_in, p_out = apply_homographies(hom_t, uv), apply_homographies(hom_t, uv_out)
    width0 = np.einsum("td,td->t", nk, p_out - p_in)  # px, one cell across
    half = np.maximum(np.minimum(cfg.edge_search_px, cfg.edge_window_cells * width0), 0.75)
    samples = cfg.edge_profile_samples
    # The inner edge has its light side inward: offsets along -nk. Its first look and the outer
    # edge's in one sampling call.
    t = len(uv)
    first, first_c = _step_offset(gray, np.concatenate([p_in, p_out]), np.concatenate([-nk, nk]),
                                  np.concatenate([half, half]), samples)
    s1, o1, c_outer = np.clip(first[:t], -half, half), first[t:], first_c[t:]
    s2, c_inner = _step_offset(gray, p_in - nk * s1[:, None], -nk, half, samples)
    inner = np.einsum("td,td->t", nk, p_in) - s1 - s2
    outer = np.einsum("td,td->t", nk, p_out) + o1
    step = half / ((samples - 1) // 2)
    # A white cell as white as the quiet zone across the border: where its neighbours (or the
    # pixel footprint) darken it, its edge is not the outer edge's mirror image.
    valid = (np.isfinite(inner) & np.isfinite(outer) & (width0 >= _MIN_CELL_PX) & (np.abs(s2) < half - step)
             & (np.abs(o1) < half - step) & (c_outer > 8.0) & (c_inner >= _MIN_CONTRAST_RATIO * c_outer))
    # The midline between the two measured edges is unbiased (both moved toward the black by the
    # same amount); the true outer edge is half a cell beyond it.
    midline = 0.5 * (inner + outer)

    group = tag_of * 4 + side
    corners = c_in
    delta = np.zeros((n, 4))
    keep = None
    for round_ in range(2):
        if round_ == 0:  # the first round's corners are the input's: its width is width0
            width = width0
        else:
            hom_t = tag_homographies(corners)[tag_of]
            p_in_c, p_out_c = apply_homographies(hom_t, uv), apply_homographies(hom_t, uv_out)
            width = np.einsum("td,td->t", nk, p_out_c - p_in_c)  # one cell across, corrected geometry
        d = midline + 0.5 * width - rho[tag_of, side]  # (T,) how far the fitted line is inside, px
        if keep is None:  # the outliers: from the first round (the second moves d by ~1 %)
            keep = _inlier_samples(d, valid, starts, counts)
        delta = _pooled_delta(d, keep, group, n)
        corners = _intersect_sides(nrm, rho + delta)
    # A correction beyond a third of a cell (or 2 px) is no tone curve: keep those tags' corners.
    cell = _norm(c_in[:, _NEXT] - c_in).min(axis=1) / TAG_CELLS
    sane = (np.abs(delta).max(axis=1) <= np.minimum(cell / 3.0, 2.0)) & np.isfinite(corners).all(axis=(1, 2))
    return np.where(sane[:, None, None], corners, c_in)


#: Fewest px a cell must span across an edge for the edge to be measured next to its neighbours:
#: a window of half a cell each way must hold the blurred step and stay off the next edge.
_MIN_CELL_PX = 2.0
#: ... and a tag is fitted on its own when its cells span this much across both axes.
_MIN_TAG_CELL_PX = 2.0
#: A sample's contrast must be at least this share of a clean reference (the quiet zone across
#: the border; a tag's 90th percentile): darker means its window saw a neighbouring cell.
_MIN_CONTRAST_RATIO = 0.7
#: Tag-unit step from a side's inner edge to its outer edge (sides 0..3: top, right, bottom, left).
_SIDE_OUT = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
#: Samples' worth of prior weight of a tag's mean delta on each side (three samples = one cell).
_SIDE_PRIOR_SAMPLES = 3.0


def _inlier_samples(d: np.ndarray, valid: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The valid samples within 3 MAD (at least 0.1 px) of their tag's median."""
    tag_of = np.repeat(np.arange(len(counts)), counts)
    tag_med = _group_median(d, valid, starts, counts)
    tag_mad = 1.4826 * _group_median(np.abs(d - tag_med[tag_of]), valid, starts, counts)
    return valid & np.isfinite(d) & (np.abs(d - tag_med[tag_of]) <= np.maximum(3.0 * tag_mad[tag_of], 0.1))


def _pooled_delta(d: np.ndarray, keep: np.ndarray, group: np.ndarray, n: int) -> np.ndarray:
    """Per-side delta (N, 4): each side's mean over its kept samples, shrunk toward its tag's
    mean (0 for a tag without samples)."""
    dv = np.where(keep, d, 0.0)
    side_sum = np.bincount(group, weights=dv, minlength=4 * n).reshape(n, 4)
    side_cnt = np.bincount(group, weights=keep.astype(np.float64), minlength=4 * n).reshape(n, 4)
    tag_cnt = side_cnt.sum(axis=1)
    has = tag_cnt > 0
    tag_mean = np.where(has, side_sum.sum(axis=1) / np.maximum(tag_cnt, 1e-12), 0.0)
    prior = _SIDE_PRIOR_SAMPLES
    return (side_sum + prior * tag_mean[:, None]) / (side_cnt + prior)


@lru_cache(maxsize=None)
def _cell_edge_samples(tag_id: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample points on every black/white cell boundary of a tag and its white quiet zone.

    Returns (uv (S, 2) in tag cell units, c0 at (0, 0), x right, y down; nu (S, 2) the boundary's
    unit normal in tag units, pointing from the black cell to the white one). Each boundary is one
    cell long and sampled at ``_EDGE_FRACTIONS`` of its length (away from the cell corners, where
    the blur mixes in the cells diagonally across).
    """
    cells = np.ones((TAG_CELLS + 2, TAG_CELLS + 2), dtype=bool)  # True = white, with the quiet zone
    cells[1:-1, 1:-1] = ~tag_cells(tag_id)
    uv, nu = [], []
    size = TAG_CELLS + 2
    for r in range(size):
        for c in range(size):
            for dr, dc in ((0, 1), (1, 0)):
                r2, c2 = r + dr, c + dc
                if r2 >= size or c2 >= size or cells[r, c] == cells[r2, c2]:
                    continue
                # Boundary between cell (r, c) and its right (dc) or lower (dr) neighbour, in tag
                # units where the tag's cell (0, 0) spans [0, 1]: grid index i -> i - 1.
                sign = 1.0 if cells[r2, c2] else -1.0  # +: the neighbour is the white one
                for f in _EDGE_FRACTIONS:
                    if dc:
                        uv.append((c2 - 1.0, r - 1.0 + f))
                        nu.append((sign, 0.0))
                    else:
                        uv.append((c - 1.0 + f, r2 - 1.0))
                        nu.append((0.0, sign))
    out = np.array(uv, dtype=np.float64), np.array(nu, dtype=np.float64)
    for a in out:
        a.setflags(write=False)
    return out


_EDGE_FRACTIONS = (0.3, 0.7)
#: Samples across each boundary's window (half a cell each way).
_FIT_PROFILE_SAMPLES = 11


def _step_offset(
    img: np.ndarray, centre: np.ndarray, to_light: np.ndarray, half: np.ndarray, samples: int
) -> tuple[np.ndarray, np.ndarray]:
    """Area location of a dark-to-light step along ``to_light`` (unit, (P, 2)) in the window
    [-half, half] around ``centre``: (offset px along ``to_light`` (P,), contrast (P,)).

    The estimator of ``_edge_pass``: levels from the window's two end samples, the edge where the
    trapezoid integral of the normalised profile puts it (exact for any blur of a step in linear
    light; under a tone curve, shifted toward the dark side by the same amount for every edge of
    the same blur and contrast).
    """
    import cv2

    k = (samples - 1) // 2
    j = _sample_index(k)
    step = half / k
    d = (to_light * step[:, None]).astype(np.float32)
    c = centre.astype(np.float32)
    vals = cv2.remap(img, c[:, 0:1] + d[:, 0:1] * j, c[:, 1:2] + d[:, 1:2] * j, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
    dark = 0.5 * (vals[:, 0] + vals[:, 1])
    contrast = 0.5 * (vals[:, -1] + vals[:, -2]) - dark
    frac = np.subtract(vals, dark[:, None], out=vals)  # in place, as _edge_pass
    frac /= np.where(contrast > 0, contrast, 1.0)[:, None]
    np.clip(frac, 0.0, 1.0, out=frac)
    area = frac.sum(axis=1) - 0.5 * (frac[:, 0] + frac[:, -1])  # trapezoid rule
    return half - area.astype(np.float64) * step, contrast.astype(np.float64)


def fit_tag_edges(
    gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray, config: DetectorConfig | None = None,
    iterations: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Corners from every cell edge of each tag at once, free of the tone-curve bias.

    The tag is a known pattern: every boundary between a black and a white cell (its border's
    two edges, the data cells', the quiet zone's) lies where the tag's homography H maps it. A
    camera's tone curve and clipping move each measured boundary toward its black side by an
    amount delta (one blur, one contrast, one curve per tag), which we do not know; what the
    estimator sees of it also depends on its window (half a cell across the boundary, narrower
    along an oblique tag's foreshortened axis), so there is one delta per boundary direction (tag
    x, tag y). Boundaries of both polarities are spread over the tag in both directions, so H (8
    parameters) and the deltas are separable: each sample's measured offset s along the image
    normal (toward the white cell) is modelled as n . J_H dh - delta_dir and one weighted
    least-squares step per iteration updates H and the deltas together (re-sampling the image each
    time); samples beyond 3.5 robust sigmas are dropped. About three times as many edge pixels as the four outer lines see, and no line is
    extrapolated to a corner.

    Args:
        gray: (H, W) uint8 image.
        corners_px: (N, 4, 2) starting corners (``refine_corners_edge``; within ~0.3 cell).
        ids: (N,) tag ids (their cells say where the boundaries are).
        config: ``edge_search_px`` and ``edge_profile_samples``.
        iterations: sample-and-solve rounds.

    Returns:
        (corners (N, 4, 2), delta_px (N,)): corrected corners (a tag keeps its input corners when
        its cells are too small to resolve or the fit is implausible) and each tag's fitted edge
        shift toward black, px, the mean of its two directions' (NaN where not fitted).
    """
    cfg = config or DetectorConfig()
    c_in = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    n = len(c_in)
    delta = np.full(n, np.nan)
    if n == 0:
        return c_in.copy(), delta
    counts, tag_of, starts, (uv, nu) = _stacked(_cell_edge_samples, tuple(int(i) for i in ids))
    u, v = uv[:, 0], uv[:, 1]
    try:
        h = tag_homographies(c_in).reshape(n, 9)[:, :8].copy()
    except np.linalg.LinAlgError:
        return c_in.copy(), delta
    samples = _FIT_PROFILE_SAMPLES
    across_x = (np.abs(nu[:, 0]) > 0.5).astype(np.float64)  # boundary normal along tag x
    keep = np.ones(len(uv), dtype=bool)
    fitted = np.zeros(n, dtype=bool)
    for it in range(iterations):
        ht = h[tag_of]
        den = ht[:, 6] * u + ht[:, 7] * v + 1.0
        px = (ht[:, 0] * u + ht[:, 1] * v + ht[:, 2]) / den
        py = (ht[:, 3] * u + ht[:, 4] * v + ht[:, 5]) / den
        # Image normal of the boundary: J^-T nu, J = d(px, py)/d(u, v).
        j11 = (ht[:, 0] - ht[:, 6] * px) / den
        j12 = (ht[:, 1] - ht[:, 7] * px) / den
        j21 = (ht[:, 3] - ht[:, 6] * py) / den
        j22 = (ht[:, 4] - ht[:, 7] * py) / den
        det = j11 * j22 - j12 * j21
        gx = (j22 * nu[:, 0] - j21 * nu[:, 1]) / det
        gy = (-j12 * nu[:, 0] + j11 * nu[:, 1]) / det
        gnorm = np.hypot(gx, gy)
        nx, ny = gx / gnorm, gy / gnorm
        cell_px = 1.0 / gnorm  # one cell across this boundary, px
        half = np.minimum(cfg.edge_search_px, 0.5 * cell_px)
        s, contrast = _step_offset(gray, np.column_stack([px, py]), np.column_stack([nx, ny]),
                                   half, samples)
        step = half / ((samples - 1) // 2)
        # Full contrast only: a boundary whose window ends are darkened by a neighbouring black
        # cell (or lightened by a white one) is not a clean step.
        top_c = _group_quantile(contrast, keep & np.isfinite(contrast), starts, counts, 0.9)
        ok = (keep & (cell_px >= _MIN_CELL_PX) & np.isfinite(s) & (np.abs(s) < half - step)
              & (contrast > 8.0) & (contrast >= _MIN_CONTRAST_RATIO * top_c[tag_of]))
        # Rows of the linearised model s = n . J_h dh - delta; columns scaled to unit size.
        jac = np.zeros((len(uv), 10))
        jac[:, 0], jac[:, 1], jac[:, 2] = nx * u / den, nx * v / den, nx / den
        jac[:, 3], jac[:, 4], jac[:, 5] = ny * u / den, ny * v / den, ny / den
        jac[:, 6] = -(nx * px + ny * py) * u / den
        jac[:, 7] = -(nx * px + ny * py) * v / den
        # One shift per boundary direction (tag x, tag y): what the estimator sees of the shift
        # depends on its window, half a cell across the boundary, and on an oblique tag the cells
        # are narrower along one axis (a window that cuts the blurred step's tails sees less).
        jac[:, 8] = -across_x
        jac[:, 9] = -(1.0 - across_x)
        for _round in range(2):
            # Noise-optimal weights: a sample's position noise goes as 1 / its contrast.
            w = np.where(ok, (contrast / np.maximum(top_c[tag_of], 1.0)) ** 2, 0.0)
            # Only the first round's residuals (the outliers) and the last round's solution are
            # used: neither the last residuals nor the first solution's checks are computed.
            sol, solved, r = _solve_grouped(jac, s, w, starts, 24, residuals=_round == 0)
            if _round == 0:
                assert r is not None
                sig = 1.4826 * _group_median(np.abs(r), ok, starts, counts)
                ok &= np.abs(r) <= np.maximum(3.5 * sig[tag_of], 0.05)
                continue
            # Both edge directions must be seen, or the fit is free along one of them.
            used = w > 0
            vertical = np.add.reduceat(used & (np.abs(nu[:, 0]) > 0.5), starts)
            solved &= (vertical >= 12) & (np.add.reduceat(used, starts) - vertical >= 12)
        h = h + np.where(solved[:, None], sol[:, :8], 0.0)
        delta = np.where(solved, sol[:, 8:].mean(axis=1), np.nan)  # the two directions' mean
        fitted = solved
        if it == iterations - 2:
            keep = ok  # the last round samples where the previous one trusted the image
    full = np.concatenate([h, np.ones((n, 1))], axis=1).reshape(n, 3, 3)
    src = np.array([[0, 0, 1], [TAG_CELLS, 0, 1], [TAG_CELLS, TAG_CELLS, 1], [0, TAG_CELLS, 1]], float)
    p = np.einsum("nij,kj->nki", full, src)
    corners = p[..., :2] / p[..., 2:3]
    cell = _norm(c_in[:, _NEXT] - c_in).min(axis=1) / TAG_CELLS
    moved = _norm(corners - c_in).max(axis=1)
    good = fitted & np.isfinite(corners).all(axis=(1, 2)) & (moved <= np.minimum(0.35 * cell, 2.5))
    return np.where(good[:, None, None], corners, c_in), np.where(good, delta, np.nan)


def fit_tags_photometric(
    gray: np.ndarray, corners_px: np.ndarray, ids: np.ndarray, **kwargs: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """The tag-level photometric fit (``ficap_ros.vision.photometric.fit_tags``, keyword arguments as
    there) of tags given by their corners and ids: (corners (N, 4, 2), fitted (N,) bool; a tag not
    fitted keeps its corners). ``gray`` may be any image ``as_gray`` takes (else ImageError)."""
    gray = as_gray(gray)  # no copy for the pipeline's uint8 grey frames
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    ids = np.asarray(ids).reshape(-1)
    usable = _usable_quads(c)
    if not usable.all():  # a tag's fit is its own: one bad quadrilateral stays unfitted alone
        out, fitted = c.copy(), np.zeros(len(c), dtype=bool)
        if usable.any():
            out[usable], fitted[usable] = fit_tags_photometric(gray, c[usable], ids[usable], **kwargs)
        return out, fitted
    if len(c) == 0:
        return c.copy(), np.zeros(0, dtype=bool)
    cells = stacked_tag_cells(tuple(int(i) for i in ids))
    return fit_tags(gray, c, tag_homographies(c), cells, **kwargs)


def _usable_quads(corners_px: np.ndarray) -> np.ndarray:
    """(K,) which quadrilaterals (K, 4, 2) give a homography (``tag_homographies`` raises for the
    batch if one does not): finite corners, c1, c2 and c3 not on a line."""
    c = corners_px
    d1, d2 = c[:, 1] - c[:, 2], c[:, 3] - c[:, 2]
    with np.errstate(invalid="ignore", over="ignore"):
        den = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    return np.isfinite(c).all(axis=(1, 2)) & np.isfinite(den) & (den != 0.0)


def _group_median(x: np.ndarray, mask: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Median of ``x`` over the masked entries of each contiguous group (0 where none)."""
    return _group_quantile(x, mask, starts, counts, 0.5)


@lru_cache(maxsize=64)
def _layout(counts_key: bytes) -> tuple[np.ndarray, np.ndarray, int]:
    """(group of each entry, its place in the group, largest group) for groups of the sizes in
    ``counts_key`` (an int64 array's bytes), laid out one after the other; cached (a tracked cap's
    tags give the same groups frame after frame)."""
    counts = np.frombuffer(counts_key, dtype=np.int64)
    group = np.repeat(np.arange(len(counts)), counts)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    pos = np.arange(int(counts.sum())) - starts[group]
    for a in (group, pos):
        a.setflags(write=False)
    return group, pos, int(counts.max()) if len(counts) else 0


def _group_quantile(
    x: np.ndarray, mask: np.ndarray, starts: np.ndarray, counts: np.ndarray, q: float
) -> np.ndarray:
    """Quantile ``q`` (nearest rank) of ``x`` over the masked entries of each contiguous group
    (0 where none)."""
    n = len(counts)
    group, pos, lmax = _layout(np.ascontiguousarray(counts, dtype=np.int64).tobytes())
    pad = np.full((n, lmax), np.inf)
    pad[group, pos] = np.where(mask, x, np.inf)
    if q == 0.5:
        return _masked_median(pad, np.isfinite(pad))
    srt = np.sort(pad, axis=1)
    cnt = np.isfinite(pad).sum(axis=1)
    rank = np.clip(np.round(q * (cnt - 1)).astype(int), 0, None)
    return np.where(cnt > 0, srt[np.arange(n), rank], 0.0)


def _solve_grouped(
    jac: np.ndarray, rhs: np.ndarray, w: np.ndarray, starts: np.ndarray, min_rows: int,
    residuals: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Weighted least squares per contiguous group of rows: (solutions (n, P), solved (n,),
    residuals rhs - jac @ solution (T,), None unless ``residuals``)."""
    n, p = len(starts), jac.shape[1]
    ends = np.append(starts[1:], len(rhs))
    jw = jac * w[:, None]
    ata = np.empty((n, p, p))
    atb = np.empty((n, p))
    # Python ints: slicing with numpy integers costs ~1 us more per group and loop.
    bounds = list(enumerate(zip(starts.tolist(), ends.tolist())))
    for g, (a, b) in bounds:  # a few dozen small products: cheaper than one (T, P, P) outer product
        jw_t = jw[a:b].T
        ata[g] = jw_t @ jac[a:b]
        atb[g] = jw_t @ rhs[a:b]
    rows = np.add.reduceat((w > 0).astype(np.float64), starts)
    # Column scaling: the parameters differ in size by orders of magnitude.
    d = np.sqrt(np.maximum(np.einsum("nii->ni", ata), 1e-30))
    a_s = ata / d[:, :, None] / d[:, None, :]
    # A parameter no weighted row touches (an exactly zero diagonal: e.g. no boundary of one
    # direction left) makes the system exactly singular; such a group is unsolved, as the one by
    # one fallback below would find, without a batch that raises and is redone group by group.
    solved = (rows >= min_rows) & np.all(np.einsum("nii->ni", ata) > 0.0, axis=1)
    sol = np.zeros((n, p))
    if solved.any():
        try:
            sol[solved] = np.linalg.solve(a_s[solved], (atb / d)[solved][..., None])[..., 0] / d[solved]
        except np.linalg.LinAlgError:  # a degenerate tag: solve one by one, dropping it
            for g in np.flatnonzero(solved):
                try:
                    sol[g] = np.linalg.solve(a_s[g], atb[g] / d[g]) / d[g]
                except np.linalg.LinAlgError:
                    solved[g] = False
    solved &= np.isfinite(sol).all(axis=1)
    if not residuals:
        return sol, solved, None
    resid = np.empty_like(rhs)
    for g, (a, b) in bounds:
        resid[a:b] = rhs[a:b] - jac[a:b] @ sol[g]
    return sol, solved, resid


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

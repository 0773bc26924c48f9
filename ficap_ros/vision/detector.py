"""Finding tag36h11 tags in an image: OpenCV ArUco (default) or AprilTag 3 (pupil-apriltags), chosen by
name, and the detector's settings and result.

Corners are in OpenCV's order (c0..c3 = top-left, top-right, bottom-right, bottom-left of the tag as
``cv2.aruco.generateImageMarker`` draws it, which is the official apriltag-imgs image turned by
180 deg, so c0..c3 = AprilTag's p1, p0, p3, p2) and OpenCV's pixel convention (pixel centres at
integer coordinates), in the image as given (distorted).

With corner refinement ``edge`` (the default) the search's corners are refined by line fits to the
tag's four outer border edges (``ficap_ros.vision.edges``) and then freed of the camera's
tone-curve bias (``ficap_ros.vision.corners``); docs/detection.md compares it with
``cv2.cornerSubPix`` and OpenCV's AprilTag refinement.
"""

from __future__ import annotations

import math
from collections.abc import Container
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from ficap_ros.errors import ConfigError, ImageError
from ficap_ros.geometry.tag36h11 import decode_tags

__all__ = [
    "TagDetection",
    "DetectorConfig",
    "TagDetector",
    "opencv_without_ipp",
    "as_gray",
    "BACKENDS",
    "CORNER_REFINES",
]

#: Search backends (``DetectorConfig.backend``).
BACKENDS = ("opencv", "apriltag")
#: Corner refinements (``DetectorConfig.corner_refine``).
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
    """Detector settings (see ``TagDetector``): the search, the corner refinement and the corner stage.

    Attributes:
        backend: ``opencv`` (cv2.aruco ArucoDetector, DICT_APRILTAG_36h11) or ``apriltag``
            (pupil-apriltags, the AprilTag 3 C library).
        corner_refine: ``edge`` (line fits to the four border edges, then the tone-curve corner
            stage), ``subpix`` (cv2.cornerSubPix, the naive peer), ``apriltag`` (OpenCV's
            CORNER_REFINE_APRILTAG; with the apriltag backend: the library's own corners) or
            ``none`` (the search's corners: ArUco contour polygon, or AprilTag's own).
        adaptive_thresh_win_size_min/max/step, adaptive_thresh_constant, min_marker_perimeter_rate,
        max_marker_perimeter_rate, polygonal_approx_accuracy_rate, min_corner_distance_rate,
        min_distance_to_border_px, perspective_remove_pixel_per_cell,
        perspective_remove_ignored_margin_per_cell, max_erroneous_bits_in_border_rate,
        error_correction_rate, use_aruco3, min_marker_length_ratio_original_img,
        min_side_length_canonical_img: cv2.aruco.DetectorParameters of the same (camelCase)
            names, opencv backend only. Three defaults differ from OpenCV's so that small,
            blurred and oblique tags still read: each bit is read from the middle 20 % of its
            cell (``perspective_remove_ignored_margin_per_cell`` 0.4, not 0.13: a blurred or
            foreshortened cell's edges belong to its neighbours), at 8 px per cell, with
            adaptive-threshold constant 5 (docs/detection.md).
        quad_decimate: AprilTag's quad_decimate (apriltag backend only): 1 = full resolution.
        search_decimate: search (ArUco or AprilTag) a box-averaged image this many times
            smaller, then map the corners back and refine them on the full image (``edge``
            refine needs the search corners within ``edge_max_shift_px``, or a wide coarse pass
            first); 1 = no decimation; 0 (default) = the largest factor (up to 4) that keeps the
            searched image's longer side at least ``search_min_side_px``, so that the cap's tags
            stay large enough for ArUco there. 0 means 1 with the apriltag backend (AprilTag 3
            decimates its own quads: ``quad_decimate``) and with ArUco's own corner refinements
            (``subpix``, ``apriltag``), which would refine on the decimated image.
        search_min_side_px: least longer side, px, of the image ``search_decimate`` 0 searches.
        decimated_thresh_win_size_px: a decimated ArUco search thresholds once, with this
            window (px of the searched image), instead of once per size of the
            adaptive_thresh_win_size range: the tags of a frame large enough to decimate are small
            in the searched image, which one window covers, and the pipeline reads the tags a
            search misses at the pose of those it found. 0: the full range.
        decimated_pixel_per_cell: a decimated ArUco search reads each candidate's cells at this
            many px per cell (``perspective_remove_pixel_per_cell`` elsewhere): its tags are
            small in the searched image (a few px per cell), so a finer resampling adds no
            detail, only cost; on ``ficap synth`` and blender_dev 1080p frames it finds as many
            tags as the finer reading in all, or more (docs/detection.md). 0: as
            ``perspective_remove_pixel_per_cell``.
        decode_rejected, decode_max_bit_errors: the search's second chance (opencv backend with
            ``edge`` refine): the quads ArUco rejected are edge-refined at full size and read
            again (``decode_tags``, at most this many of 36 bits corrected). ArUco's
            own reading at its polygon corners loses small, blurred or oblique tags.
        edge_search_px: longest half-length, px, of the search along each side's normal
            (``edge`` refine).
        edge_window_cells: the same half-length's cap in cells across the side (on an oblique
            tag, narrower than the mean cell), so the search stays on the black border and the
            white quiet zone; never under 0.75 px.
        edge_profile_samples: samples across each side's window (odd; ``edge`` refine): their
            spacing is the window's length / (samples - 1).
        edge_samples_per_side: samples along each side (``edge`` refine).
        edge_corner_skip: fraction of each side left out next to each corner (``edge`` refine),
            where the neighbouring side's edge blurs in.
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
            through an sRGB tone curve (``fit_tags_photometric``, ``ficap_ros.vision.photometric``).
            More accurate where noise limits the cell-edge fit (low light), at a much higher CPU
            cost per tag than that fit (costs in docs/benchmarks.md). ``edge`` refine with
            ``edge_fit`` only (else ``ConfigError``).
        edge_photometric_auto: with ``edge_photometric`` off, fit photometrically only the tags
            where noise limits the cell-edge fit: those whose noise ratio
            (``tag_noise.noise_ratios``: noise sd over contrast times sqrt(px per cell), from the
            tag's own cell centres) exceeds ``edge_photometric_noise_ratio``; the rest keep the
            cell-edge corners. ``edge`` refine with ``edge_fit`` only (else it does nothing).
        edge_photometric_noise_ratio: that threshold, chosen on ``ficap synth`` frames alone: on
            its dim frames the photometric fit of the tags above it gives about nine tenths of
            the median gain its fit of every tag gives; clean tags lie several times below it
            (docs/detection.md).
        motion_corners: where the camera's exposure is stated and the frames before give the
            cap's velocity, refit the corners of each tag that moves over the exposure with the
            photometric model of its pattern moving along that motion (the mean over the
            exposure in linear light, before the tone curve), so the corners are the
            mid-exposure ones (``ficap_ros.vision.motion_corners``); ``edge`` refine only.
        motion_corners_min_px: the least predicted motion of a tag's corners over the exposure,
            px, for which it is refitted (slower tags keep the cell-edge corners).
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
    # Both backends: search an image decimated by this factor (box average), refine at full size.
    search_decimate: int = 0
    search_min_side_px: int = 960
    decimated_thresh_win_size_px: int = 13
    decimated_pixel_per_cell: int = 4
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
    edge_photometric_auto: bool = True
    edge_photometric_noise_ratio: float = 0.03
    # Moving tags (pipeline.FrameProcessor with an exposure stated): motion-aware corners.
    motion_corners: bool = True
    motion_corners_min_px: float = 2.0

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
        if not 0 <= self.decimated_pixel_per_cell <= 32:
            raise ConfigError(f"decimated_pixel_per_cell must be in [0, 32], got {self.decimated_pixel_per_cell}")
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
        if not (math.isfinite(self.edge_photometric_noise_ratio) and self.edge_photometric_noise_ratio >= 0.0):
            raise ConfigError(f"edge_photometric_noise_ratio must be >= 0, got {self.edge_photometric_noise_ratio}")
        if not (math.isfinite(self.motion_corners_min_px) and self.motion_corners_min_px >= 0.0):
            raise ConfigError(f"motion_corners_min_px must be >= 0, got {self.motion_corners_min_px}")
        if self.edge_photometric and not (self.corner_refine == "edge" and self.edge_fit):
            # It refines the cell-edge fit's corners: without that fit it would do nothing.
            raise ConfigError("the photometric corner fit (edge_photometric, --photometric, "
                              "detector.photometric) needs corner_refine 'edge' with edge_fit, "
                              f"got corner_refine {self.corner_refine!r}, edge_fit {self.edge_fit}")


def opencv_without_ipp() -> None:
    """Turn OpenCV's Intel IPP dispatch off for the calling thread (``cv2.ipp.setUseIPP(False)``).

    OpenCV's IPP path runs ``cpuid`` on every call it dispatches, and in a virtual machine every
    ``cpuid`` traps to the hypervisor. ArUco reads each candidate's cells with many such small
    calls, so with IPP its search is several times slower in a virtual machine, for bit-identical
    detections and poses (docs/detection.md, "Speed"). The switch is OpenCV's and per thread, so
    ``TagDetector`` sets it in the thread that detects.
    """
    import cv2

    if cv2.ipp.useIPP():
        cv2.ipp.setUseIPP(False)


class TagDetector:
    """Finds every tag36h11 tag in a grey image (not filtered by a cap model).

    The backend's detector objects are built once here and reused for every frame. Detecting
    turns OpenCV's IPP off in the calling thread (``opencv_without_ipp``): same results, faster in a
    virtual machine.

    The ``edge`` refinement's stages (``ficap_ros.vision.edges``, ``ficap_ros.vision.corners``)
    take this module's ``DetectorConfig``, so they are imported where they are called, not at the
    top of this module.
    """

    def __init__(self, config: DetectorConfig | None = None) -> None:
        self.config = config or DetectorConfig()
        cfg = self.config
        opencv_without_ipp()
        self._search_scale = 1.0
        self._decimated = False
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
                small tags the completion's prediction leaves out. None / 0: never skip.

        Returns:
            All detections, duplicates included, in the backend's order.

        Raises:
            ImageError: invalid image or ROI.
        """
        full = as_gray(image)
        opencv_without_ipp()  # per thread: the node and the workers detect in their own threads
        edge = self.config.corner_refine == "edge"
        # Auto decimation only where the corners are refined on the full image afterwards (``edge``):
        # ArUco's own refinements (``subpix``, ``apriltag``) would run on the decimated image.
        dec = int(self.config.search_decimate) or (
            1 if self._apriltag is not None or not edge
            else _auto_decimate(full.shape, self.config.search_min_side_px))
        ids, corners, hamming, margin, rejected = self._search_full_size(full, roi, dec)
        searched = corners  # the search's own corners: a second start for the cell-edge fit
        if len(ids) and edge:
            corners = self._refine(full, corners, dec)
        enough = (dec > 1 and wanted_ids is not None and enough_tags > 0
                  and len({int(i) for i in ids if int(i) in wanted_ids}) >= enough_tags)
        if len(rejected) and edge and self.config.decode_rejected and not enough:
            ids, corners, hamming, margin = self._second_chance(full, rejected, ids, corners, hamming, margin)
        shift = np.full(len(ids), np.nan)
        if len(ids) and edge:
            corners, shift = self._corner_stage(full, corners, searched, ids)
        elif len(ids) and self.config.corner_refine == "subpix" and self._apriltag is not None:
            corners = _subpix(full, corners)
        return [
            TagDetection(int(i), c, int(h), float(m), float(e))
            for i, c, h, m, e in zip(ids, corners, hamming, margin, shift)
        ]

    def _search_full_size(
        self, full: np.ndarray, roi: tuple[int, int, int, int] | None, dec: int
    ) -> tuple[np.ndarray, ...]:
        """The search of ``full``'s ``roi`` (all of it for None), decimated by ``dec``: (ids,
        corners (N, 4, 2), hamming, margin, rejected quads (R, 4, 2)) as ``_search``, with the
        corners and quads in full-image coordinates."""
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
        return ids, corners + offset, hamming, margin, rejected + offset

    def _corner_stage(
        self, full: np.ndarray, corners: np.ndarray, searched: np.ndarray, ids: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Every tag found (searched or read again) freed of the tone-curve bias
        (``refine_tag_corners``): (corners, edge shift px). A tag whose fit failed or reads its own
        cells wrong (a corner a cell off: at low light a search polygon or a line side latches
        onto a neighbouring edge) is fitted again from the search's corners and from each corner
        rebuilt from the other three."""
        from ficap_ros.vision.corners import refine_tag_corners

        starts = np.full((len(ids), 4, 2), np.nan)
        starts[:len(searched)] = searched
        return refine_tag_corners(full, corners, ids, self.config, retry_px=starts)

    def _set_search_scale(self, scale: float, decimated: bool = False) -> None:
        """Perimeter-rate limits for a search image ``scale`` times smaller than the full frame,
        and the threshold windows and cell resampling of a decimated search."""
        cfg = self.config
        if self._aruco is None or (scale, decimated) == (self._search_scale, self._decimated):
            return
        params = self._aruco.getDetectorParameters()
        params.minMarkerPerimeterRate = float(cfg.min_marker_perimeter_rate) * scale
        params.maxMarkerPerimeterRate = float(cfg.max_marker_perimeter_rate) * scale
        lo, hi = ((cfg.decimated_thresh_win_size_px,) * 2 if decimated and cfg.decimated_thresh_win_size_px > 0 else
                  (cfg.adaptive_thresh_win_size_min, cfg.adaptive_thresh_win_size_max))
        params.adaptiveThreshWinSizeMin, params.adaptiveThreshWinSizeMax = int(lo), int(hi)
        params.perspectiveRemovePixelPerCell = int(
            cfg.decimated_pixel_per_cell if decimated and cfg.decimated_pixel_per_cell > 0
            else cfg.perspective_remove_pixel_per_cell)
        self._aruco.setDetectorParameters(params)
        self._search_scale, self._decimated = scale, decimated

    def _refine(self, full: np.ndarray, corners: np.ndarray, dec: int) -> np.ndarray:
        """Edge-refined corners; from a decimated search, a tag the refinement cannot reach (its
        polygon corners up to ``dec`` times further off) gets a wide coarse pass, then the fine one."""
        from ficap_ros.vision.edges import (
            refine_corners_edge_ok,
            refine_corners_edge_wide,
        )

        refined, ok = refine_corners_edge_ok(full, corners, self.config)
        if dec > 1 and not ok.all():
            lost = ~ok
            refined[lost] = refine_corners_edge_wide(full, corners[lost], self.config)
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
                # OpenCV's port of AprilTag's refinement returns AprilTag's pixel convention.
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

    pupil-apriltags' ``Detector.__del__`` (1.0.4) destroys the tag families first and then the
    detector, whose destroy still releases each family's decode table: a use after free that
    corrupts the heap and may kill the process long after. Here the detector goes first.

    Raises:
        ConfigError: pupil-apriltags is not installed (an optional package).
    """
    try:
        import pupil_apriltags
    except ImportError as err:
        raise ConfigError("the apriltag detector backend needs the Python package pupil-apriltags "
                          "(pip install pupil-apriltags); the default backend is opencv") from err

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

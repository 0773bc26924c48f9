"""Settings of the as-built model (``BuildConfig``) and the error of recordings that cannot
build it (``CoverageError``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ficap_ros.errors import ConfigError, ModelError

__all__ = ["CoverageError", "BuildConfig"]


class CoverageError(ModelError):
    """The frames do not see every tag often enough, together with enough others, to build it."""


@dataclass(frozen=True)
class BuildConfig:
    """Settings of ``build_model`` and ``replay_check``.

    Attributes:
        min_tags_per_frame: frames with fewer (pose-inlier) model tags are not used.
        min_frames_per_tag: every model tag must be seen in at least this many used frames.
        max_frames: at most this many frames are used (evenly spaced over the input).
        loss: ``least_squares`` robust loss (``soft_l1``, ``huber``, ``cauchy``, ``linear``).
        f_scale_px: residual (px) where the robust loss starts to flatten.
        assembly_sigma_mm: how far (per axis, 1 sigma) a plate may sit from its nominal place: the
            prior that anchors the cap's overall size and the gauge.
        assembly_sigma_deg: the same for its orientation (each rotation axis).
        fit_edge_offset: estimate the global edge offset of the detected corners; ``False`` holds it
            at ``edge_offset_px`` (the printed tag side is then the only scale reference).
        edge_offset_px: start (or fixed) value of the edge offset, px, positive outward.
        anchor_size: hold the RMS radius of the tag centres (about their centroid) at the
            nominal's (a stiff prior, 1e-4 relative): the cap's overall size comes from the
            nominal layout, the plates' moves and turns from the images. ``False`` leaves the size
            to the images and the per-plate priors.
        size: ``auto`` (default): the anchored, edge-offset model is solved first; when the size
            change its fitted edge offset implies (2 |offset| / median tag side, with the size
            free) is smaller than what hand assembly does to the size (``assembly_sigma_mm /
            (sqrt(N) r)``, r the RMS radius of the tag centres), the corners are unbiased enough
            for the printed side to be the better scale reference, and the model is solved again
            with the offset held at 0 and the size free. ``fixed``: ``fit_edge_offset`` and
            ``anchor_size`` as given.
        outlier_px: after a first solve, a tag observation whose corner RMS exceeds this (and 5x the
            median) is dropped and the problem solved again.
        max_nfev: function evaluation budget of each solve.
        max_corner_sigma_mm: a tag whose corners are less certain than this (1 sigma, rms over the
            four, after the gauge) is poorly observed: at a quarter of the ~1 mm a plate is off
            by hand, a built tag is clearly closer to the truth than its nominal place.
        min_view_spread_deg: a tag seen from directions spanning less than this is poorly observed
            (its distance along the one line of sight rests on its apparent size alone). Default 0
            (reported, not judged): the uncertainty already carries the geometry, and a tag seen
            from a narrow spread of directions can still be built well.
        max_depth_change: ``replay_check``: the largest median relative change of the camera-cap
            distance between the built and the nominal model's poses (a fraction). A correct
            as-built model moves it only by what the nominal model gets wrong, a fraction of what
            hand assembly does to the size; a cap grown by the corner bias moves it several times
            further.
    """

    min_tags_per_frame: int = 4
    min_frames_per_tag: int = 3
    max_frames: int = 400
    loss: str = "soft_l1"
    f_scale_px: float = 1.0
    assembly_sigma_mm: float = 1.0
    assembly_sigma_deg: float = 2.0
    fit_edge_offset: bool = True
    edge_offset_px: float = 0.0
    anchor_size: bool = True
    size: str = "auto"
    outlier_px: float = 3.0
    max_nfev: int = 100
    max_corner_sigma_mm: float = 0.25
    min_view_spread_deg: float = 0.0
    max_depth_change: float = 0.003

    def __post_init__(self) -> None:
        if self.min_tags_per_frame < 2:
            raise ConfigError(f"min_tags_per_frame must be >= 2, got {self.min_tags_per_frame}")
        if self.min_frames_per_tag < 1:
            raise ConfigError(f"min_frames_per_tag must be >= 1, got {self.min_frames_per_tag}")
        if self.max_frames < 2:
            raise ConfigError(f"max_frames must be >= 2, got {self.max_frames}")
        if self.max_nfev < 1:
            raise ConfigError(f"max_nfev must be >= 1, got {self.max_nfev}")
        if self.size not in ("auto", "fixed"):
            raise ConfigError(f"size must be 'auto' or 'fixed', got {self.size!r}")
        if self.loss not in ("linear", "soft_l1", "huber", "cauchy", "arctan"):
            raise ConfigError(f"unknown loss {self.loss!r}")
        for name in ("f_scale_px", "assembly_sigma_mm", "assembly_sigma_deg", "outlier_px",
                     "max_corner_sigma_mm", "max_depth_change"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")
        if not np.isfinite(self.edge_offset_px) or abs(self.edge_offset_px) > 5.0:
            raise ConfigError(f"edge_offset_px must be within +-5 px, got {self.edge_offset_px}")
        if not 0.0 <= self.min_view_spread_deg < 180.0:
            raise ConfigError(f"min_view_spread_deg must be in [0, 180), got {self.min_view_spread_deg}")

"""The cap as built, by bundle adjustment over frames that see many tags at once.

Unknowns: every tag is a rigid 32 mm square with its own 6-DoF pose in the cap frame (``R_cap_tag``,
``t_cap_tag_mm``); every frame has its camera pose ``T_cam_cap``; and one global nuisance, the
*edge offset* of the detected corners (px, positive outward). Residuals are the reprojection errors
of the detected corners (undistorted with the frame's intrinsics, so every lens model shares one
pinhole projection), minimised with ``scipy.optimize.least_squares`` (TRF, a sparse Jacobian by
grouped differences, robust ``soft_l1`` loss so a bad corner cannot drag a tag).

Why the edge offset. A corner detector that fits the tag's border lines finds them displaced by a
roughly constant fraction of a pixel when the image chain (lens blur, tone curve, JPEG) is not
symmetric about the black-white edge: on real images the corners sit a fraction of a pixel inside
each tag. If the printed 32 mm side were the only metric reference, every tag would look small by
twice that fraction of its side, and the solver would grow the whole cap to fit (a replay with
that model then puts the cap too far away). So the predicted corner of a tag is its projected corner moved so that both of its
border lines shift by the same ``edge_offset_px`` along their outward normals in the image (the
intersection of the two shifted lines), the way a border-line detector errs.

Why the size is anchored to the nominal layout. An edge offset and a uniform scale of the cap are
nearly interchangeable in the images (both change how large a tag looks), and only the spread of
distances and view angles separates them (and a bias that is not exactly an edge offset leaks
into the size). Hand assembly moves and turns plates; it does not grow the cap. So the RMS radius
of the tag centres is held at the nominal's (``anchor_size``, a stiff prior), and every tag has a
prior toward its nominal place (``assembly_sigma_mm``, about the accuracy of gluing a plate by
hand) and orientation (``assembly_sigma_deg``), which fix the gauge (the rigid motion of the whole
cap the images cannot see) and hold a tag the images barely see. Each plate's own deviation is
measured by the images (its prior weighs about (0.05 mm / 1 mm)^2 against the data).

The anchor costs what hand assembly does to the size (``assembly_size_sigma``: about 0.3 % for
1 mm plates). So with ``size="auto"`` (the default) the edge offset of the same fit with the size
free decides: when the size change it implies (2 |offset| / median tag side) is below that, the
corners are unbiased enough for the printed side to be the better scale, and the model is solved
again with the offset held at 0 and the size free. After the solve the model is Kabsch-aligned
to the nominal corners, so the as-built cap frame is the nominal one in the least-squares sense,
and per-tag deviations are relative to it.

Trust. Each tag's deviation comes with a standard deviation from the Gauss-Newton covariance (the
Schur complement over the camera poses, the whole-cap rigid motion projected out), with its
observation count and the spread of the directions it was seen from. ``BuildResult.problems`` lists
every reason not to trust the model (solver budget reached, a tag seen too rarely or with a large
uncertainty; optionally from too narrow a spread of directions); ``replay_check`` re-estimates
every frame's pose with the nominal and the built model, the pose code replay uses, and adds a
warning when the built model fits the recording worse, a problem when it moves the cap along the
line of sight by more than hand assembly can (``depth_change_limit``).

Modules: ``config`` (BuildConfig), ``geometry`` (tag frames, edge offset, size, alignment),
``observations`` (usable frames, observation arrays, coverage), ``adjustment`` (residuals,
Jacobian, solve, covariance), ``report`` (TagDeviation, BuildResult), ``replay_check``, ``build``
(``build_model``). This package exports their public names.
"""

from __future__ import annotations

from ficap_ros.tools.model_build.build import build_model
from ficap_ros.tools.model_build.config import BuildConfig, CoverageError
from ficap_ros.tools.model_build.geometry import (
    LOCAL_CORNERS_MM,
    align_model,
    edge_shift_px,
    size_ratio,
    tag_frames,
)
from ficap_ros.tools.model_build.replay_check import (
    ReplayCheck,
    assembly_size_sigma,
    depth_change_limit,
    replay_check,
)
from ficap_ros.tools.model_build.report import BuildResult, TagDeviation

__all__ = [
    "CoverageError",
    "BuildConfig",
    "TagDeviation",
    "BuildResult",
    "ReplayCheck",
    "build_model",
    "replay_check",
    "depth_change_limit",
    "assembly_size_sigma",
    "tag_frames",
    "align_model",
    "size_ratio",
    "edge_shift_px",
    "LOCAL_CORNERS_MM",
]

"""The tag-level photometric corner fit (``DetectorConfig(edge_photometric=True)``).

On ``ficap synth`` frames rendered through the realistic chain (lens PSF in linear light, shot and
read noise, clipping, a tone curve, JPEG) with exact truth: the fit, run as the corner stage's last
step, must beat the cell-edge fit it starts from where noise limits it (low light) and keep the
corner targets (median <= 0.15 px, p95 <= 0.5 px, mean radial within +-0.05 px) where it does not
(a sharp lens under an S-curve, a soft lens with clipped highlights), on fully visible tags within
70 deg of head-on. Its pixel selection is checked against a plain per-box oracle.
"""

from __future__ import annotations

import numpy as np
import pytest
from corner_eval import MODEL, clean_corner_errors, drive_frames

from ficap_ros.geometry.metrics import corner_errors_px
from ficap_ros.tools.synth import RenderConfig
from ficap_ros.vision.corners import fit_tags_photometric
from ficap_ros.vision.detector import DetectorConfig, TagDetector
from ficap_ros.vision.tracking import view_angles_deg

EDGE = TagDetector(DetectorConfig(edge_photometric_auto=False))
PHOTO = TagDetector(DetectorConfig(edge_photometric=True))


@pytest.mark.parametrize(
    "resolution, tone, gamma, psf_sigma_px, lighting, max_median_px",
    [
        ("540p", "srgb", 2.2, 0.7, "low", 0.10),
        ("1080p", "filmic", 2.2, 0.4, "low", 0.08),
    ],
)
def test_photometric_fit_beats_the_cell_edge_fit_in_low_light(
    resolution, tone, gamma, psf_sigma_px, lighting, max_median_px,
) -> None:
    """Low light (noise-limited): the photometric fit's median at most three quarters of the
    cell-edge fit's on the same frames, the same tags, unbiased (|mean radial| <= 0.05 px)."""
    frames = drive_frames(resolution, RenderConfig(lighting=lighting, tone=tone, gamma=gamma,
                                              psf_sigma_px=psf_sigma_px, jpeg_quality=95))
    e0, _, n0, _ = clean_corner_errors(EDGE, frames)
    e1, r1, n1, _ = clean_corner_errors(PHOTO, frames)
    print(f"edge median {np.median(e0):.3f}; photometric median {np.median(e1):.3f} "
          f"p95 {np.percentile(e1, 95):.3f} radial {r1.mean():+.3f} ({n1} tags)")
    assert n1 == n0  # the same tags: the fit only moves corners
    assert np.median(e1) <= max_median_px
    assert np.median(e1) <= 0.75 * np.median(e0)
    assert np.percentile(e1, 95) <= 0.3
    assert abs(r1.mean()) <= 0.05


@pytest.mark.parametrize(
    "resolution, tone, gamma, psf_sigma_px, lighting",
    [("540p", "filmic", 2.2, 0.4, "neutral"), ("540p", "gamma", 1.8, 1.0, "high")],
)
def test_photometric_fit_keeps_the_targets_without_noise(resolution, tone, gamma, psf_sigma_px, lighting) -> None:
    """A sharp lens under an S-curve and a soft lens with clipped highlights: not worse than the
    cell-edge fit, within the targets."""
    frames = drive_frames(resolution, RenderConfig(lighting=lighting, tone=tone, gamma=gamma,
                                              psf_sigma_px=psf_sigma_px, jpeg_quality=95))
    e0, _, _, _ = clean_corner_errors(EDGE, frames)
    e1, r1, _, _ = clean_corner_errors(PHOTO, frames)
    print(f"edge median {np.median(e0):.3f}; photometric median {np.median(e1):.3f} "
          f"p95 {np.percentile(e1, 95):.3f} radial {r1.mean():+.3f}")
    assert np.median(e1) <= np.median(e0) + 0.005
    assert np.median(e1) <= 0.15
    assert np.percentile(e1, 95) <= 0.5
    assert abs(r1.mean()) <= 0.05


def test_photometric_fit_converges_from_displaced_corners_and_leaves_a_bad_start_alone() -> None:
    """From the true corners moved 0.3 px (a cell-edge fit's error on a noisy frame) the fit
    returns to within 0.1 px median; a start two cells off, where the fit settles in a false
    minimum (its residual a third or more of the tag's contrast), is not fitted (kept as given)."""
    fr = drive_frames("1080p", RenderConfig(lighting="neutral", tone="srgb", psf_sigma_px=0.7, jpeg_quality=95), n=1)[0]
    angles = dict(zip(MODEL.ids, view_angles_deg(MODEL, fr.T_cam_cap)))
    ids = np.array([t for t in fr.visible_ids(0.999) if angles[t] <= 60.0])
    truth = np.array([fr.corners_px[t] for t in ids])
    rng = np.random.default_rng(1)
    start = truth + rng.normal(scale=0.3 / np.sqrt(2.0), size=truth.shape)
    fitted, ok = fit_tags_photometric(fr.image, start, ids)
    e_start, _ = corner_errors_px(start, truth)
    e, _ = corner_errors_px(fitted, truth)
    print(f"start median {np.median(e_start):.3f} -> {np.median(e):.3f} px, {ok.sum()}/{len(ids)} fitted")
    assert ok.all()
    assert np.median(e) <= 0.1
    bad = truth.copy()
    side = np.linalg.norm(truth[:, 1] - truth[:, 0], axis=1)
    bad[:, :, 0] += (2.0 * side / 8.0)[:, None]  # two cells to the right
    out, ok_bad = fit_tags_photometric(fr.image, bad, ids)
    assert not ok_bad.any()
    np.testing.assert_array_equal(out, bad)


def test_photometric_fit_takes_colour_frames_and_refuses_what_it_cannot_do() -> None:
    """A BGR frame gives the grey frame's answer (``as_gray``), a frame of the wrong dtype is an
    ImageError (one readable line, not numpy's), and one Gauss-Newton step, where no misfit is
    ever measured, is refused rather than leaving every tag unfitted."""
    import cv2

    from ficap_ros.errors import ImageError

    fr = drive_frames("540p", RenderConfig(lighting="neutral", jpeg_quality=95), n=1)[0]
    ids = np.array(fr.visible_ids(0.999)[:3])
    start = np.array([fr.corners_px[t] for t in ids]) + 0.1
    grey = fit_tags_photometric(fr.image, start, ids)
    colour = fit_tags_photometric(cv2.cvtColor(fr.image, cv2.COLOR_GRAY2BGR), start, ids)
    assert grey[1].all()
    np.testing.assert_array_equal(grey[0], colour[0])
    with pytest.raises(ImageError, match="dtype"):
        fit_tags_photometric(fr.image.astype(np.float32), start, ids)
    with pytest.raises(ValueError, match="iterations"):
        fit_tags_photometric(fr.image, start, ids, iterations=1)
    with pytest.raises(ValueError, match="damping"):
        fit_tags_photometric(fr.image, start, ids, damping=0.0)
    with pytest.raises(ValueError, match="instant_spacing_sds"):
        fit_tags_photometric(fr.image, start, ids, instant_spacing_sds=-1.0)


def test_pipeline_takes_the_uncertainty_profile_of_its_corners() -> None:
    """An unset uncertainty (None) means the synth-calibrated profile of the corner estimator in use
    (``UncertaintyConfig.for_corners``): with photometric corners the pipeline's bounds are those of
    ``estimate_cap_pose`` with the photometric profile on the same detections (tilt gain 0.1, so a
    narrower translation bound under spotlights than the default corners' profile would give), with
    the default corners those of ``PoseConfig()``; an uncertainty set by the user is kept; and the
    fleet fingerprint's pose is the one applied."""
    from ficap_ros.tools.fleet.fingerprints import config_json, label_settings
    from ficap_ros.vision.detector import as_gray
    from ficap_ros.vision.pipeline import (
        FrameProcessor,
        hidden_tag_ids,
        pose_config_for,
    )
    from ficap_ros.vision.pose import PoseConfig, estimate_cap_pose
    from ficap_ros.vision.uncertainty import UncertaintyConfig

    photo_u = UncertaintyConfig.for_corners("photometric")
    assert UncertaintyConfig.for_corners("edge") == UncertaintyConfig()
    assert photo_u == UncertaintyConfig(light_gradient_tilt_gain=0.1, edge_shift_tilt_gain=0.0,
                                        shared_bias_gain=0.0, common_offset_gain=0.75,
                                        common_offset_se_gain=0.75)
    fr = drive_frames("540p", RenderConfig(lighting="high"), n=1)[0]
    for det, profile in ((DetectorConfig(edge_photometric=True), photo_u),
                         (DetectorConfig(), UncertaintyConfig())):
        r = FrameProcessor(MODEL, det, PoseConfig(), tracking=False).process(fr.image, fr.camera)
        assert r.pose is not None, r.reason
        hidden = hidden_tag_ids(as_gray(fr.image), r.detections)
        bounds = {}
        for name, u in (("applied", profile), ("edge", UncertaintyConfig()), ("photometric", photo_u)):
            p = estimate_cap_pose(r.detections, MODEL, fr.camera, PoseConfig(uncertainty=u), hidden_ids=hidden).pose
            bounds[name] = (p.trans_err95_mm, p.rot_err95_deg)
        print(det.edge_photometric, r.pose.trans_err95_mm, bounds)
        assert (r.pose.trans_err95_mm, r.pose.rot_err95_deg) == pytest.approx(bounds["applied"], rel=1e-12)
        # Spotlights: the light-gradient tilt term is in play, so the two profiles differ here.
        assert bounds["photometric"][0] < 0.9 * bounds["edge"][0]
        err_mm = 1e3 * np.linalg.norm(r.pose.T_cam_cap.translation_m - fr.T_cam_cap.translation_m)
        assert err_mm <= r.pose.trans_err95_mm
    # A set uncertainty is the user's, whatever the corners, even the defaults; unset is resolved.
    mine = PoseConfig(uncertainty=UncertaintyConfig(light_gradient_tilt_gain=0.2))
    assert pose_config_for(mine, DetectorConfig(edge_photometric=True)) is mine
    defaults = PoseConfig(uncertainty=UncertaintyConfig())
    assert pose_config_for(defaults, DetectorConfig(edge_photometric=True)) is defaults
    assert pose_config_for(PoseConfig(), DetectorConfig()) == defaults
    assert label_settings(MODEL, PoseConfig())["pose"] == config_json(defaults)
    photo = label_settings(MODEL, PoseConfig(), detector=DetectorConfig(edge_photometric=True))["pose"]
    assert photo == config_json(PoseConfig(uncertainty=photo_u))
    assert photo["uncertainty"]["light_gradient_tilt_gain"] == 0.1


def test_photometric_fit_leaves_a_tag_without_contrast_unfitted() -> None:
    """A tag region painted flat (nothing to fit: its misfit is zero) is reported not fitted and
    keeps its corners, while the other tags of the frame are fitted as before."""
    fr = drive_frames("540p", RenderConfig(lighting="neutral", jpeg_quality=95), n=1)[0]
    ids = np.array(fr.visible_ids(0.999)[:3])
    start = np.array([fr.corners_px[t] for t in ids]) + 0.1
    before, ok_before = fit_tags_photometric(fr.image, start, ids)
    flat = fr.image.copy()
    x0, y0 = np.floor(start[0].min(axis=0) - 6).astype(int)
    x1, y1 = np.ceil(start[0].max(axis=0) + 6).astype(int)
    flat[max(y0, 0):y1, max(x0, 0):x1] = 128
    out, ok = fit_tags_photometric(flat, start, ids)
    assert ok_before.all() and not ok[0]
    np.testing.assert_array_equal(out[0], start[0])
    np.testing.assert_array_equal(ok[1:], ok_before[1:])


def _select_pixels_per_box(shape, hom, tables, sd_px, reach_px, max_pixels):  # noqa: ANN001, ANN202
    """The pixel selection without shortcuts (every pixel of each tag's box, its summed-area
    table read per pixel): the oracle for ``photometric._select_pixels``."""
    from ficap_ros.geometry.tag36h11 import TAG_CELLS
    from ficap_ros.vision.photometric import _PAD

    h_img, w_img = shape
    face = np.array([[-1, -1, 1], [9, -1, 1], [9, 9, 1], [-1, 9, 1]], float)
    tags, cols, rows = [], [], []
    for t in range(len(hom)):
        q = face @ hom[t].T
        xy = q[:, :2] / q[:, 2:]
        x0, y0 = np.floor(xy.min(axis=0)).astype(int)
        x1, y1 = np.ceil(xy.max(axis=0)).astype(int)
        x0, y0, x1, y1 = max(x0, 1), max(y0, 1), min(x1, w_img - 2), min(y1, h_img - 2)
        if x1 - x0 < 3 or y1 - y0 < 3:
            continue
        xs, ys = np.arange(x0, x1 + 1, dtype=np.float64), np.arange(y0, y1 + 1, dtype=np.float64)
        Hi = np.linalg.inv(hom[t])
        u = np.add.outer(Hi[0, 1] * ys, Hi[0, 0] * xs).ravel() + Hi[0, 2]
        v = np.add.outer(Hi[1, 1] * ys, Hi[1, 0] * xs).ravel() + Hi[1, 2]
        den = np.add.outer(Hi[2, 1] * ys, Hi[2, 0] * xs).ravel() + Hi[2, 2]
        u, v = u / den, v / den
        on = np.flatnonzero((u > -0.9) & (u < TAG_CELLS + 0.9) & (v > -0.9) & (v < TAG_CELLS + 0.9))
        gy, gx = np.divmod(on, len(xs))
        u, v = u[on], v[on]
        side = np.linalg.norm(xy[[1, 2, 3, 0]] - xy, axis=1).mean() / 10.0
        r = (reach_px + 1.5 * sd_px) / max(side, 1e-6)
        tab = tables[t]
        sat = np.zeros((tab.shape[0] + 1, tab.shape[1] + 1))
        sat[1:, 1:] = tab.cumsum(0).cumsum(1)
        last = tab.shape[1] - 1
        lo_u = np.clip(np.floor(u - r) + _PAD, 0, last).astype(np.intp)
        hi_u = np.clip(np.floor(u + r) + _PAD, 0, last).astype(np.intp) + 1
        lo_v = np.clip(np.floor(v - r) + _PAD, 0, last).astype(np.intp)
        hi_v = np.clip(np.floor(v + r) + _PAD, 0, last).astype(np.intp) + 1
        black = sat[hi_v, hi_u] - sat[lo_v, hi_u] - sat[hi_v, lo_u] + sat[lo_v, lo_u]
        near = np.flatnonzero((black > 0) & (black < (hi_u - lo_u) * (hi_v - lo_v)))
        if len(near) > max_pixels:
            near = near[np.linspace(0, len(near) - 1, max_pixels).astype(np.intp)]
        tags.append(np.full(len(near), t))
        cols.append(gx[near] + x0)
        rows.append(gy[near] + y0)
    if not tags:
        return (np.zeros(0, dtype=np.intp),) * 3
    return np.concatenate(tags), np.concatenate(cols), np.concatenate(rows)


def test_pixel_selection_is_the_per_box_one() -> None:
    """``_select_pixels`` (tags' boxes, inverses and reaches at once; where the reach is under a
    cell, one lookup a pixel in a table of every box's colours) picks the same pixels, in the same
    order, as the per-box oracle: tags from 0.8 to 25 px a cell (reach 0.1 to 2.5 cells:
    boxes of 1 to 3 cells a side, and the clipped path), strong perspective, cut by the image
    border, thinned and not."""
    from ficap_ros.vision.photometric import _black_tables, _select_pixels

    rng = np.random.default_rng(3)
    shape = (540, 960)
    homs = []
    for k in range(40):
        cell = [0.8, 1.2, 3.0, 6.0, 12.0, 25.0][k % 6]
        a = cell * np.array([[np.cos(0.3 * k), -np.sin(0.3 * k)], [np.sin(0.3 * k), np.cos(0.3 * k)]])
        centre = rng.uniform([-40, -40], [shape[1] + 40, shape[0] + 40])
        H = np.eye(3)
        H[:2, :2] = a
        H[2, :2] = rng.normal(0.0, 0.004 / cell, 2) * (k % 3)  # perspective on two tags in three
        H[:2, 2] = centre - a @ [4.0, 4.0]
        homs.append(H)
    hom = np.array(homs)
    tables = _black_tables(rng.random((len(hom), 8, 8)) < 0.5)
    for sd_px, max_pixels in ((0.66, 1500), (1.2, 300)):
        got = _select_pixels(shape, hom, tables, sd_px, 1.0, max_pixels)
        want = _select_pixels_per_box(shape, hom, tables, sd_px, 1.0, max_pixels)
        assert len(want[0]) > 1000 and len(np.unique(want[0])) > 20
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
    assert len(_select_pixels(shape, hom[:0], tables[:0], 0.66, 1.0, 1500)[0]) == 0


def test_photometric_fit_of_a_tag_does_not_depend_on_the_others() -> None:
    """Each tag's fit is its own, which lets ``fit_tags`` fit a frame's tags a few at a time: all
    of a frame's tags at once (more than a chunk) give, bit for bit, what each tag fitted alone does."""
    fr = drive_frames("540p", RenderConfig(lighting="low", jpeg_quality=95), n=1)[0]
    ids = np.array(fr.visible_ids(0.999))
    start = np.array([fr.corners_px[t] for t in ids]) + 0.1
    assert len(ids) > 12
    together, ok = fit_tags_photometric(fr.image, start, ids)
    for k in range(len(ids)):
        alone, ok1 = fit_tags_photometric(fr.image, start[k:k + 1], ids[k:k + 1])
        np.testing.assert_array_equal(alone[0], together[k])
        assert ok1[0] == ok[k]
    assert ok.sum() >= len(ids) - 2

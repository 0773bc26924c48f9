"""The pose covariance and its 95 % bounds (ficap_ros.vision.uncertainty): never zero, the propagation right
(Monte Carlo with errors drawn from the stated sources), the residuals split into their sources."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg, rotation_from_ypr_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth import default_scene
from ficap_ros.vision.detector import TagDetection
from ficap_ros.vision.error_bounds import error_bound95
from ficap_ros.vision.frame_measures import shared_bias_ratio
from ficap_ros.vision.pose import PoseConfig, estimate_cap_pose
from ficap_ros.vision.reprojection import TagObservations
from ficap_ros.vision.tracking import view_angles_deg
from ficap_ros.vision.uncertainty import (
    UncertaintyConfig,
    combine_uncertainty,
    common_offset_mode,
    uncertainty_bounds,
    uncertainty_sources,
    uncertainty_terms,
)

MODEL = nominal_model()
SCENE = default_scene("540p")
CAM = SCENE.camera


def _truth(yaw: float = 20.0, pitch: float = 5.0):  # noqa: ANN202
    return SCENE.cap_pose(rotation_from_ypr_deg(yaw, pitch, 2.0))


def _exact_corners(T, max_view_deg: float = 70.0) -> dict[int, np.ndarray]:  # noqa: ANN001
    seen = view_angles_deg(MODEL, T) < max_view_deg
    px = CAM.project(T.apply(MODEL.corners_mm.reshape(-1, 3) / 1000.0)).reshape(-1, 4, 2)
    return {int(i): px[k] for k, i in enumerate(MODEL.ids) if seen[k]}


def _pose(corners: dict[int, np.ndarray], config: PoseConfig | None = None):  # noqa: ANN202
    dets = [TagDetection(i, c) for i, c in corners.items()]
    result = estimate_cap_pose(dets, MODEL, CAM, config or PoseConfig())
    assert result.pose is not None, result.reason
    return result.pose


def test_covariance_never_zero_or_infinite() -> None:
    T = _truth()
    exact = _exact_corners(T)
    assert len(exact) >= 6
    for ids in (list(exact), list(exact)[:2], list(exact)[:1]):
        pose = _pose({i: exact[i] for i in ids})  # perfect corners: zero residuals
        cov = pose.covariance
        assert np.all(np.isfinite(cov)) and np.allclose(cov, cov.T)
        assert np.linalg.eigvalsh(cov).min() > 0  # the floors: never "exact"
        assert 0 < pose.rot_err95_deg < 180 and 0 < pose.trans_err95_mm < 1e4
        assert 0 < pose.reliability < 1
    # Fewer tags, wider bounds, lower reliability.
    many, two = _pose(exact), _pose({i: exact[i] for i in list(exact)[:2]})
    assert two.rot_err95_deg > many.rot_err95_deg and two.reliability < many.reliability


def _draw_errors(rng: np.random.Generator, corners: dict[int, np.ndarray], T, cfg: UncertaintyConfig):  # noqa: ANN001, ANN202
    """Corners moved by errors drawn from the stated sources: independent noise, per-tag and
    common radial bias, plate shifts and turns (built cap vs model)."""
    out = {}
    common = rng.normal(0.0, cfg.corner_bias_common_px)
    for i, c in corners.items():
        plate = MODEL.corners_of(i)
        centre = plate.mean(axis=0)
        shift = rng.normal(0.0, cfg.model_mm, 3)
        turn = np.radians(rng.normal(0.0, cfg.model_deg, 3))
        from scipy.spatial.transform import Rotation

        built = Rotation.from_rotvec(turn).apply(plate - centre) + centre + shift
        px = CAM.project(T.apply(built / 1000.0))
        radial = px - px.mean(axis=0)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        bias = common + rng.normal(0.0, cfg.corner_bias_px)
        out[i] = px + bias * radial + rng.normal(0.0, cfg.corner_noise_px, (4, 2))
    return out


def _floors_only(corners: dict[int, np.ndarray], T, cfg: UncertaintyConfig) -> np.ndarray:  # noqa: ANN001
    """The covariance of the stated sources alone (the residual-based share left out)."""
    obs = TagObservations.of({i: CAM.undistort_px(c) for i, c in corners.items()}, MODEL, CAM.K)
    terms, seen = uncertainty_terms(obs, T)
    return combine_uncertainty(terms, dict.fromkeys(seen, 0.0), cfg)


SOURCES = UncertaintyConfig(corner_noise_px=0.1, corner_bias_px=0.1, corner_bias_common_px=0.1,
                            model_mm=0.3, model_deg=0.5, residual_inflation=1.0)


def _monte_carlo(T, cfg: UncertaintyConfig, config: PoseConfig, n: int = 300):  # noqa: ANN001, ANN202
    exact = _exact_corners(T)
    rng = np.random.default_rng(7)
    out = {k: [] for k in ("rot_err", "trans_err", "rot95", "trans95", "dtheta")}
    for _ in range(n):
        pose = _pose(_draw_errors(rng, exact, T, cfg), config)
        out["rot_err"].append(angle_deg(pose.T_cam_cap.rotation, T.rotation))
        out["trans_err"].append(1e3 * np.linalg.norm(pose.T_cam_cap.translation_m - T.translation_m))
        out["rot95"].append(pose.rot_err95_deg)
        out["trans95"].append(pose.trans_err95_mm)
        out["dtheta"].append((pose.T_cam_cap.rotation * T.rotation.inv()).as_rotvec())
    return exact, {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("yaw", [0.0, 40.0])
def test_propagation_of_the_stated_sources(yaw: float) -> None:
    """Errors drawn from exactly the sources a covariance states: its rotation block predicts the
    spread of the pose errors they cause (first-order propagation through the fit), and its 95 %
    bounds cover about 95 % of them."""
    T = _truth(yaw)
    exact, mc = _monte_carlo(T, SOURCES, PoseConfig(uncertainty=SOURCES))
    cov = _floors_only(exact, T, SOURCES)
    emp = np.cov(mc["dtheta"].T)
    ratio = np.trace(cov[3:, 3:]) / np.trace(emp)
    rot95, trans95 = error_bound95(cov)
    cover_r = np.mean(mc["rot_err"] <= rot95)
    cover_t = np.mean(mc["trans_err"] <= trans95)
    print(f"\nyaw {yaw}: predicted / drawn rotation variance {ratio:.2f}; coverage rotation "
          f"{100 * cover_r:.1f} %, translation {100 * cover_t:.1f} %")
    assert 0.8 < ratio < 1.25
    assert 0.92 <= cover_r <= 0.98 and 0.92 <= cover_t <= 0.98


def test_residuals_alone_cover_what_they_show() -> None:
    """With negligible floors, the residual-based share (each corner pattern's sigma pooled over
    the frame's tags) covers errors from noise, per-tag bias and misplaced plates by itself."""
    T = _truth(25.0)
    tiny = UncertaintyConfig(corner_noise_px=1e-4, corner_bias_px=0.0, corner_bias_common_px=0.0,
                             model_mm=0.0, model_deg=0.0, residual_inflation=1.0,
                             shared_bias_gain=0.0)
    drawn = UncertaintyConfig(corner_noise_px=0.1, corner_bias_px=0.1, corner_bias_common_px=0.0,
                              model_mm=0.3, model_deg=0.5)
    _, mc = _monte_carlo(T, drawn, PoseConfig(uncertainty=tiny))
    cover = np.mean(mc["rot_err"] <= mc["rot95"])
    sharp = np.median(mc["rot95"]) / np.median(mc["rot_err"])
    print(f"\nresidual-based only: rotation coverage {100 * cover:.1f} %, median bound / error {sharp:.2f}")
    assert 0.88 <= cover <= 0.995 and sharp < 3.0


def test_residuals_reveal_misplaced_plates() -> None:
    """A built cap whose plates sit ~1 mm off the model: the residuals' per-tag shifts raise the
    plate term above its floor, so the bound grows to cover the larger error."""
    T = _truth(10.0)
    exact = _exact_corners(T)
    rng = np.random.default_rng(3)
    built = _draw_errors(rng, exact, T, UncertaintyConfig(corner_noise_px=0.02, corner_bias_px=0.0,
                                                          corner_bias_common_px=0.0, model_mm=1.0,
                                                          model_deg=1.0))
    nominal = _pose(_draw_errors(rng, exact, T, UncertaintyConfig(corner_noise_px=0.02,
                                                                  corner_bias_px=0.0,
                                                                  corner_bias_common_px=0.0,
                                                                  model_mm=0.0, model_deg=0.0)))
    asbuilt = _pose(built)
    assert asbuilt.rot_err95_deg > 3 * nominal.rot_err95_deg
    assert angle_deg(asbuilt.T_cam_cap.rotation, T.rotation) < asbuilt.rot_err95_deg


@pytest.mark.parametrize("offset_px", [0.3, -0.3])
def test_the_signed_common_offset_predicts_the_pose_error(offset_px: float) -> None:
    """Every tag's corners moved radially by the same amount (outward positive): the signed
    estimate reads it with its sign, and the pose error along the offset's mode is its effect (the
    mode's translation oriented toward the camera for an outward offset: a larger image is a
    closer cap)."""
    T = _truth(15.0)
    corners = {}
    for i, c in _exact_corners(T).items():
        radial = c - c.mean(axis=0)
        corners[i] = c + offset_px * radial / np.linalg.norm(radial, axis=1, keepdims=True)
    pose = _pose(corners)
    obs = TagObservations.of({i: CAM.undistort_px(c) for i, c in corners.items()}, MODEL, CAM.K)
    terms, seen = uncertainty_terms(obs, pose.T_cam_cap)
    assert seen["bias_common_signed"] == pytest.approx(offset_px, rel=0.05)
    assert seen["bias_common"] == pytest.approx(abs(offset_px), rel=0.05)
    a_m = common_offset_mode(terms)[:3]
    a_m = a_m if a_m[2] < 0.0 else -a_m  # outward: toward the camera
    error_m = pose.T_cam_cap.translation_m - T.translation_m
    predicted_m = a_m * seen["bias_common_signed"]
    assert np.linalg.norm(error_m - predicted_m) < 0.15 * np.linalg.norm(error_m)


def test_offset_is_the_measured_common_radial_share() -> None:
    """The offset ``uncertainty_bounds`` returns is the share of the covariance that the tags'
    measured common radial offset contributes (the covariance minus it is the rest), and the
    degrees of freedom are those the residual pooling had."""
    T = _truth(15.0)
    exact = _exact_corners(T)
    rng = np.random.default_rng(8)
    corners = {}
    for i, c in exact.items():
        radial = c - c.mean(axis=0)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        corners[i] = c - 0.3 * radial + rng.normal(0.0, 0.05, (4, 2))  # every tag 0.3 px inward
    obs = TagObservations.of({i: CAM.undistort_px(c) for i, c in corners.items()}, MODEL, CAM.K)
    cfg = UncertaintyConfig(common_offset_gain=1.0)
    terms, seen = uncertainty_terms(obs, T)
    assert seen["bias_common"] > 0.1
    cov = combine_uncertainty(terms, seen, cfg)
    offset, dof = uncertainty_bounds(terms, seen, cfg, cov)
    rest = combine_uncertainty(terms, {**seen, "bias_common": 0.0}, cfg)
    np.testing.assert_allclose(cov - np.outer(offset, offset), rest, rtol=1e-6, atol=1e-15)
    assert all(np.isfinite(d) and d > 10 for d in dof)  # ~20 tags x patterns
    # Each profile states it at its gain: the edge one (the defaults) as measured, the
    # photometric one at 0.75.
    for profile, gain in (("edge", 1.0), ("photometric", 0.75)):
        cfg = UncertaintyConfig.for_corners(profile)
        assert cfg.common_offset_gain == gain
        off, _ = uncertainty_bounds(terms, seen, cfg, cov)
        np.testing.assert_allclose(off, gain * offset, rtol=1e-9)
    off0, _ = uncertainty_bounds(terms, seen, UncertaintyConfig(common_offset_gain=0.0), cov)
    assert np.all(off0 == 0.0)


def test_common_offset_standard_error_is_its_scatter() -> None:
    """``bias_common_se`` is the scatter of the measured common offset over noise draws (every
    tag 0.3 px inward, well above the noise: the estimate is not clipped), and
    ``common_offset_se_gain`` states it as a sigma along the common radial mode (0: not at all;
    the edge profile's default 1: as measured)."""
    T = _truth(15.0)
    exact = _exact_corners(T)
    rng = np.random.default_rng(5)
    flat = PoseConfig(uncertainty=UncertaintyConfig(weight_tags=False))  # the terms' equal weights
    estimates, errors = [], []
    for _ in range(40):
        corners = _with_common_offset(exact, -0.3, 0.1, rng)
        obs = TagObservations.of({i: CAM.undistort_px(c) for i, c in corners.items()}, MODEL, CAM.K)
        terms, seen = uncertainty_terms(obs, _pose(corners, flat).T_cam_cap)
        estimates.append(seen["bias_common"])
        errors.append(seen["bias_common_se"])
    assert abs(np.median(estimates) - 0.3) < 0.05  # the offset, scaled back
    assert 0.6 < np.std(estimates) / np.median(errors) < 1.6
    assert UncertaintyConfig().common_offset_se_gain == 1.0  # the edge profile: as measured
    base = UncertaintyConfig(common_offset_se_gain=0.0)
    np.testing.assert_array_equal(combine_uncertainty(terms, seen, base),
                                  combine_uncertainty(terms, {**seen, "bias_common_se": 9.0}, base))
    stated = UncertaintyConfig(common_offset_se_gain=1.5)
    added = combine_uncertainty(terms, seen, stated) - combine_uncertainty(terms, seen, base)
    np.testing.assert_allclose(added, (1.5 * seen["bias_common_se"]) ** 2 * terms["bias_common"],
                               rtol=1e-6, atol=1e-18)


def test_noisy_tags_weighted_down() -> None:
    """A few tags with ten times the corner noise of the others (oblique, dark, or read a second
    time): weighting each tag by its own residuals (``tag_noise_px``) lowers the pose error, and
    the weighted fit's bound still covers it."""
    T = _truth(15.0)
    exact = _exact_corners(T)
    noisy = set(list(exact)[::4])
    rng = np.random.default_rng(11)
    equal = PoseConfig(uncertainty=UncertaintyConfig(weight_tags=False))
    err_w, err_eq, bound_w = [], [], []
    for _ in range(60):
        corners = {i: c + rng.normal(0.0, 0.5 if i in noisy else 0.05, (4, 2)) for i, c in exact.items()}
        weighted, unweighted = _pose(corners), _pose(corners, equal)
        err_w.append(angle_deg(weighted.T_cam_cap.rotation, T.rotation))
        err_eq.append(angle_deg(unweighted.T_cam_cap.rotation, T.rotation))
        bound_w.append(weighted.rot_err95_deg)
    err_w, err_eq, bound_w = map(np.array, (err_w, err_eq, bound_w))
    print(f"\n{len(noisy)} noisy of {len(exact)} tags: median rotation error weighted "
          f"{np.median(err_w):.4f} deg, equal weights {np.median(err_eq):.4f} deg; weighted bound "
          f"covers {100 * np.mean(err_w <= bound_w):.0f} %")
    assert np.median(err_w) < 0.7 * np.median(err_eq)
    assert np.mean(err_w <= bound_w) >= 0.9


#: The light terms by the gradient alone (as the uncorrected corners' profile states them).
GRADIENT_ONLY = UncertaintyConfig(light_gradient_tilt_gain=0.35, edge_shift_tilt_gain=0.0)


def test_uneven_light_widens_the_bound() -> None:
    """With the light stated by its gradient: edge shifts that vary smoothly across the cap (a
    spotlight) widen the bounds; the same shift on every tag (even light: the cell fit removed it)
    or no cell fit leaves them as they were."""
    T = _truth(10.0)
    exact = _exact_corners(T)
    rng = np.random.default_rng(4)
    corners = {i: c + rng.normal(0.0, 0.05, (4, 2)) for i, c in exact.items()}
    x = np.array([c[:, 0].mean() for c in corners.values()])
    ramp = 0.2 + 0.6 * (x - x.min()) / np.ptp(x)

    def bounds(shifts, config=PoseConfig(uncertainty=GRADIENT_ONLY)):  # noqa: ANN001, ANN202
        dets = [TagDetection(i, c, edge_shift_px=s) for (i, c), s in zip(corners.items(), shifts)]
        p = estimate_cap_pose(dets, MODEL, CAM, config).pose
        assert p is not None
        return p.rot_err95_deg, p.trans_err95_mm

    none = bounds([float("nan")] * len(corners))
    even = bounds([0.4] * len(corners))
    uneven = bounds(ramp)
    assert even == pytest.approx(none, rel=1e-9)
    # With these gains this 0.6 px ramp widens both bounds well beyond 1.3x; the term grows
    # with the gains.
    assert uneven[0] > 1.3 * none[0] and uneven[1] > 1.3 * none[1]
    stronger = bounds(ramp, PoseConfig(uncertainty=UncertaintyConfig(light_gradient_gain=0.6,
                                                                     light_gradient_tilt_gain=0.7)))
    assert stronger[0] > uneven[0] and stronger[1] > uneven[1]


def _tilt_stated_px2(terms: dict, seen: dict, config: UncertaintyConfig) -> float:
    """The variance the covariance states along the tilt mode's translation, in px^2 of the mode."""
    cov = sum(uncertainty_sources(terms, seen, config).values())[:3, :3]
    a2 = terms["tilt"][:3, :3]
    return float(np.sum(a2 * cov)) / float(np.trace(a2)) ** 2


def test_edge_shift_tilt_is_counted_beyond_the_other_terms() -> None:
    """The light's tilt at sigma gain x |mean edge shift| (px edge-on) is stated along the tilt
    mode only where the other terms state less there: along it the covariance states the larger
    of the two, never their sum, and a frame without edge shifts gets none."""
    T = _truth(10.0)
    rng = np.random.default_rng(5)
    corners = {i: c + rng.normal(0.0, 0.05, (4, 2)) for i, c in _exact_corners(T).items()}
    obs = TagObservations.of({i: CAM.undistort_px(c) for i, c in corners.items()}, MODEL, CAM.K)
    terms, seen = uncertainty_terms(obs, T, edge_shift_px=np.full(len(obs), 0.6))
    assert seen["edge_shift_mean"] == pytest.approx(0.6, rel=1e-12)
    off = UncertaintyConfig(edge_shift_tilt_gain=0.0)
    others = _tilt_stated_px2(terms, seen, off)
    assert others > 0.0
    for gain in (0.1 * np.sqrt(others) / 0.6, 10.0 * np.sqrt(others) / 0.6):
        cfg = UncertaintyConfig(edge_shift_tilt_gain=gain)
        sigma2 = (gain * 0.6) ** 2
        assert _tilt_stated_px2(terms, seen, cfg) == pytest.approx(max(sigma2, others), rel=1e-9)
        part = uncertainty_sources(terms, seen, cfg)["light_shift_tilt"]
        np.testing.assert_allclose(part, max(sigma2 - others, 0.0) * terms["tilt"], rtol=1e-9, atol=1e-30)
    # The sign of the shift is immaterial; no edge shifts, no term.
    neg = {**seen, "edge_shift_mean": -0.6}
    cfg = UncertaintyConfig(edge_shift_tilt_gain=1.0)
    np.testing.assert_allclose(combine_uncertainty(terms, neg, cfg), combine_uncertainty(terms, seen, cfg),
                               rtol=1e-12)
    bare, bare_seen = uncertainty_terms(obs, T)
    assert bare_seen["edge_shift_mean"] == 0.0
    np.testing.assert_allclose(combine_uncertainty(bare, bare_seen, cfg), combine_uncertainty(bare, bare_seen, off),
                               rtol=1e-12)


def _with_common_offset(corners: dict[int, np.ndarray], offset_px: float, noise_px: float,
                        rng: np.random.Generator) -> dict[int, np.ndarray]:
    """Every tag's corners moved ``offset_px`` outward (negative: inward) and independent noise."""
    out = {}
    for i, c in corners.items():
        radial = c - c.mean(axis=0)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        out[i] = c + offset_px * radial + rng.normal(0.0, noise_px, (4, 2))
    return out


def test_shared_bias_term_is_the_common_radial_mode() -> None:
    """The shared bias part is the common radial mode at sigma gain x ratio (the ratio from the
    frame's own residuals), it is almost all depth, and it scales with the gain squared."""
    T = _truth(15.0)
    rng = np.random.default_rng(21)
    corners = _with_common_offset(_exact_corners(T), 0.0, 0.08, rng)
    obs = TagObservations.of({i: CAM.undistort_px(c) for i, c in corners.items()}, MODEL, CAM.K)
    terms, seen = uncertainty_terms(obs, T)
    # Corner noise 0.08 px per coordinate: tag_noise_px ~ sqrt(2) x the residual rms (< 0.08:
    # the fit takes a share), over cells of the 540p scene's ~40 px tags.
    assert 0.001 < seen["shared_bias_ratio"] < 0.03
    for gain in (0.6, 1.2):
        part = uncertainty_sources(terms, seen, UncertaintyConfig(shared_bias_gain=gain))["shared_bias"]
        np.testing.assert_allclose(part, (gain * seen["shared_bias_ratio"]) ** 2 * terms["bias_common"],
                                   rtol=1e-12)
    unit = terms["bias_common"][:3, :3]
    los = T.translation_m / np.linalg.norm(T.translation_m)
    assert los @ unit @ los > 0.9 * np.trace(unit)  # the depth takes a common radial offset


def _offset_coverage(T: Transform, n: int, draw: Callable[[], dict[int, np.ndarray]],
                     config: PoseConfig | None, baseline: PoseConfig) -> tuple[float, float, float]:
    """Over ``n`` frames of corners from ``draw``: the translation bounds' coverage of the errors
    with ``config`` (None: the defaults) and with ``baseline``, and the former's sharpness."""
    err, bound, bound0 = [], [], []
    for _ in range(n):
        corners = draw()
        p = _pose(corners, config)
        err.append(1e3 * np.linalg.norm(p.T_cam_cap.translation_m - T.translation_m))
        bound.append(p.trans_err95_mm)
        bound0.append(_pose(corners, baseline).trans_err95_mm)
    err, bound, bound0 = map(np.array, (err, bound, bound0))
    return (float(np.mean(err <= bound)), float(np.mean(err <= bound0)),
            float(np.median(bound) / np.median(err)))


def test_shared_bias_covers_a_drawn_common_offset() -> None:
    """Frames whose tags share a radial corner offset drawn at the sigma the term states (gain x
    the ratio of a frame without the offset) besides independent noise: with the term the
    translation bounds cover at least 95 % of the errors and stay sharp (the offset also raises
    the residuals a little, and with them the ratio), without it they cover far fewer."""
    T = _truth(10.0)
    exact = _exact_corners(T)
    rng = np.random.default_rng(33)
    noise_px, gain = 0.06, 4.0
    # The measured common offset unused: the ratio term alone.
    with_term = PoseConfig(uncertainty=UncertaintyConfig(shared_bias_gain=gain, common_offset_gain=0.0))
    without = PoseConfig(uncertainty=UncertaintyConfig(shared_bias_gain=0.0, common_offset_gain=0.0))
    obs = TagObservations.of({i: CAM.undistort_px(c) for i, c in
                              _with_common_offset(exact, 0.0, noise_px, rng).items()}, MODEL, CAM.K)
    sigma_px = gain * uncertainty_terms(obs, T)[1]["shared_bias_ratio"]
    cover, cover0, sharpness = _offset_coverage(
        T, 300, lambda: _with_common_offset(exact, rng.normal(0.0, sigma_px), noise_px, rng), with_term, without)
    print(f"\nshared offset sigma {sigma_px:.4f} px: translation coverage {100 * cover:.1f} % "
          f"(sharpness {sharpness:.2f}) with the term, {100 * cover0:.1f} % without")
    assert cover >= 0.95 and sharpness < 4.0
    assert cover0 < 0.75


def test_edge_profile_states_a_shared_offset_the_residuals_show() -> None:
    """Frames whose tags share a radial corner offset of a few hundredths of a px (the size the
    depth errors of path-traced 540p renders imply) besides independent noise: the edge profile
    (the defaults) states it from the residuals (``common_offset_gain``) and its translation bounds
    cover at least 90 % of the errors; with the residual-based terms alone they cover fewer."""
    T = _truth(10.0)
    exact = _exact_corners(T)
    rng = np.random.default_rng(41)
    bare = PoseConfig(uncertainty=UncertaintyConfig(common_offset_gain=0.0))
    cover, cover0, sharpness = _offset_coverage(
        T, 200, lambda: _with_common_offset(exact, rng.choice((-0.05, 0.05)), 0.06, rng), None, bare)
    print(f"\nshared offset 0.05 px: translation coverage {100 * cover:.1f} % (sharpness "
          f"{sharpness:.2f}) with the measured offset, {100 * cover0:.1f} % without")
    assert cover >= 0.9 and sharpness < 4.0
    assert cover0 < cover - 0.1


def test_shared_bias_grows_at_low_resolution() -> None:
    """The same cap, the same corner noise in px, half the focal length (a 540p camera against a
    1080p one): the ratio doubles (cells half as wide) and a common offset moves the depth twice as
    far (tags half as large), so the shared bias part's translation sigma is four times as large."""
    T = _truth(5.0)
    parts = []
    for scale in (1.0, 0.5):
        K = CAM.K.copy()
        K[:2] *= scale
        pts = MODEL.corners_mm.reshape(-1, 3) / 1000.0
        cam = T.apply(pts) @ K.T
        px = (cam[:, :2] / cam[:, 2:3]).reshape(-1, 4, 2)
        rng = np.random.default_rng(5)
        seen_ids = view_angles_deg(MODEL, T) < 70.0
        corners = {int(i): px[k] + rng.normal(0.0, 0.08, (4, 2)) for k, i in enumerate(MODEL.ids)
                   if seen_ids[k]}
        obs = TagObservations.of(corners, MODEL, K)
        terms, seen = uncertainty_terms(obs, T)
        part = uncertainty_sources(terms, seen, UncertaintyConfig(shared_bias_gain=1.0))["shared_bias"]
        parts.append((seen["shared_bias_ratio"], np.sqrt(np.trace(part[:3, :3]))))
    (r_hi, t_hi), (r_lo, t_lo) = parts
    assert r_lo / r_hi == pytest.approx(2.0, rel=0.15)
    assert t_lo / t_hi == pytest.approx(4.0, rel=0.2)


def test_shared_bias_ratio_on_rendered_frames() -> None:
    """On rendered frames (the realistic chain: lens blur, tone curve, noise, JPEG) the ratio the
    pose's residuals give is below a tenth at 540p, and a half to a sixth of that at 1080p for
    the same poses (cells twice as wide, and the same blur in px moves wider edges' corners less)."""
    from ficap_ros.tools.synth import RenderConfig, naturalistic_drive, render
    from ficap_ros.vision.pipeline import FrameProcessor
    from ficap_ros.vision.reprojection import undistorted_corners
    from ficap_ros.vision.uncertainty import tag_noise_px

    ratios = {}
    for res in ("540p", "1080p"):
        scene = default_scene(res)
        drive = naturalistic_drive(90, 30.0, 3, scene)[::30]
        out = []
        for k, d in enumerate(drive):
            frame = render(MODEL, scene.camera, d.T_cam_cap, RenderConfig(lighting="neutral"), seed=k)
            r = FrameProcessor(MODEL).process(frame.image, scene.camera, 0)
            assert r.pose is not None
            groups = undistorted_corners(r.detections, scene.camera)
            used = {i: groups[i][0] for i in r.pose.used_ids}
            obs = TagObservations.of(used, MODEL, scene.camera.K)
            out.append(shared_bias_ratio(obs.image_px, tag_noise_px(obs, r.pose.T_cam_cap)))
        ratios[res] = float(np.median(out))
    print(f"\nshared bias ratio: 540p {ratios['540p']:.4f}, 1080p {ratios['1080p']:.4f}")
    assert 0.003 < ratios["540p"] < 0.05
    assert 1.8 < ratios["540p"] / ratios["1080p"] < 6.0


def test_uncorrected_corners_bound_their_measured_offset() -> None:
    """Corners that keep the tone curve's bias (every tag 0.3 px inward, as OpenCV's sub-pixel
    corners sit): the ``uncorrected`` and ``edge`` profiles use the offset the residuals show and
    their bounds cover the depth error it causes; without the offset's terms they fall short."""
    T = _truth(12.0)
    rng = np.random.default_rng(13)
    configs = {"edge": UncertaintyConfig.for_corners("edge"),
               "uncorrected": UncertaintyConfig.for_corners("uncorrected"),
               "without": UncertaintyConfig(common_offset_gain=0.0, common_offset_se_gain=0.0)}
    misses = dict.fromkeys(configs, 0)
    for _ in range(20):
        corners = _with_common_offset(_exact_corners(T), -0.3, 0.05, rng)
        for name, cfg in configs.items():
            p = _pose(corners, PoseConfig(uncertainty=cfg))
            err = 1e3 * np.linalg.norm(p.T_cam_cap.translation_m - T.translation_m)
            misses[name] += err > p.trans_err95_mm
    assert UncertaintyConfig.for_corners("uncorrected").common_offset_gain == 1.0
    assert misses["uncorrected"] <= 1 and misses["edge"] <= 1 and misses["without"] >= 15

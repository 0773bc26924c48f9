"""Renderer and drive generator: rendered corners are exact, lighting and motion as specified."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import norm

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import TAG_SIDE_MM, CapModel, nominal_model
from ficap_ros.geometry.metrics import angle_deg, rotation_from_ypr_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth import (
    HEAD_CENTRE_M,
    HEAD_SEMI_AXES_M,
    NECK_CENTRE_M,
    NECK_SEMI_AXES_M,
    REALISTIC,
    RenderConfig,
    default_scene,
    naturalistic_drive,
    naturalistic_motion,
    render,
    srgb_to_linear,
    tone_curve,
)

MODEL = nominal_model()
#: An idealised camera (no lens blur, grey levels proportional to light): what the geometry tests
#: need; the realistic chain's corner bias is measured apart (test_naive_peer_is_biased_inward).
IDEAL = RenderConfig(psf_sigma_px=0.0, tone="linear")


def _detect(image: np.ndarray) -> dict[int, np.ndarray]:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params
    )
    corners, ids, _ = detector.detectMarkers(image)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2).astype(np.float64) for c, i in zip(corners, ids.ravel())}


def _view_angles_deg(T_cam_cap: Transform) -> dict[int, float]:
    """Angle between each tag's outward normal and the direction to the camera, deg."""
    normals = T_cam_cap.rotation.apply(MODEL.normals)
    centres = T_cam_cap.apply(MODEL.centres_mm / 1000.0)
    to_cam = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    cos = np.clip(np.einsum("ij,ij->i", normals, to_cam), -1.0, 1.0)
    return {tag_id: float(np.degrees(np.arccos(c))) for tag_id, c in zip(MODEL.ids, cos)}


def _corner_errors(frame, max_view_deg: float = 60.0) -> tuple[np.ndarray, list[int], list[int]]:
    """Signed corner errors (n, 2) of well-seen tags, their ids, and ids wrongly detected."""
    found = _detect(frame.image)
    angles = _view_angles_deg(frame.T_cam_cap)
    wanted = [k for k, v in frame.visible_fraction.items() if v >= 0.99 and angles[k] < max_view_deg]
    wrong = [k for k in found if k not in frame.corners_px]
    missing = [k for k in wanted if k not in found]
    errors = np.concatenate([found[k] - frame.corners_px[k] for k in wanted if k in found])
    return errors, missing, wrong


def test_head_and_neck_lie_inside_every_face() -> None:
    faces = MODEL.face_corners_mm() / 1000.0
    g = np.linspace(0.0, 1.0, 9)
    pts = np.array([f[0] + a * (f[1] - f[0]) + b * (f[3] - f[0]) for f in faces for a in g for b in g])
    for centre, axes in ((HEAD_CENTRE_M, HEAD_SEMI_AXES_M), (NECK_CENTRE_M, NECK_SEMI_AXES_M)):
        r = np.sqrt((((pts - np.array(centre)) / np.array(axes)) ** 2).sum(axis=1))
        assert r.min() > 1.0  # every face point outside the ellipsoid


def test_frontal_1080p_corners_match_truth() -> None:
    scene = default_scene("1080p")
    T = scene.cap_pose(Rotation.identity())
    frame = render(MODEL, scene.camera, T, IDEAL, seed=1)
    assert frame.image.shape == (1080, 1920) and frame.image.dtype == np.uint8
    errors, missing, wrong = _corner_errors(frame)
    assert not missing and not wrong
    assert len(errors) >= 4 * 10
    dist = np.linalg.norm(errors, axis=1)
    assert dist.mean() < 0.3
    assert np.all(np.abs(errors.mean(axis=0)) < 0.1)  # no half-pixel convention slip


def test_distorted_camera_corners_match_truth() -> None:
    base = default_scene("540p").camera
    camera = CameraModel(base.width_px, base.height_px, base.K, [-0.28, 0.09, 0.001, -0.0005, 0.0],
                         "plumb_bob")
    scene = default_scene("540p")
    T = scene.cap_pose(rotation_from_ypr_deg(15.0, -5.0, 2.0))
    frame = render(MODEL, camera, T, IDEAL, seed=2)
    assert frame.image.shape == (540, 960)
    ideal = T.apply(MODEL.corners_of(11) / 1000.0)
    assert np.allclose(frame.corners_px[11], camera.project(ideal))
    # The distortion is strong enough to matter: the pinhole projection is pixels away.
    pinhole = CameraModel(base.width_px, base.height_px, base.K, [], "none")
    shift = np.abs(np.array([frame.corners_px[k] - pinhole.project(T.apply(MODEL.corners_of(k) / 1e3))
                             for k in frame.corners_px])).max()
    assert shift > 3.0
    errors, missing, wrong = _corner_errors(frame)
    assert not missing and not wrong and len(errors) >= 4 * 6
    assert np.linalg.norm(errors, axis=1).mean() < 0.3
    assert np.all(np.abs(errors.mean(axis=0)) < 0.1)


def test_back_faces_never_reported() -> None:
    scene = default_scene("540p")
    for yaw in (-80.0, 0.0, 55.0):
        T = scene.cap_pose(rotation_from_ypr_deg(yaw, -10.0, 0.0))
        frame = render(MODEL, scene.camera, T, RenderConfig(noise=False), seed=0)
        normals = T.rotation.apply(MODEL.normals)
        centres = T.apply(MODEL.centres_mm / 1000.0)
        facing = {t for t, n, c in zip(MODEL.ids, normals, centres) if n @ c < 0}
        assert set(frame.corners_px) == facing == set(frame.visible_fraction)
        assert len(facing) >= 5
        if abs(yaw) > 45:
            assert len(facing) < len(MODEL) - 5
        assert not set(_detect(frame.image)) - facing


def test_occluder_hides_faces_at_large_yaw() -> None:
    scene = default_scene("540p")
    T = scene.cap_pose(rotation_from_ypr_deg(80.0, 0.0, 0.0))
    plain = RenderConfig(noise=False, head=False)
    free = render(MODEL, scene.camera, T, plain).visible_fraction
    # The default head sits inside the cap: it never covers a front-facing face here.
    default = render(MODEL, scene.camera, T, RenderConfig(noise=False)).visible_fraction
    assert all(default[k] >= free[k] - 0.02 for k in free)
    # A bigger head (thick hair poking past the cap rim) hides faces through the depth test.
    big = RenderConfig(noise=False, head_centre_m=(0.0, 0.0, -0.03),
                       head_semi_axes_m=(0.12, 0.1, 0.13))
    frame = render(MODEL, scene.camera, T, big)
    hidden = [k for k in free if free[k] > 0.5 and frame.visible_fraction[k] < 0.2]
    assert hidden
    assert not set(hidden) & set(_detect(frame.image))


def test_lighting_modes_differ_as_specified() -> None:
    scene = default_scene("540p")
    T = scene.cap_pose(rotation_from_ypr_deg(10.0, 0.0, 0.0))
    images = {(m, seed): render(MODEL, scene.camera, T, RenderConfig(lighting=m, **REALISTIC), seed=seed).image
              for m in ("neutral", "high", "low") for seed in (4, 5)}
    clean = render(MODEL, scene.camera, T, RenderConfig(noise=False, **REALISTIC))
    cap = np.zeros((540, 960), bool)
    for c in clean.corners_px.values():
        mask = np.zeros((540, 960), np.uint8)
        cv2.fillConvexPoly(mask, np.round(c).astype(np.int32), 1)
        cap |= mask > 0
    white = cap & (clean.image > 150)  # the white cells of the tags
    assert white.sum() > 2000
    sat = {m: float(np.mean(images[(m, 4)][white] >= 254)) for m in ("neutral", "high", "low")}
    # High light really saturates (the paper's "highly saturated images"); the others never clip.
    assert sat["high"] > 0.3 and sat["neutral"] == 0.0 and sat["low"] == 0.0
    # Neutral through sRGB: white paper ~200-215, black ink (5 % of white, plus flare) ~50.
    neutral = images[("neutral", 4)]
    assert 195 <= np.percentile(neutral[cap], 95) <= 232
    assert 35 <= np.percentile(neutral[cap], 5) <= 70
    # Low: dark, and noisy with its gain: the white cells' signal-to-noise ratio (noise from two
    # seeds) is many times worse than neutral's.
    low = images[("low", 4)]
    assert low[cap].mean() < 0.5 * neutral[cap].mean() and np.percentile(low[cap], 99) <= 110

    def snr(m: str) -> float:
        a, b = (images[(m, seed)][white].astype(np.float64) for seed in (4, 5))
        return float(a.mean() / (np.std(a - b) / np.sqrt(2.0)))

    assert snr("low") < 0.3 * snr("neutral")
    # Same seed, same image; another seed, other noise (and other spotlights).
    again = render(MODEL, scene.camera, T, RenderConfig(lighting="high", **REALISTIC), seed=4).image
    assert np.array_equal(again, images[("high", 4)])
    for m in ("neutral", "low", "high"):
        assert not np.array_equal(images[(m, 4)], images[(m, 5)])


@pytest.mark.parametrize("tone, gamma", [("srgb", 2.2), ("gamma", 1.8), ("gamma", 2.2), ("filmic", 2.2),
                                         ("linear", 2.2)])
def test_tone_curves_monotone_and_fix_black_and_white(tone: str, gamma: float) -> None:
    v = np.linspace(0.0, 1.0, 100_001)
    y = tone_curve(v, tone, gamma)
    assert y[0] == 0.0 and abs(y[-1] - 1.0) < 1e-12
    assert np.all(np.diff(y) > 0.0)  # strictly increasing
    assert np.all(tone_curve(np.array([-0.5, 2.0]), tone, gamma) == [0.0, 1.0])  # clipped
    if tone != "linear":
        assert tone_curve(np.array([0.18]), tone, gamma)[0] > 0.18  # lifts the mid-tones
    if tone == "srgb":
        assert np.allclose(srgb_to_linear(y), v, atol=1e-9)
        assert abs(tone_curve(np.array([0.5]), "srgb")[0] - 0.735357) < 1e-5  # IEC 61966-2-1
    if tone == "filmic":
        # An S-curve on the sRGB value: flatter than sRGB in the toe and the shoulder.
        s = tone_curve(v, "srgb")
        assert np.all(y[1:5000] < s[1:5000]) and np.all(y[-5000:-1] > s[-5000:-1])


def _frontal_square(z_m: float) -> tuple[CapModel, Transform]:
    """One 32 mm tag facing the camera squarely at depth ``z_m``, left edge off the pixel grid."""
    h = TAG_SIDE_MM / 2
    corners = np.array([[[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]]])
    return CapModel((0,), corners), Transform(Rotation.identity(), np.array([0.0013, 0.0, z_m]))


def _edge_crossing_px(image: np.ndarray, x_edge: float, rows: slice, level: float) -> float:
    """Mean x (OpenCV pixel convention) where rows go from above ``level`` (white quiet zone, left)
    to below it (black border), searched near ``x_edge``."""
    xs = []
    x0 = int(np.floor(x_edge)) - 8
    for row in image[rows, x0:x0 + 17].astype(np.float64):
        k = int(np.flatnonzero((row[:-1] >= level) & (row[1:] < level))[0])
        xs.append(x0 + k + (row[k] - level) / (row[k] - row[k + 1]))
    return float(np.mean(xs))


@pytest.mark.parametrize("tone, gamma", [("srgb", 2.2), ("gamma", 1.8), ("linear", 2.2)])
def test_psf_acts_in_linear_light_before_the_tone_curve(tone: str, gamma: float) -> None:
    """A Gaussian-blurred black/white edge: the 8-bit 50 % crossing sits where theory puts it.

    In linear light the blurred step is w - (w - b) Phi(d / sigma) at distance d into the black;
    the tone curve's mid-level m = (T(w) + T(b)) / 2 is the linear level T^-1(m), reached at
    d = sigma Phi^-1((w - T^-1(m)) / (w - b)): on the black side for sRGB and gamma, on the edge
    for a linear camera. sigma includes the pixel's own box (variance 1/12 px^2).
    """
    model, T = _frontal_square(0.2)
    camera = default_scene("540p").camera
    sigma = 2.0
    cfg = RenderConfig(psf_sigma_px=sigma, tone=tone, gamma=gamma, noise=False, head=False,
                       background=False)
    frame = render(model, camera, T, cfg)
    c = frame.corners_px[0]
    x_edge = float(c[[0, 3], 0].mean())  # the left side is vertical: TL and BL share x
    assert abs(c[0, 0] - c[3, 0]) < 1e-9 and (x_edge % 1.0) not in (0.0, 0.5)
    cell = (c[3, 1] - c[0, 1]) / 8
    rows = slice(int(c[0, 1] + 2 * cell), int(c[3, 1] - 2 * cell))
    img = frame.image.astype(np.float64)
    # Plateaus: the white quiet zone (half a cell out) and the black border (half a cell in).
    w8 = np.median(img[rows, int(round(x_edge - 0.5 * cell))])
    b8 = np.median(img[rows, int(round(x_edge + 0.5 * cell))])
    level = 0.5 * (w8 + b8)
    inverse = {"srgb": lambda y: srgb_to_linear(y), "gamma": lambda y: y ** gamma, "linear": lambda y: y}[tone]
    w, b, lm = (float(inverse(np.array(v / 255.0))) for v in (w8, b8, level))
    sigma_eff = np.hypot(sigma, np.sqrt(1.0 / 12.0))
    expected = sigma_eff * norm.ppf((w - lm) / (w - b))
    measured = _edge_crossing_px(frame.image, x_edge, rows, level) - x_edge
    assert abs(measured - expected) < 0.06, (measured, expected)
    if tone == "linear":
        assert abs(measured) < 0.06
    else:
        assert measured > 0.5  # toward the black: the bias real cameras show


def test_motion_blur_truth_is_mid_exposure() -> None:
    """A tag sliding sideways at constant speed: the frame's truth is the pose at mid-exposure, the
    pose is sampled over the whole exposure, and in linear light the smeared edge's 50 % point
    stays at the mid-exposure edge while its width grows with the travel."""
    model, T0 = _frontal_square(0.2)
    camera = default_scene("540p").camera
    speed_m_s = 0.3
    exposure_ms = 8.0
    asked: list[float] = []

    def pose_at(dt_s: float) -> Transform:
        asked.append(dt_s)
        return Transform(T0.rotation, T0.translation_m + [speed_m_s * dt_s, 0.0, 0.0])

    base = RenderConfig(tone="linear", psf_sigma_px=0.5, noise=False, head=False, background=False)
    moving = render(model, camera, pose_at, replace(base, exposure_ms=exposure_ms))
    still = render(model, camera, T0, replace(base, exposure_ms=exposure_ms))
    np.testing.assert_allclose(moving.corners_px[0], camera.project(T0.apply(model.corners_mm[0] / 1000.0)))
    np.testing.assert_array_equal(moving.corners_px[0], still.corners_px[0])
    assert moving.T_cam_cap is not None and np.allclose(moving.T_cam_cap.translation_m, T0.translation_m)
    travel_px = camera.K[0, 0] * speed_m_s * exposure_ms / 1000.0 / T0.translation_m[2]
    assert travel_px > 5.0
    times = np.array(sorted(set(asked)))
    assert len(times) % 2 == 1 and len(times) >= 2 * travel_px - 1  # <= 0.5 px between sub-frames
    half = exposure_ms / 2000.0
    assert -half <= times.min() < -0.9 * half and half >= times.max() > 0.9 * half
    np.testing.assert_allclose(times + times[::-1], 0.0, atol=1e-15)  # symmetric about 0
    c = still.corners_px[0]
    x_edge = float(c[[0, 3], 0].mean())
    cell = (c[3, 1] - c[0, 1]) / 8
    rows = slice(int(c[0, 1] + 2 * cell), int(c[3, 1] - 2 * cell))
    for frame in (moving, still):
        img = frame.image.astype(np.float64)
        w8 = np.median(img[rows, int(round(x_edge - 0.55 * cell))])
        b8 = np.median(img[rows, int(round(x_edge + 0.55 * cell))])
        assert abs(_edge_crossing_px(frame.image, x_edge, rows, 0.5 * (w8 + b8)) - x_edge) < 0.08
    # The smear: 10-90 % width of a box of length L convolved with the 0.5 px PSF is ~0.8 L.
    def width(frame) -> float:
        prof = frame.image[rows].astype(np.float64).mean(axis=0)
        x0 = int(x_edge) - 12
        seg = prof[x0:x0 + 25]
        lo, hi = seg.min(), seg.max()
        return float(np.sum((seg < lo + 0.9 * (hi - lo)) & (seg > lo + 0.1 * (hi - lo))))

    assert width(still) <= 2 and abs(width(moving) - 0.8 * travel_px) <= 1.5
    # The default is still frames: a Transform pose is one sub-frame, whatever the exposure.
    assert np.array_equal(still.image, render(model, camera, T0, base).image)


def test_drive_motion_matches_frames() -> None:
    scene = default_scene("540p")
    drive = naturalistic_drive(400, fps=30.0, seed=5, scene=scene)
    motion = naturalistic_motion(400 / 30.0, seed=5, scene=scene)
    for f in drive[::37]:
        T = motion.around(f.stamp_ns / 1e9)(0.0)
        assert angle_deg(T.rotation, f.T_cam_cap.rotation) < 1e-9
        assert np.allclose(T.translation_m, f.T_cam_cap.translation_m, atol=1e-12)
    # Between frames the motion is continuous: half a frame later lies between the two frames.
    a, b = drive[200], drive[201]
    mid = motion.T_cam_cap_at((a.stamp_ns + b.stamp_ns) / 2e9)
    gap = angle_deg(a.T_cam_cap.rotation, b.T_cam_cap.rotation)
    assert angle_deg(mid.rotation, a.T_cam_cap.rotation) <= gap + 1e-9
    assert angle_deg(mid.rotation, b.T_cam_cap.rotation) <= gap + 1e-9


def test_render_config_rejects_bad_knobs() -> None:
    for bad in (dict(psf_sigma_px=float("nan")), dict(psf_sigma_px=-0.1), dict(exposure_ms=0.0),
                dict(exposure_ms=float("inf")), dict(gain=-1.0), dict(gamma=0.0), dict(tone="log"),
                dict(defocus_radius_px=-1.0), dict(read_noise_e=float("nan"))):
        with pytest.raises(ConfigError):
            RenderConfig(**bad)
    assert RenderConfig(**REALISTIC).psf_sigma_for(1080) == pytest.approx(0.7)
    assert RenderConfig(**REALISTIC).psf_sigma_for(540) == pytest.approx(0.7 * np.sqrt(0.5))
    # Shutter-priority auto-exposure: half the exposure, twice the gain; never below gain 1.
    e, g = RenderConfig(lighting="low").exposure_and_gain()
    assert g > 1.0
    assert RenderConfig(lighting="low", exposure_ms=e / 2).exposure_and_gain() == pytest.approx((e / 2, 2 * g))
    assert RenderConfig(lighting="low", exposure_ms=e * 100).exposure_and_gain() == pytest.approx((e * 100, 1.0))


def test_cli_rejects_bad_camera_knobs(tmp_path, capsys) -> None:
    from ficap_ros.cli.main import main

    # Bad arguments: exit 2 with argparse's line naming the flag, as for every verb's numbers.
    for flag, value in (("--psf-sigma-px", "nan"), ("--psf-sigma-px", "-1"), ("--exposure-ms", "inf"),
                        ("--exposure-ms", "0"), ("--gamma", "-2"), ("--gain", "nan"), ("--defocus-px", "-0.5"),
                        ("--fps", "0"), ("--fps", "nan"), ("--frontal-s", "-1"), ("--jpeg-quality", "101"),
                        ("--jpeg-quality", "x")):
        with pytest.raises(SystemExit) as exc:
            main(["synth", "--out", str(tmp_path / "bag"), "--frames", "1", flag, value, "--quiet"])
        assert exc.value.code == 2, (flag, value)
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith(f"ficap synth: error: argument {flag}:"), err
        assert not (tmp_path / "bag").exists()


def test_naive_peer_is_biased_inward_on_default_synth_frames(tmp_path) -> None:
    """Issue 10: default ``ficap synth`` frames show what real cameras do to corners: the naive
    peer's (OpenCV sub-pixel) corners sit >= 0.2 px toward the tag centre."""
    from ficap_ros.cli.main import main
    from ficap_ros.geometry.metrics import corner_errors_px
    from ficap_ros.io.sources import decode_raw, open_frames
    from ficap_ros.vision.detector import DetectorConfig, TagDetector
    from ficap_ros.vision.tracking import view_angles_deg

    seed, n = 11, 3
    bag = tmp_path / "bag"
    assert main(["synth", "--out", str(bag), "--frames", str(n), "--fps", "2", "--frontal-s", "0",
                 "--seed", str(seed), "--quiet"]) == 0
    images = [decode_raw(raw) for raw in open_frames(bag).raw_frames()]
    assert len(images) == n
    scene = default_scene("540p")
    peer = TagDetector(DetectorConfig(corner_refine="subpix"))
    radial = []
    for f, image in zip(naturalistic_drive(n, fps=2.0, seed=seed, scene=scene, frontal_s=0.0), images):
        # The truth of the bag's frame (same drive, same default chain and seeds as `ficap synth`).
        truth = render(MODEL, scene.camera, f.T_cam_cap, RenderConfig(background_seed=seed, **REALISTIC),
                       seed=seed * 100003 + f.index)
        ok, jpg = cv2.imencode(".jpg", truth.image, [cv2.IMWRITE_JPEG_QUALITY, 95])
        assert np.array_equal(cv2.imdecode(jpg, cv2.IMREAD_UNCHANGED), image)
        angles = dict(zip(MODEL.ids, view_angles_deg(MODEL, f.T_cam_cap)))
        clean = [t for t in truth.visible_ids(0.999) if angles[t] <= 70.0]
        found = {d.tag_id: d.corners_px for d in peer.detect(image)}
        ids = [t for t in clean if t in found]
        assert len(ids) >= 6
        _, r = corner_errors_px(np.array([found[t] for t in ids]), np.array([truth.corners_px[t] for t in ids]))
        radial.append(r.ravel())
    mean_radial = float(np.concatenate(radial).mean())
    print(f"naive peer mean radial offset {mean_radial:+.3f} px")
    assert mean_radial <= -0.2


def test_color_blur_jpeg_options() -> None:
    scene = default_scene((480, 270))
    T = scene.cap_pose(Rotation.identity())
    frame = render(MODEL, scene.camera, T, RenderConfig(color=True, psf_sigma_px=0.8, jpeg_quality=80))
    assert frame.image.shape == (270, 480, 3) and frame.image.dtype == np.uint8
    with pytest.raises(ConfigError):
        RenderConfig(lighting="sunset")


def test_drive_motion_is_naturalistic_and_consistent() -> None:
    scene = default_scene("540p")
    fps = 30.0
    drive = naturalistic_drive(int(60 * fps), fps=fps, seed=3, scene=scene, frontal_s=3.0)
    ypr = np.array([f.ypr_deg for f in drive])
    assert np.all(np.abs(ypr[:, 0]) <= 62.0)
    assert ypr[:, 0].max() > 40.0 and ypr[:, 0].min() < -40.0
    assert np.any(ypr[:, 1] > 15.0)  # instrument cluster: below, pitch positive nose down (REP-103)
    start = [f for f in drive if f.frontal]
    assert len(start) == int(3.0 * fps)
    assert max(angle_deg(Rotation.identity(), f.R_frontal_head) for f in start) < 1.0
    assert [f.index for f in drive] == list(range(len(drive)))
    assert drive[31].stamp_ns == round(31 * 1e9 / fps)
    # Smooth: no frame-to-frame jump above what 400 deg/s allows.
    steps = [angle_deg(a.R_frontal_head, b.R_frontal_head) for a, b in zip(drive, drive[1:])]
    assert max(steps) < 400.0 / fps
    for f in drive[::97]:
        expected = scene.R_cam_frontal * f.R_frontal_head * scene.R_cap_head.inv()
        assert angle_deg(expected, f.T_cam_cap.rotation) < 1e-9
        back = scene.R_cam_frontal.inv() * f.T_cam_cap.rotation * scene.R_cap_head
        assert angle_deg(back, f.R_frontal_head) < 1e-9
        assert np.allclose(rotation_from_ypr_deg(*f.ypr_deg).as_matrix(), f.R_frontal_head.as_matrix())
        # The head turns about the neck pivot (plus a lean of at most a few cm).
        pivot_to_cap = f.T_cam_cap.translation_m - scene.p_cam_neck_m
        turned = scene.R_cam_frontal.apply(f.R_frontal_head.apply(np.array(scene.neck_to_cap_m)))
        assert np.linalg.norm(pivot_to_cap - turned) < 0.03
    again = naturalistic_drive(100, fps=fps, seed=3, scene=scene)
    assert all(np.array_equal(a.ypr_deg, b.ypr_deg) for a, b in zip(again, drive))


def test_default_scene_tag_size() -> None:
    scene = default_scene("540p")
    frame = render(MODEL, scene.camera, scene.cap_pose(Rotation.identity()), RenderConfig())
    c = frame.corners_px[11]
    side = np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1))
    assert 55.0 <= side <= 65.0


@pytest.mark.parametrize("lighting", ["neutral", "low"])
def test_lamp_at_the_camera_lights_an_oblique_face_unevenly(lighting: str) -> None:
    """Neutral light is mostly a lamp beside the camera: each point of a face gets
    cos(incidence) / r^2 of it (metered at the cap's distance), so a face seen at 60 deg is
    brighter on its nearer side. Measured in linear light (no PSF, no noise) in the middle of the
    white quiet zone on both sides, against the geometry computed here; ``low`` light (one distant
    source) lights a face evenly."""
    from ficap_ros.tools.synth.lighting import LIGHTS

    h = TAG_SIDE_MM / 2
    corners = np.array([[[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]]])
    model = CapModel((0,), corners)
    # Facing the camera (the model's outward normal is -z), turned 60 deg about the camera's y axis.
    T = Transform(Rotation.from_euler("y", 60.0, degrees=True), np.array([0.0, 0.0, 0.6]))
    camera = default_scene("1080p").camera
    gain = 1.0 if lighting == "neutral" else 40.0  # low light's white paper at ~40 % (8 bits)
    cfg = RenderConfig(lighting=lighting, psf_sigma_px=0.0, tone="linear", noise=False, head=False,
                       background=False, gain=gain)
    frame = render(model, camera, T, cfg)
    assert frame.visible_ids() == [0]
    light = LIGHTS[lighting]
    normal = T.rotation.apply(model.normals[0])
    assert normal[2] < 0.0  # facing the camera
    to_light = np.asarray(light.toward_light_cam) / np.linalg.norm(light.toward_light_cam)
    r_cap = float(np.linalg.norm(T.translation_m))
    levels, expected = [], []
    for x_mm in (-18.0, 18.0):  # the middle of the quiet zone (16-20 mm from the centre), both sides
        pts_mm = np.array([[x_mm, y, 0.0] for y in np.linspace(-6.0, 6.0, 7)])
        P = T.apply(pts_mm / 1000.0)
        uv = camera.project(P).astype(np.float32)
        got = cv2.remap(frame.image.astype(np.float32), uv[:, 0:1], uv[:, 1:2], cv2.INTER_LINEAR)
        levels.append(float(np.mean(got)) / 255.0)
        dist = np.linalg.norm(P, axis=1)
        cos_inc = np.abs(P @ normal) / dist
        irradiance = (light.ambient + light.diffuse * max(0.0, float(normal @ to_light))
                      + light.camera_lamp * cos_inc * (r_cap / dist) ** 2)
        expected.append(gain * (float(np.mean(irradiance)) + light.flare))
    near, far = (0, 1) if np.linalg.norm(T.apply(np.array([-0.018, 0, 0]))) < 0.6 else (1, 0)
    assert np.allclose(levels, expected, rtol=0.01, atol=1.5 / 255), (levels, expected)
    ratio = levels[near] / levels[far]
    if lighting == "neutral":
        assert 1.05 < ratio < 1.2, ratio  # ~1.1: 30 mm nearer at 0.6 m, met less obliquely
    else:
        assert abs(ratio - 1.0) < 0.02, ratio

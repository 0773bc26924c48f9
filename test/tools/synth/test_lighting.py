"""ficap_ros.tools.synth.lighting: the three modes' levels, noise and saturation as specified, the
lamp at the camera lighting an oblique face unevenly, and a face's irradiance by its formula."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from synth_frames import MODEL

from ficap_ros.geometry.cap_model import TAG_SIDE_MM, CapModel
from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth import REALISTIC, RenderConfig, default_scene, render
from ficap_ros.tools.synth.lighting import LIGHTINGS, LIGHTS, irradiance


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


def test_irradiance_is_ambient_plus_diffuse_by_the_cosine() -> None:
    """A face turned to the light gets ambient + diffuse, one turned away or edge-on ambient only,
    one at 60 deg ambient + diffuse / 2."""
    assert LIGHTINGS == tuple(LIGHTS)
    for light in LIGHTS.values():
        to_light = np.asarray(light.toward_light_cam) / np.linalg.norm(light.toward_light_cam)
        edge_on = np.cross(to_light, [0.0, 0.0, 1.0])
        edge_on /= np.linalg.norm(edge_on)
        at_60 = 0.5 * to_light + np.sqrt(0.75) * edge_on
        got = irradiance(light, np.array([to_light, -to_light, edge_on, at_60]))
        np.testing.assert_allclose(got, [light.ambient + light.diffuse, light.ambient, light.ambient,
                                         light.ambient + 0.5 * light.diffuse], rtol=1e-12)


def test_spotlights_only_add_light_and_follow_their_seed() -> None:
    from ficap_ros.tools.synth.lighting import spotlights

    k = default_scene((320, 180)).camera.K
    faces = np.array([[[x, y, 0.5] for x, y in ((-0.02, -0.02), (0.02, -0.02), (0.02, 0.02),
                                                 (-0.02, 0.02))]])
    base = np.full((180, 320), 0.4, np.float32)
    lit = [base.copy() for _ in range(3)]
    for img, seed in zip(lit, (1, 1, 2)):
        spotlights(img, faces, k, np.random.default_rng(seed))
    assert (lit[0] >= base).all() and lit[0].max() > 0.8  # a gain >= 1 plus glare >= 0
    np.testing.assert_array_equal(lit[0], lit[1])
    assert np.abs(lit[0] - lit[2]).max() > 0.01

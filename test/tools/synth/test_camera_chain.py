"""ficap_ros.tools.synth.camera_chain: the lens blurs in linear light before the tone curve (a
blurred edge's 8-bit crossing where theory puts it), the PSF keeps the light, the sensor's code and
the tone curve's lookup table, the JPEG round trip."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm
from synth_frames import edge_crossing_px, frontal_square

from ficap_ros.tools.synth import RenderConfig, default_scene, render, srgb_to_linear


@pytest.mark.parametrize("tone, gamma", [("srgb", 2.2), ("gamma", 1.8), ("linear", 2.2)])
def test_psf_acts_in_linear_light_before_the_tone_curve(tone: str, gamma: float) -> None:
    """A Gaussian-blurred black/white edge: the 8-bit 50 % crossing sits where theory puts it.

    In linear light the blurred step is w - (w - b) Phi(d / sigma) at distance d into the black;
    the tone curve's mid-level m = (T(w) + T(b)) / 2 is the linear level T^-1(m), reached at
    d = sigma Phi^-1((w - T^-1(m)) / (w - b)): on the black side for sRGB and gamma, on the edge
    for a linear camera. sigma includes the pixel's own box (variance 1/12 px^2).
    """
    model, T = frontal_square(0.2)
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
    measured = edge_crossing_px(frame.image, x_edge, rows, level) - x_edge
    assert abs(measured - expected) < 0.06, (measured, expected)
    if tone == "linear":
        assert abs(measured) < 0.06
    else:
        assert measured > 0.5  # toward the black: the bias real cameras show


def _second_moment_px2(image: np.ndarray) -> tuple[float, float, float]:
    """(sum, variance along x, variance along y) of an image read as a distribution, px^2."""
    total = float(image.sum())
    ys, xs = np.indices(image.shape, dtype=np.float64)
    cx, cy = float((xs * image).sum() / total), float((ys * image).sum() / total)
    return (total, float(((xs - cx) ** 2 * image).sum() / total),
            float(((ys - cy) ** 2 * image).sum() / total))


@pytest.mark.parametrize("sigma_px, radius_px", [(1.5, 0.0), (0.0, 4.0), (1.0, 3.0)])
def test_lens_psf_keeps_the_light_and_spreads_it_by_its_kernels(sigma_px: float,
                                                                 radius_px: float) -> None:
    """A point of light: the blur keeps its energy, and its variance is the Gaussian's sigma^2 plus
    the defocus disc's R^2 / 4 (a uniform disc's variance along an axis), per axis."""
    from ficap_ros.tools.synth.camera_chain import lens_psf

    point = np.zeros((61, 61), np.float32)
    point[30, 30] = 1.0
    out = lens_psf(point.copy(), sigma_px, radius_px)
    total, var_x, var_y = _second_moment_px2(out.astype(np.float64))
    assert total == pytest.approx(1.0, abs=1e-5)
    expected = sigma_px ** 2 + radius_px ** 2 / 4.0
    assert var_x == pytest.approx(expected, rel=0.05) and var_y == pytest.approx(expected, rel=0.05)
    assert lens_psf(point.copy(), 0.0, 0.0)[30, 30] == 1.0  # no lens: untouched


def test_sensor_code_and_tone_without_noise() -> None:
    """No noise: the 8-bit value is the tone curve of radiance x exposure / nominal exposure x gain,
    clipped at full well and at the converter's top."""
    from ficap_ros.tools.synth.camera_chain import sensor_and_tone

    scene = np.array([[0.0, 0.1, 0.25, 0.5, 0.9, 1.3]], np.float32)
    rng = np.random.default_rng(0)
    for tone in ("linear", "srgb"):
        cfg = RenderConfig(noise=False, tone=tone)
        e, g = cfg.exposure_and_gain()
        for exposure, gain in ((e, 1.0), (e / 2, 1.0), (e, 1.5)):
            got = sensor_and_tone(scene.copy(), cfg, exposure, gain, rng)
            level = np.minimum(np.minimum(scene * exposure / e, 1.0) * gain, 1.0)
            want = np.round(255 * (level if tone == "linear" else
                                   np.where(level <= 0.0031308, 12.92 * level,
                                            1.055 * level ** (1 / 2.4) - 0.055)))
            assert np.abs(got.astype(int) - want).max() <= 1, (tone, exposure, gain, got, want)


def test_sensor_noise_is_shot_and_read_noise() -> None:
    """A flat grey at a quarter of full well (2000 electrons of 8000): shot noise sqrt(2000) and
    4 electrons of read noise, 1.43 levels of 8 bits in a linear camera (plus the rounding's
    1/12 level^2)."""
    from ficap_ros.tools.synth.camera_chain import sensor_and_tone

    cfg = RenderConfig(tone="linear")
    e, _ = cfg.exposure_and_gain()
    out = sensor_and_tone(np.full((300, 300), 0.25, np.float32), cfg, e, 1.0,
                          np.random.default_rng(3)).astype(np.float64)
    sigma_e = np.hypot(np.sqrt(2000.0), cfg.read_noise_e)
    expected = np.sqrt((255 * sigma_e / cfg.full_well_e) ** 2 + 1.0 / 12.0)
    assert out.mean() == pytest.approx(0.25 * 255, abs=0.1)
    assert out.std() == pytest.approx(expected, rel=0.05)


def test_tone_lut_is_the_tone_curve_at_every_code() -> None:
    from ficap_ros.tools.synth.camera_chain import CODE_MAX, tone_lut

    for tone, gamma in (("srgb", 2.2), ("gamma", 1.8), ("linear", 2.2)):
        lut = tone_lut(tone, gamma)
        assert lut.shape == (CODE_MAX + 1,) and lut.dtype == np.uint8 and not lut.flags.writeable
        assert lut[0] == 0 and lut[-1] == 255 and np.all(np.diff(lut.astype(int)) >= 0)
    assert tone_lut("linear", 2.2)[CODE_MAX // 2] == 127
    assert tone_lut("srgb", 2.2)[round(0.5 * CODE_MAX)] == 188  # 255 x 0.735357, IEC 61966-2-1
    assert tone_lut("gamma", 2.0)[round(0.25 * CODE_MAX)] == 128  # 255 x 0.25 ** (1/2)


def test_jpeg_round_trip_is_opencvs_codec() -> None:
    import cv2

    from ficap_ros.tools.synth.camera_chain import jpeg_round_trip

    image = cv2.GaussianBlur(np.random.default_rng(1).integers(0, 256, (64, 96), np.uint8), (7, 7), 2)
    out = jpeg_round_trip(image, 90)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    np.testing.assert_array_equal(out, cv2.imdecode(buf, cv2.IMREAD_UNCHANGED))
    assert out.shape == image.shape and np.abs(out.astype(int) - image).mean() < 2.0
    assert np.abs(jpeg_round_trip(image, 5).astype(int) - image).mean() > \
        np.abs(out.astype(int) - image).mean()


def test_distortion_maps_point_each_pixel_at_its_ideal_pinhole_pixel() -> None:
    """Every distorted pixel's ideal pinhole pixel (on the canvas, minus its offset), projected
    back through the lens, lands on that pixel."""
    from ficap_ros.geometry.camera import CameraModel
    from ficap_ros.tools.synth.camera_chain import distortion_maps

    base = default_scene((320, 180)).camera
    camera = CameraModel(320, 180, base.K, [-0.28, 0.09, 0.001, -0.0005, 0.0], "plumb_bob")
    map_x, map_y, (ox, oy, cw, ch) = distortion_maps(320, 180, camera.K.tobytes(),
                                                     camera.D.tobytes(), "plumb_bob")
    assert map_x.shape == (180, 320) and cw >= 320 and ch >= 180
    assert 0 <= map_x.min() and map_x.max() < cw and 0 <= map_y.min() and map_y.max() < ch
    ideal = np.stack([map_x.ravel() - ox, map_y.ravel() - oy], axis=1).astype(np.float64)
    rays = np.c_[ideal, np.ones(len(ideal))] @ np.linalg.inv(camera.K).T
    u, v = np.meshgrid(np.arange(320.0), np.arange(180.0))
    np.testing.assert_allclose(camera.project(rays), np.stack([u.ravel(), v.ravel()], axis=1),
                               atol=0.02)  # float32 maps

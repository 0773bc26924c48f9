"""ficap_ros.tools.synth.shutter: each row's weights on the shared sample grid (sum 1, mean time
exactly the row's, a box over its exposure); rendered rows seen at the blender_dev convention's
times (row r of H exposed centred on stamp + (r + 0.5 - H/2) / H * readout), with or without blur,
in either row order; what the rolling shutter refuses."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from synth_frames import MODEL, edge_crossing_px, frontal_square

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth import RenderConfig, default_scene, render
from ficap_ros.tools.synth.shutter import (
    MAX_SAMPLES,
    rolling_corners_px,
    sample_weights,
)

CAMERA = default_scene("540p").camera
H = CAMERA.height_px
#: A lone tag 0.2 m ahead sliding right at 0.3 m/s: about 1250 px/s in the image.
SPEED_M_S = 0.3
SQUARE, T0 = frontal_square(0.2)
#: Linear light, a sharp lens, no noise, no head or interior: edges as exact as the raster draws.
PLAIN = RenderConfig(tone="linear", psf_sigma_px=0.0, noise=False, head=False, background=False,
                     exposure_ms=8.0)


def _sliding(dt_s: float) -> Transform:
    return Transform(T0.rotation, T0.translation_m + [SPEED_M_S * dt_s, 0.0, 0.0])


def _convention_s(rows: np.ndarray, readout_s: float, height: int) -> np.ndarray:
    """blender_dev's README, written out: row r of H exposed centred on
    stamp + (r + 0.5 - H/2) / H * readout_s."""
    return (rows + 0.5 - height / 2) / height * readout_s


@given(readout_ms=st.floats(0.5, 40.0), step_ms=st.floats(0.2, 5.0), m=st.integers(1, 12),
       height=st.integers(2, 1200), bottom_up=st.booleans())
def test_each_rows_weights_are_a_box_centred_on_its_time(readout_ms: float, step_ms: float,
                                                         m: int, height: int,
                                                         bottom_up: bool) -> None:
    """Non-negative, summing to 1, mean time exactly the row's (however the rows fall on the
    grid), spread that of a box of m steps smoothed by the interpolation, support within one
    step of the window; the grid is whole steps with 0 (the stamp) on it."""
    timing = CameraTiming(readout_ms=readout_ms,
                          row_order="bottom_to_top" if bottom_up else "top_to_bottom")
    t = timing.row_time_s(np.arange(height), height)
    step = step_ms * 1e-3
    try:
        times, w = sample_weights(t, step, m)
    except ConfigError:
        assert (readout_ms / step_ms) + m + 2 > MAX_SAMPLES
        return
    assert np.all(w >= 0.0)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(w @ times, t, rtol=0, atol=1e-12 * max(1.0, readout_ms))
    np.testing.assert_allclose(times / step, np.round(times / step), atol=1e-9)
    assert np.any(np.abs(times) < 1e-12)
    spread = w @ times**2 - t**2
    box = step**2 * (m**2 - 1) / 12.0  # variance of m points one step apart
    assert np.all(spread >= box - 1e-12) and np.all(spread <= box + step**2 / 4 + 1e-12)
    reach = np.where(w > 0, np.abs(times[None, :] - t[:, None]), 0.0).max(axis=1)
    assert np.all(reach <= (m + 1) / 2 * step + 1e-12)


def test_a_row_on_the_grid_takes_the_midpoint_rule() -> None:
    """A row whose sub-steps fall on the grid averages its m samples equally (a global shutter's
    sub-frames); one a quarter step later interpolates each sub-step between two samples."""
    times, w = sample_weights(np.array([0.5e-3, 0.75e-3]), 1e-3, 4)
    np.testing.assert_allclose(times[w[0] > 0], [-1e-3, 0.0, 1e-3, 2e-3], atol=1e-15)
    np.testing.assert_allclose(w[0][w[0] > 0], 0.25)
    np.testing.assert_allclose(w[1][w[1] > 0], [0.1875, 0.25, 0.25, 0.25, 0.0625])


def _edge_per_row(frame, x_rows: np.ndarray, rows: np.ndarray, half_smear_px: float) -> np.ndarray:
    """Where each row crosses halfway from the white margin to the black border, searched near
    ``x_rows`` (the levels read just outside the smear on either side)."""
    img = frame.image.astype(np.float64)
    xs = []
    for x, r in zip(x_rows, rows):
        a, b = int(round(x - half_smear_px)), int(round(x + half_smear_px))
        white, black = np.median(img[r, a - 6:a - 2]), np.median(img[r, b + 3:b + 7])
        xs.append(edge_crossing_px(frame.image, x, slice(r, r + 1), 0.5 * (white + black)))
    return np.array(xs)


@pytest.mark.parametrize("row_order", ["top_to_bottom", "bottom_to_top"])
@pytest.mark.parametrize("blur", [False, True])
def test_rows_are_seen_at_the_conventions_times(row_order: str, blur: bool) -> None:
    """The tag's left edge, sliding right, is slanted by the readout: each row shows it where the
    pose at that row's time puts it (blender_dev's convention, in the given row order), to a
    tenth of a pixel; with motion blur its 50 % point (linear light: a box smear is symmetric)
    stays at the row's mid-exposure position while the smear is as long as the exposure's travel.
    The frame's truth is the pose at the stamp."""
    readout_ms = 40.0
    cfg = replace(PLAIN, readout_ms=readout_ms, row_order=row_order, motion_blur=blur)
    frame = render(SQUARE, CAMERA, _sliding, cfg)
    assert np.allclose(frame.T_cam_cap.translation_m, T0.translation_m)
    c = frame.corners_px[0]  # at the stamp
    np.testing.assert_allclose(c, CAMERA.project(T0.apply(SQUARE.corners_mm[0] / 1000.0)))
    x_stamp = float(c[[0, 3], 0].mean())
    cell = (c[3, 1] - c[0, 1]) / 8
    rows = np.arange(int(c[0, 1] + 2 * cell), int(c[3, 1] - 2 * cell), 3)
    v_px_s = CAMERA.K[0, 0] * SPEED_M_S / T0.translation_m[2]
    sign = 1.0 if row_order == "top_to_bottom" else -1.0
    want = x_stamp + v_px_s * sign * _convention_s(rows, readout_ms * 1e-3, H)
    travel_px = v_px_s * PLAIN.exposure_ms * 1e-3 if blur else 0.0
    got = _edge_per_row(frame, want, rows, 0.5 * travel_px)
    slant_px = v_px_s * readout_ms * 1e-3 * (rows[-1] - rows[0]) / H
    assert slant_px > 4.0
    assert np.abs(got - want).max() < 0.1, np.abs(got - want).max()
    # Sharper, free of the raster's own sub-pixel error: a row is the row of a global-shutter
    # frame exposed at that row's time (blurred the same way, or not), up to the interpolation
    # between samples a quarter pixel of travel apart and the 8-bit output.
    some = rows[:: max(1, len(rows) // 5)]
    at_row = [render(SQUARE, CAMERA, lambda dt, t=t: _sliding(t + dt), replace(cfg, readout_ms=0.0))
              for t in sign * _convention_s(some, readout_ms * 1e-3, H)]
    ref = np.array([_edge_per_row(f, want[np.searchsorted(rows, r)][None], np.array([r]),
                                  0.5 * travel_px)[0] for f, r in zip(at_row, some)])
    mine = got[np.searchsorted(rows, some)]
    assert np.abs(mine - ref).max() < 0.05, np.abs(mine - ref).max()
    # The rolling corners: each at the time of its own row.
    moved = rolling_corners_px(SQUARE, CAMERA, _sliding, cfg.timing, [0])[0]
    np.testing.assert_allclose(moved[:, 1], c[:, 1], atol=1e-9)
    np.testing.assert_allclose(moved[:, 0], c[:, 0] + v_px_s * sign * _convention_s(
        c[:, 1], readout_ms * 1e-3, H), atol=1e-6)
    if blur:  # the 10-90 % width of a box smear of length L is 0.8 L
        k = len(rows) // 2
        prof = frame.image[rows[k]].astype(np.float64)
        near = np.abs(np.arange(prof.size) - want[k]) < 0.5 * travel_px + 2
        lo, hi = prof[near].min(), prof[near].max()
        ramp = np.sum(near & (prof > lo + 0.1 * (hi - lo)) & (prof < lo + 0.9 * (hi - lo)))
        assert travel_px > 8.0 and abs(ramp - 0.8 * travel_px) <= 1.5


def test_a_still_pose_and_a_global_shutter_are_unchanged() -> None:
    """A rolling shutter of a still pose is the still frame; a global shutter without blur
    renders the pose at the stamp (the pose function is asked nothing else)."""
    still = render(SQUARE, CAMERA, T0, PLAIN)
    rs = render(SQUARE, CAMERA, lambda dt: T0, replace(PLAIN, readout_ms=20.0, motion_blur=False))
    assert np.abs(rs.image.astype(int) - still.image.astype(int)).max() <= 1
    asked: list[float] = []

    def pose_at(dt: float) -> Transform:
        asked.append(dt)
        return _sliding(dt)

    frame = render(SQUARE, CAMERA, pose_at, replace(PLAIN, motion_blur=False))
    assert set(asked) == {0.0}
    assert np.array_equal(frame.image, render(SQUARE, CAMERA, T0, PLAIN).image)


def test_what_the_rolling_shutter_refuses() -> None:
    distorted = CameraModel(CAMERA.width_px, CAMERA.height_px, CAMERA.K, [-0.2, 0.05, 0, 0, 0],
                            "plumb_bob")
    with pytest.raises(ConfigError, match="undistorted"):
        render(MODEL, distorted, lambda dt: T0, replace(PLAIN, readout_ms=10.0))
    with pytest.raises(ConfigError, match="samples"):
        sample_weights(np.linspace(0.0, 1.0, 10), 1e-3, 1)
    for bad in ({"readout_ms": -1.0}, {"readout_ms": 2000.0}, {"row_order": "sideways"}):
        with pytest.raises(ConfigError):
            RenderConfig(**bad)
    assert RenderConfig(readout_ms=22.0, exposure_ms=16.7).timing == CameraTiming(16.7, 22.0)
    assert RenderConfig(readout_ms=22.0, motion_blur=False).timing == CameraTiming(readout_ms=22.0)

"""A tag's noise ratio (``tag_noise.noise_ratios``): noise sd / (contrast sqrt(px per cell)).

On single tags drawn with known levels, blur and Gaussian noise the ratio is the drawn one within
a stated tolerance, grows with the noise and falls with the contrast; on ``ficap synth`` frames
the tags of a clean 1080p frame lie far below the auto threshold and most tags of a dim 540p
frame above it.
"""

from __future__ import annotations

import numpy as np
import pytest
from corner_eval import drive_frames
from tag_images import tag_image

from ficap_ros.tools.synth import RenderConfig
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.tag_noise import noise_ratios

THRESHOLD = DetectorConfig().edge_photometric_noise_ratio


def _tag(side_px: float, levels: tuple[float, float], noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Tag 7 of ``side_px`` turned by 20 deg in a 240 x 240 image: (image, corners (1, 4, 2))."""
    a = np.radians(20.0)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side_px / 2 @ rot.T + 120.0
    img = tag_image(7, corners, (240, 240), np.random.default_rng(seed), background=120, levels=levels,
                    blur=0.7, noise=noise)
    return img, corners[None]


@pytest.mark.parametrize("side_px, noise", [(64.0, 3.0), (64.0, 8.0), (40.0, 6.0), (96.0, 10.0)])
def test_the_ratio_is_the_drawn_noise_over_contrast_and_cell_size(side_px: float, noise: float) -> None:
    """Levels 40 / 200 (contrast 160), cells of side / 8 px: within 25 % of noise / (160 sqrt(cell))
    (64 cell-centre pixels a tag: the MAD's own scatter is about 15 %)."""
    got = np.array([noise_ratios(*_tag(side_px, (40.0, 200.0), noise, seed), np.array([7]))[0]
                    for seed in range(4)])
    want = noise / (160.0 * np.sqrt(side_px / 8.0))
    assert np.median(got) == pytest.approx(want, rel=0.25)


def test_the_ratio_grows_with_noise_and_falls_with_contrast() -> None:
    quiet = noise_ratios(*_tag(64.0, (40.0, 200.0), 2.0, 1), np.array([7]))[0]
    noisy = noise_ratios(*_tag(64.0, (40.0, 200.0), 8.0, 1), np.array([7]))[0]
    dim = noise_ratios(*_tag(64.0, (40.0, 80.0), 8.0, 1), np.array([7]))[0]
    assert quiet < noisy < dim
    assert dim / noisy == pytest.approx(160.0 / 40.0, rel=0.3)


def test_no_tags_and_a_tag_without_contrast() -> None:
    assert noise_ratios(np.zeros((50, 50), np.uint8), np.zeros((0, 4, 2)), np.zeros(0, int)).shape == (0,)
    flat = np.full((240, 240), 128, np.uint8)
    corners = np.array([[[80.0, 80.0], [160.0, 80.0], [160.0, 160.0], [80.0, 160.0]]])
    # No contrast and no noise: 0 / max(0, 1) -- nothing says this tag's corners are noisy.
    assert noise_ratios(flat, corners, np.array([7]))[0] == 0.0


@pytest.mark.parametrize("resolution, lighting, above", [("1080p", "neutral", (0.0, 0.15)),
                                                          ("540p", "low", (0.6, 1.0))])
def test_synth_frames_clean_tags_below_the_threshold_dim_tags_above(resolution: str, lighting: str,
                                                                     above: tuple[float, float]) -> None:
    """The share of a frame's fully visible tags above the auto threshold (``DetectorConfig``'s
    ``edge_photometric_noise_ratio``) at their true corners: a few of a clean frame's (a glint
    or a steep view over their cell centres), most of a dim frame's."""
    fr = drive_frames(resolution, RenderConfig(lighting=lighting, jpeg_quality=95), n=1)[0]
    ids = np.array(fr.visible_ids(0.999))
    ratios = noise_ratios(fr.image, np.array([fr.corners_px[t] for t in ids]), ids)
    share = float(np.mean(ratios > THRESHOLD))
    assert above[0] <= share <= above[1], (share, np.round(ratios, 4))

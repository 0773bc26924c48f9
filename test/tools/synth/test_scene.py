"""ficap_ros.tools.synth.scene: the head and neck sit inside the cap, each face's texture is its tag
inside a one-cell white quiet zone, and the interior and hair are deterministic in their seed."""

from __future__ import annotations

import numpy as np
import pytest
from synth_frames import MODEL, detect

from ficap_ros.geometry.tag36h11 import tag_cells
from ficap_ros.tools.synth import (
    HEAD_CENTRE_M,
    HEAD_SEMI_AXES_M,
    NECK_CENTRE_M,
    NECK_SEMI_AXES_M,
)
from ficap_ros.tools.synth.scene import CELLS_FACE, background, face_texture, hair_waves


def test_head_and_neck_lie_inside_every_face() -> None:
    faces = MODEL.face_corners_mm() / 1000.0
    g = np.linspace(0.0, 1.0, 9)
    pts = np.array([f[0] + a * (f[1] - f[0]) + b * (f[3] - f[0]) for f in faces for a in g for b in g])
    for centre, axes in ((HEAD_CENTRE_M, HEAD_SEMI_AXES_M), (NECK_CENTRE_M, NECK_SEMI_AXES_M)):
        r = np.sqrt((((pts - np.array(centre)) / np.array(axes)) ** 2).sum(axis=1))
        assert r.min() > 1.0  # every face point outside the ellipsoid


@pytest.mark.parametrize("tag_id, cell_px", [(0, 1), (11, 3), (22, 6)])
def test_face_texture_is_the_tag_inside_a_white_quiet_zone(tag_id: int, cell_px: int) -> None:
    tex = face_texture(tag_id, cell_px)
    n = CELLS_FACE * cell_px
    assert tex.shape == (n, n, 3) and tex.dtype == np.uint8 and not tex.flags.writeable
    assert (tex[..., 0] == 255).all()  # the whole face is covered
    inner = np.zeros((n, n), bool)
    inner[cell_px:n - cell_px, cell_px:n - cell_px] = True
    np.testing.assert_array_equal(tex[..., 1] == 255, inner)  # the tag square: 8 of 10 cells
    assert (tex[..., 2][~inner] == 0).all()  # the quiet zone is white
    # Each cell of the tag is black exactly where tag36h11 says (sampled at the cell centres).
    centres = cell_px + cell_px * np.arange(8) + cell_px // 2
    black = tex[..., 2][np.ix_(centres, centres)] == 255
    np.testing.assert_array_equal(black, tag_cells(tag_id))


def test_a_face_texture_decodes_to_its_id() -> None:
    tex = face_texture(7, 6)
    image = np.full((100, 100), 255, np.uint8)
    image[20:80, 20:80] = np.where(tex[..., 2] == 255, 0, 255)
    assert set(detect(image)) == {7}


def test_background_and_hair_are_fixed_by_their_seed() -> None:
    a = background(160, 90, 3, False)
    assert a.shape == (90, 160, 1) and a.dtype == np.float32 and not a.flags.writeable
    assert 0.0 < a.min() and a.max() <= 1.0  # linear albedo, never pure black
    np.testing.assert_array_equal(background.__wrapped__(160, 90, 3, False), a)  # not the cache
    assert np.abs(background(160, 90, 4, False) - a).max() > 0.01  # another seed, another car
    colour = background(160, 90, 3, True)
    assert colour.shape == (90, 160, 3)
    # The tint is mild: the channels stay within 15 % of the grey image's level.
    np.testing.assert_allclose(colour.mean(axis=2), a[..., 0], rtol=0.15)
    k, phase = hair_waves(5)
    assert k.shape == (6, 3) and phase.shape == (6,)
    assert np.all((np.linalg.norm(k, axis=1) >= 8.0) & (np.linalg.norm(k, axis=1) <= 40.0))
    k2, phase2 = hair_waves.__wrapped__(5)
    np.testing.assert_array_equal(k, k2)
    np.testing.assert_array_equal(phase, phase2)

"""ficap_ros.tools.synth.config: RenderConfig's validation and defaults (the realistic camera, the
PSF for the height, the shutter-priority auto-exposure), and RenderedFrame's visible ids."""

from __future__ import annotations

import numpy as np
import pytest

from ficap_ros.errors import ConfigError
from ficap_ros.tools.synth import REALISTIC, RenderConfig


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


@pytest.mark.parametrize("bad", [dict(full_well_e=0.0), dict(read_noise_e=-1.0),
                                 dict(motion_subframes=256), dict(jpeg_quality=0),
                                 dict(jpeg_quality=101), dict(supersample=0), dict(supersample=9),
                                 dict(head_semi_axes_m=(0.1, 0.0, 0.1)),
                                 dict(head_centre_m=(0.0, 0.0)), dict(gain="much")])
def test_render_config_rejects_each_bad_field(bad: dict) -> None:
    with pytest.raises(ConfigError, match=next(iter(bad)).split("_m")[0]):
        RenderConfig(**bad)


def test_render_config_defaults_are_the_realistic_camera() -> None:
    from ficap_ros.tools.synth import PSF_SIGMA_1080P_PX, default_psf_sigma_px
    from ficap_ros.tools.synth.lighting import LIGHTS

    default = RenderConfig()
    assert default == RenderConfig(**REALISTIC)
    assert default.lighting == "neutral" and default.tone == "srgb" and default.noise
    assert default.psf_sigma_px is None and default.jpeg_quality is None
    # The PSF for the height: sqrt(height / 1080) of 0.7 px; an explicit value wins, 0 is none.
    assert PSF_SIGMA_1080P_PX == 0.7
    for height in (270, 540, 720, 1080, 2160):
        assert default.psf_sigma_for(height) == pytest.approx(0.7 * np.sqrt(height / 1080))
        assert default_psf_sigma_px(height) == default.psf_sigma_for(height)
    assert RenderConfig(psf_sigma_px=0.0).psf_sigma_for(1080) == 0.0
    assert RenderConfig(psf_sigma_px=1.3).psf_sigma_for(540) == 1.3
    # Auto-exposure: the lighting's nominal exposure and gain; an explicit gain is kept.
    for lighting, light in LIGHTS.items():
        assert RenderConfig(lighting=lighting).exposure_and_gain() == (light.exposure_ms, light.gain)
        assert RenderConfig(lighting=lighting, gain=3.0).exposure_and_gain() == (light.exposure_ms, 3.0)


def test_visible_ids_are_those_seen_enough_in_order() -> None:
    from ficap_ros.geometry.transform import Transform
    from ficap_ros.tools.synth import RenderedFrame

    frame = RenderedFrame(np.zeros((2, 2), np.uint8), Transform.identity(), {},
                          {7: 1.0, 2: 0.9995, 5: 0.5, 1: 0.0})
    assert frame.visible_ids() == [2, 7]
    assert frame.visible_ids(0.5) == [2, 5, 7]
    assert frame.visible_ids(0.0) == [1, 2, 5, 7]

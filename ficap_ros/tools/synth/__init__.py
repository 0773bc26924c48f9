"""Rendered Fi-Cap frames with exact ground truth, and naturalistic driving head motion.

Renderer (``render``): any ``CapModel`` seen by any ``CameraModel`` at a known ``T_cam_cap``,
formed the way a camera forms an image, in this order (``RenderConfig`` holds every knob):

1. **Scene radiance in linear light**, in units of the sensor's full well at the lighting's nominal
   exposure (``raster``, ``scene``, ``lighting``). Every front-facing face (40 mm white square,
   32 mm tag36h11 centred, as drawn by ``cv2.aruco.generateImageMarker``, upright: image top row
   along the model's TL->TR edge) is drawn by a per-face homography, supersampled (3-8x) over the
   face's bounding box and box-filtered down (``cv2.INTER_AREA``): each pixel integrates linear
   light over its area, so the tag's outer black corners sit at
   ``camera.project(T_cam_cap.apply(c))`` in OpenCV's pixel convention (pixel centres at integers)
   at any sub-pixel phase. White paper reflects 1, black ink 0.05 of it. Back faces are culled;
   front faces are painted far to near. A dark, hair-textured head ellipsoid (and neck) fixed in
   the cap frame hides faces behind it with a per-pixel depth test; a static seeded car interior
   behind (``RenderConfig.background_seed``). Lighting ``neutral`` (mostly a lamp beside the
   camera, lighting each point of a face by cos(incidence) / distance^2, so an oblique face's near
   side is brighter; plus the cabin's diffuse light: white paper at 45-70 % of full well),
   ``high`` (the paper's three spotlights on the cap: whites far past full well, glare lifts
   blacks) or ``low`` (one source at the driver's front-right, 1-10 % of full well, shadows);
   every preset adds veiling flare and goes through the whole chain.
2. **Lens PSF**, in linear light (``camera_chain``): a Gaussian (``psf_sigma_px``; realistic:
   0.7 px at 1080p times sqrt(height/1080), 0.49 px at 540p) and optionally a defocus disc
   (``defocus_radius_px``).
3. **Motion blur** (optional, ``render``): given a pose *function* of time instead of a pose, the
   frame averages sub-frames rendered over the exposure (``exposure_ms``; an odd count, at most
   half a pixel of corner travel between two, so only fast motion costs more); its ground truth is
   the pose at mid-exposure. ``naturalistic_motion(...).around(t)`` gives that function for a drive.
   A **rolling shutter** (``readout_ms``, ``row_order``; ``shutter``) exposes each row over its
   own window, centred ``(y + 0.5 - H / 2) / H * readout`` after the stamp (the middle row's
   mid-exposure, whose pose is the truth), with or without the blur (``motion_blur``).
4. **Sensor** (``camera_chain``): charge = radiance x exposure / nominal exposure x full well
   (``full_well_e``), shot noise (Poisson, Gaussian limit), clipping at full well, read noise
   (``read_noise_e``), then ``gain`` (auto: the lighting's, scaled for a non-nominal exposure) into
   a 16-bit code that clips at 1: ``high`` light saturates, ``low`` light is dark and, with gain
   2.5, noisy.
5. **Tone curve** (``tone``, ``ficap_ros.vision.tone``): ``srgb``, ``gamma`` (``gamma`` exponent),
   ``filmic`` (an S-curve on sRGB) or ``linear`` (an idealised camera), then **8 bit** by a lookup
   table.
6. **JPEG** (optional, ``jpeg_quality``; ``ficap synth`` always stores JPEG).

``RenderConfig()`` is the realistic camera (the PSF for the height, sRGB), which is also what
``ficap synth`` renders (``REALISTIC`` names it); ``psf_sigma_px=0, tone="linear"`` gives the
idealised camera.

Distorted cameras: the ideal pinhole with the same K is rendered on a canvas large enough, then
``cv2.remap``-ed (still in linear light, before the PSF) into the distorted image, so
``corners_px`` (``camera.project``) stays exact.

Why the order matters: a lens blurs light, the camera then bends it. After a tone curve the 50 %
grey point of a blurred black/white edge sits on the black side of the true edge (about 0.5-0.8
sigma for sRGB, further where whites clip), which is what corner methods that look for a grey
midpoint or a gradient peak inherit on real images. ``tone="linear", psf_sigma_px=0`` gives the
idealised images the geometry tests want.

Motion (``drive``): ``naturalistic_drive`` gives a list of ``DriveFrame`` with the true head and
cap poses of a drive that looks ahead, then glances at the mirrors and the instrument cluster;
``glance_motion`` strings such glances back to back, each turn peaking at 150-250 deg/s.

Modules: ``config`` (RenderConfig, RenderedFrame), ``lighting``, ``scene`` (what is drawn),
``raster`` (drawing it into radiance), ``camera_chain`` (lens, sensor, ISP), ``shutter`` (a
rolling shutter's rows), ``render`` (the chain), ``drive`` (head motion). This package exports
their public names.
"""

from __future__ import annotations

from ficap_ros.tools.synth.config import (
    PSF_SIGMA_1080P_PX,
    REALISTIC,
    RENDER_VERSION,
    RenderConfig,
    RenderedFrame,
    default_psf_sigma_px,
)
from ficap_ros.tools.synth.drive import (
    GLANCE_PEAK_DEG_S,
    MOTIONS,
    RESOLUTIONS,
    DriveFrame,
    DriveMotion,
    DriveScene,
    default_scene,
    drive_motion,
    glance_motion,
    naturalistic_drive,
    naturalistic_motion,
)
from ficap_ros.tools.synth.lighting import LIGHTINGS
from ficap_ros.tools.synth.render import render
from ficap_ros.tools.synth.scene import (
    HEAD_CENTRE_M,
    HEAD_SEMI_AXES_M,
    NECK_CENTRE_M,
    NECK_SEMI_AXES_M,
)
from ficap_ros.vision.tone import TONES, srgb_to_linear, tone_curve

__all__ = [
    "RENDER_VERSION",
    "LIGHTINGS",
    "HEAD_CENTRE_M",
    "HEAD_SEMI_AXES_M",
    "NECK_CENTRE_M",
    "NECK_SEMI_AXES_M",
    "RenderConfig",
    "RenderedFrame",
    "render",
    "DriveScene",
    "DriveFrame",
    "default_scene",
    "naturalistic_drive",
    "naturalistic_motion",
    "glance_motion",
    "drive_motion",
    "MOTIONS",
    "GLANCE_PEAK_DEG_S",
    "DriveMotion",
    "TONES",
    "tone_curve",
    "srgb_to_linear",
    "default_psf_sigma_px",
    "PSF_SIGMA_1080P_PX",
    "REALISTIC",
    "RESOLUTIONS",
]

"""Path-traced calibration sets: the cap rendered with Blender Cycles, in blender_dev's format.

``ficap synth`` (``ficap_ros.tools.synth``) draws the cap analytically; ``../shared/data/blender_dev`` is a
path-traced check set that must not be tuned to. This script makes *our own* path-traced sets, with
their own poses and seeds, so that calibration can see the physics the analytic renderer lacks
(Monte Carlo noise at a few samples per pixel, real light fall-off and inter-reflection, the
renderer's pixel filter). It reads blender_dev (``--dev-data``) only for the what-if set at its
poses (``AS_DEV``), a check of the renderer; nothing is fitted to it.

Two processes, two venvs (the package never imports bpy):
  1. the project venv plans a set (poses from ``synth.naturalistic_drive``, cap corners from
     ``cap_model.nominal_model``, tag textures from ``cv2.aruco.generateImageMarker``, lights)
     into ``<out>/_work/<set>/plan.json``;
  2. ``.venv-bpy/bin/python datasets/cycles_render.py _bpy plan.json`` (Blender as a Python
     module) path-traces each frame's *linear* radiance to ``frame_XXX.npy`` and ray-casts every
     tag corner for visibility (``vis.json``); nothing else;
  3. the project venv applies ``ficap_ros.tools.synth``'s camera chain (flare, Gaussian lens PSF in
     linear light, exposure, shot and read noise, full-well clipping, gain, tone curve, 8 bit,
     JPEG 95) and writes the set with ``ficap_ros.io.bag_writer``: ``<set>/metadata.yaml``,
     ``<set>/<set>.mcap`` (/rear_camera/image_raw/compressed, /rear_camera/camera_info,
     /ground_truth/cap_pose, /ground_truth/head_pose) and ``<set>/ground_truth.json`` with
     blender_dev's fields, so the benchmarks' blender_dev reader (``benchmarks/_lib/devsets.py``)
     reads it unchanged.

The bpy venv on a fresh machine (Blender 5.0.1 as a module, CPython 3.11, manylinux x86_64; it
brings its own numpy 1.26):
    python3.11 -m venv .venv-bpy && .venv-bpy/bin/pip install bpy==5.0.1
(``make bpy-venv`` does this). Usage (project venv):
    .venv/bin/python datasets/cycles_render.py [--out out/cycles_sets] [--sets cyc_540p_neutral,...]
        [--frames N] [--check | --finish-only]
What the sets showed is in docs/studies.md ("Path-traced calibration sets"). The set order is
``<out>/sets.txt``; the what-if sets (``_sky``, ``_noisy``, ``cyc_as_dev_*``) are diagnoses, not
calibration data.
Deterministic: poses, lights, Cycles' sampling seed and the sensor noise are functions of the set.

Scene (physical choices, nothing fitted to blender_dev): the 23 nominal 40 mm plates (quiet zone
+ tag, white paper reflectance 0.80, black ink 0.04 = 5 %), a dark fabric shell under them, the
head (synth's ellipsoid, dark hair 0.05), ears and neck (skin 0.25), a headrest, a torso and a car
interior (grey 0.2-0.3 Lambertian), all Lambertian (Diffuse BSDF). Camera: K = 0.75 W focal,
principal point (W/2, H/2) in OpenCV's pixel convention, the cap origin 0.77 m ahead and 6 cm
below (blender_dev's geometry, so tag sizes match it: a foreshortened 540p cell is 2-3 px; synth's
default scene is 0.54 m with a 60 deg lens, 1.7x larger tags). Cycles CPU, 8 samples per pixel,
no denoising, the default pixel filter (Blackman-Harris 1.5 px), no motion blur, 1 thread.
Exposure: an auto-exposure metering the plates per frame (``METER_ON_RENDER``; high: ``WHITE_LEVEL``).
Lights: neutral = a small lamp 5 cm above the lens plus a weak sky through the open side of the
car; high = a bright sun and sky plus three spotlights on the cap (1-2.5x the base light each:
clipped highlights); low = one street lamp outside at the front right, gain 2.5.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BPY_PYTHON = ROOT / ".venv-bpy" / "bin" / "python"
#: Default output folder (``/out/`` is ignored by git).
DEFAULT_OUT = ROOT / "out" / "cycles_sets"
#: blender_dev next to the clone (or next to its parent: a git worktree one level further down).
DEFAULT_DEV = next((p / "shared" / "data" / "blender_dev" for p in (ROOT.parent, ROOT.parent.parent)
                    if (p / "shared" / "data" / "blender_dev").is_dir()),
                   ROOT.parent / "shared" / "data" / "blender_dev")
SAMPLES = 8
#: Seconds between the frames of a set (a 30 fps naturalistic drive sampled every 60th frame).
FRAME_STEP = 60
WHITE_ALBEDO = 0.80
BLACK_ALBEDO = 0.04  # 5 % of white paper
#: set -> (width, height, lighting, PSF sigma px, tone name as in blender_dev, drive seed).
SET_SPECS: dict[str, tuple[int, int, str, float, str, int]] = {
    "cyc_540p_neutral": (960, 540, "neutral", 0.60, "gamma18", 701),
    "cyc_540p_high": (960, 540, "high", 0.50, "filmic", 702),
    "cyc_540p_low": (960, 540, "low", 0.45, "srgb", 703),
    "cyc_1080p_neutral": (1920, 1080, "neutral", 0.90, "filmic", 704),
    "cyc_1080p_high": (1920, 1080, "high", 0.65, "srgb", 705),
    # What-if (not a calibration set): 540p neutral's poses and chain, but daylight through the
    # windows (sky) as the main light and the lamp at a fifth: how much of the path-tracing noise
    # is the light's directness.
    "cyc_540p_neutral_sky": (960, 540, "neutral", 0.60, "gamma18", 701),
    # What-if (not a calibration set): cyc_540p_neutral's own renders with extra per-pixel noise
    # in the linear radiance (``EXTRA_NOISE``), standing in for a path tracer's Monte Carlo noise
    # at fewer effective samples: does the noise move the shift along the foreshortening?
    "cyc_540p_neutral_noisy": (960, 540, "neutral", 0.60, "gamma18", 701),
    # What-if (a check of the renderer, not a calibration set): this scene and chain at
    # blender_dev 540p neutral's true cap poses (read from its ground_truth.json), to tell the
    # poses from the renderer.
    "cyc_as_dev_540p_neutral": (960, 540, "neutral", 0.60, "gamma18", 706),
}
#: What-if sets at a blender_dev set's cap poses: name -> blender_dev set.
AS_DEV = {"cyc_as_dev_540p_neutral": "dev_540p_neutral"}
#: What-if sets made from another set's renders: name -> (source set, relative sd of Gaussian
#: noise multiplied into each pixel's radiance before the lens PSF). 0.15 brings the flat white
#: areas' grey noise near blender_dev 540p neutral's (a diagnosis of what differs, not a fit:
#: nothing is calibrated on it).
EXTRA_NOISE = {"cyc_540p_neutral_noisy": ("cyc_540p_neutral", 0.15)}
#: Auto-exposure per frame, metered on the rendered radiance: the 90th percentile over the cap's
#: facing plates (its brightest white) is set to this share of the full well (neutral: 70 %, an
#: auto-exposure's usual headroom, synth's 45-70 %; low: 8 % at gain 2.5, synth's 1-10 %, a night
#: camera at its longest exposure). High light is exposed for its base light (the sun and sky,
#: ``WHITE_LEVEL``) and the spotlights push past it, as synth's spotlights do.
METER_ON_RENDER = {"neutral": 0.70, "low": 0.08}
DEFAULT_FRAMES = {"cyc_540p_neutral": 40, "cyc_540p_high": 40, "cyc_540p_low": 40,
                  "cyc_1080p_neutral": 25, "cyc_1080p_high": 25, "cyc_540p_neutral_sky": 30,
                  "cyc_540p_neutral_noisy": 30, "cyc_as_dev_540p_neutral": 25}
#: Cap origin ahead of the camera (frontal frame F: x forward, y left, z up), m.
P_FRONTAL_CAP_M = (0.77, 0.0, -0.06)
#: High light: white paper facing the sun collects this share of the full well (before the sky's
#: share and the spotlights, which clip it).
WHITE_LEVEL = {"high": 0.50}
#: OpenCV camera frame -> Blender world (the camera sits at the origin looking down -z, y up).
F_CV_TO_BL = np.diag([1.0, -1.0, -1.0, 1.0])


# ------------------------------------------------------------------------------------------------
# Project venv: plan, post-process, write
# ------------------------------------------------------------------------------------------------
def drive_scene(width: int, height: int):  # noqa: ANN201
    from ficap_ros.geometry.camera import CameraModel
    from ficap_ros.geometry.transform import CAM_FROM_FORWARD
    from ficap_ros.tools.synth import DriveScene

    f = 0.75 * width
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    camera = CameraModel(width, height, K, np.zeros(5), "plumb_bob")
    neck_to_cap = np.array([-0.04, 0.0, 0.13])
    p_cam_neck = CAM_FROM_FORWARD.apply(np.array(P_FRONTAL_CAP_M) - neck_to_cap)
    return DriveScene(camera=camera, R_cam_frontal=CAM_FROM_FORWARD, p_cam_neck_m=p_cam_neck,
                      neck_to_cap_m=neck_to_cap)


def _cv_from_frontal(p_frontal) -> list[float]:  # noqa: ANN001
    from ficap_ros.geometry.transform import CAM_FROM_FORWARD

    return [float(v) for v in CAM_FROM_FORWARD.apply(np.asarray(p_frontal, dtype=np.float64))]


def _face_white(tag_id: int) -> np.ndarray:
    """(10, 10) True where the printed face is white: the 8-cell tag (``detection.tag_cells``,
    ``generateImageMarker``'s drawing) in a 1-cell white quiet zone, row 0 = top."""
    from ficap_ros.geometry.tag36h11 import tag_cells

    face = np.ones((10, 10), bool)
    face[1:9, 1:9] = ~tag_cells(tag_id)
    return face


def _tag_texture(tag_id: int, cell_px: int = 16) -> np.ndarray:
    """Reflectance (10 x 10 cells: 1-cell white quiet zone round the 8-cell tag), row 0 = top."""
    refl = np.where(_face_white(tag_id), WHITE_ALBEDO, BLACK_ALBEDO).astype(np.float32)
    return np.kron(refl, np.ones((cell_px, cell_px), np.float32))


def make_plan(name: str, n_frames: int, work: Path, dev_root: Path = DEFAULT_DEV) -> dict:
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools.synth import (
        HEAD_CENTRE_M,
        HEAD_SEMI_AXES_M,
        NECK_CENTRE_M,
        NECK_SEMI_AXES_M,
        naturalistic_drive,
    )

    width, height, lighting, psf, tone, seed = SET_SPECS[name]
    scene = drive_scene(width, height)
    model = nominal_model()
    drive = naturalistic_drive(n_frames * FRAME_STEP, fps=30.0, seed=seed, scene=scene)[FRAME_STEP // 2::FRAME_STEP]
    if name in AS_DEV:
        import dataclasses

        dev = json.loads((dev_root / AS_DEV[name] / "ground_truth.json").read_text())
        from ficap_ros.geometry.transform import Transform

        drive = [dataclasses.replace(d, index=int(g["motion_frame"]),
                                     T_cam_cap=Transform.from_matrix(np.asarray(g["T_cam_cap"])))
            for d, g in zip(naturalistic_drive(len(dev["frames"]), seed=seed, scene=scene), dev["frames"])]
    work.mkdir(parents=True, exist_ok=True)
    textures = []
    for tag_id in model.ids:
        path = work / f"tag_{tag_id:02d}.npy"
        np.save(path, _tag_texture(tag_id))
        textures.append(str(path))
    faces_m = model.face_corners_mm() / 1000.0
    rng = np.random.default_rng(seed)
    r_cap = float(np.linalg.norm(P_FRONTAL_CAP_M))
    frames = []
    for d in drive:
        T = np.eye(4)
        T[:3, :3] = d.T_cam_cap.rotation.as_matrix()
        T[:3, 3] = d.T_cam_cap.translation_m
        spots = []
        if lighting == "high":
            centres = T[:3, :3] @ model.centres_mm.T / 1000.0 + T[:3, 3:4]
            for _ in range(3):
                pos = [rng.uniform(-0.35, 0.35), rng.uniform(-0.25, 0.05), rng.uniform(-0.05, 0.25)]
                aim = centres[:, rng.integers(0, centres.shape[1])] + rng.normal(0, 0.02, 3)
                spots.append({"pos_cv": [float(v) for v in pos], "aim_cv": [float(v) for v in aim],
                              "gain": float(rng.uniform(1.0, 2.5)), "cone_deg": float(rng.uniform(20, 40))})
        frames.append({"index": int(d.index), "T_cam_cap": T.tolist(), "spots": spots,
                       "seed": int(seed * 1000 + d.index % 997)})
    # Lights, camera frame (OpenCV), metres; powers in Blender watts (point/spot: intensity P/4pi
    # W/sr), sun strength in W/m^2, sky = world strength (radiance).
    if name.endswith("_sky"):
        lights = {"lamp": {"pos_cv": [0.0, -0.05, 0.0], "power_w": 2.0, "radius_m": 0.01},
                  "sky": 3.0}
        meter = float("nan")
    elif lighting == "neutral":
        lights = {"lamp": {"pos_cv": [0.0, -0.05, 0.0], "power_w": 10.0, "radius_m": 0.01},
                  "sky": 0.25}
        meter = WHITE_ALBEDO * 10.0 / (4 * math.pi * r_cap**2) / math.pi
    elif lighting == "high":
        sun_dir = np.array([0.3, -0.5, -0.81]) / np.linalg.norm([0.3, -0.5, -0.81])  # toward the sun
        lights = {"sun": {"toward_cv": sun_dir.tolist(), "strength": 3.0}, "sky": 0.6}
        meter = WHITE_ALBEDO * 3.0 / math.pi  # spots scale with the metered base light
        for f in frames:
            for s in f["spots"]:
                dist = float(np.linalg.norm(np.subtract(s["aim_cv"], s["pos_cv"])))
                s["power_w"] = s["gain"] * meter * math.pi / WHITE_ALBEDO * 4 * math.pi * dist**2
    else:
        toward = np.array([0.85, -0.15, 0.5]) / np.linalg.norm([0.85, -0.15, 0.5])
        cap_cv = np.array(_cv_from_frontal(P_FRONTAL_CAP_M))
        pos = cap_cv + 3.0 * toward
        lights = {"lamp": {"pos_cv": pos.tolist(), "power_w": 200.0, "radius_m": 0.1}, "sky": 0.002}
        meter = WHITE_ALBEDO * 200.0 / (4 * math.pi * 3.0**2) / math.pi
    cv = _cv_from_frontal
    cap_z = P_FRONTAL_CAP_M[2]
    plan = {
        "name": name, "width": width, "height": height, "lighting": lighting, "samples": SAMPLES,
        "f_px": 0.75 * width, "work": str(work), "textures": textures,
        "faces_m": faces_m.tolist(), "ids": [int(i) for i in model.ids],
        "white_albedo": WHITE_ALBEDO,
        "cap_parts": [  # ellipsoids in the cap frame: (centre m, semi-axes m, reflectance)
            {"name": "shell", "centre": [0.0, 0.0, 0.0], "axes": [0.089, 0.089, 0.089], "albedo": 0.06},
            {"name": "head", "centre": list(HEAD_CENTRE_M), "axes": list(HEAD_SEMI_AXES_M), "albedo": 0.05},
            {"name": "neck", "centre": list(NECK_CENTRE_M), "axes": list(NECK_SEMI_AXES_M), "albedo": 0.25},
            {"name": "ear_l", "centre": [0.03, 0.078, -0.03], "axes": [0.03, 0.012, 0.033], "albedo": 0.25},
            {"name": "ear_r", "centre": [0.03, -0.078, -0.03], "axes": [0.03, 0.012, 0.033], "albedo": 0.25},
        ],
        # Car-fixed boxes, camera frame: (centre, half sizes along the frontal frame's x, y, z, albedo).
        "static_boxes": [
            {"name": "headrest", "centre": cv([0.64, 0.0, cap_z - 0.20]), "half_f": [0.04, 0.13, 0.09], "albedo": 0.2},
            {"name": "seat", "centre": cv([0.72, 0.0, cap_z - 0.55]), "half_f": [0.06, 0.26, 0.25], "albedo": 0.2},
            {"name": "torso", "centre": cv([0.83, 0.0, cap_z - 0.42]), "half_f": [0.10, 0.22, 0.2], "albedo": 0.15},
            {"name": "floor", "centre": cv([0.8, 0.0, -1.0]), "half_f": [1.5, 0.9, 0.01], "albedo": 0.2},
            # The roof ends above the head (a rear window / sunroof behind it lets the sky and the
            # high light's sun in); the right side is open (the window).
            {"name": "roof", "centre": cv([1.6, 0.0, 0.35]), "half_f": [0.7, 0.9, 0.01], "albedo": 0.3},
            {"name": "door", "centre": cv([0.8, 0.75, -0.3]), "half_f": [1.5, 0.01, 0.7], "albedo": 0.25},
            {"name": "dash", "centre": cv([2.0, 0.0, -0.5]), "half_f": [0.01, 0.9, 0.4], "albedo": 0.25},
        ],
        "lights": lights, "meter_white": meter, "frames": frames,
    }
    (work / "plan.json").write_text(json.dumps(plan))
    return plan


def _tag_geometry(model, T_cam_cap) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """(facing, view angle deg) of every tag (``tracking.view_angles_deg``; facing: under 90)."""
    from ficap_ros.vision.tracking import view_angles_deg

    angle = view_angles_deg(model, T_cam_cap)
    return angle < 90.0, angle


def _plates_p90(radiance: np.ndarray, model, T: np.ndarray, camera) -> float:  # noqa: ANN001
    """90th percentile of the radiance over the facing plates' pixels (an auto-exposure's meter)."""
    import cv2

    from ficap_ros.geometry.transform import Transform

    T_cam_cap = Transform.from_matrix(T)
    facing, _ = _tag_geometry(model, T_cam_cap)
    faces = T_cam_cap.apply(model.face_corners_mm().reshape(-1, 3) / 1000.0)
    px = camera.project(faces).reshape(-1, 4, 2)
    mask = np.zeros(radiance.shape, np.uint8)
    for k in np.flatnonzero(facing):
        cv2.fillConvexPoly(mask, np.round(px[k]).astype(np.int32), 1)
    return float(np.percentile(radiance[mask > 0], 90))


def finish_set(name: str, plan: dict, out: Path) -> dict:
    """Camera chain on the rendered radiance, then the bag and ground_truth.json."""
    import cv2

    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.geometry.metrics import yaw_pitch_roll_deg
    from ficap_ros.geometry.transform import Transform
    from ficap_ros.io import messages
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.io.messages import ROSBAGS
    from ficap_ros.io.sources import CAMERA_INFO_TYPE, COMPRESSED_TYPE
    from ficap_ros.tools import synth
    from ficap_ros.tools.synth import camera_chain
    from ficap_ros.tools.synth.lighting import LIGHTS

    width, height, lighting, psf, tone_name, seed = SET_SPECS[name]
    model = nominal_model()
    tone = "gamma" if tone_name.startswith("gamma") else tone_name
    gamma = 1.8 if tone_name == "gamma18" else 2.2
    cfg = synth.RenderConfig(lighting=lighting, tone=tone, gamma=gamma, psf_sigma_px=psf)
    exposure_ms, gain = cfg.exposure_and_gain()
    flare = LIGHTS[lighting].flare
    scene = drive_scene(width, height)
    camera = scene.camera
    work = Path(plan["work"])
    extra_rel = EXTRA_NOISE[name][1] if name in EXTRA_NOISE else 0.0
    extra_rng = np.random.default_rng(seed + 5000)
    vis = json.loads((work / "vis.json").read_text())
    R_head_cap = scene.R_cap_head.inv()
    T_head_cap = np.eye(4)
    T_head_cap[:3, :3] = R_head_cap.as_matrix()
    frames_gt = []
    start = 1_700_000_000_000_000_000
    set_dir = out / name
    with BagWriter(set_dir, storage="mcap", layout="folder") as bag:
        for topic, typ in (("/rear_camera/image_raw/compressed", COMPRESSED_TYPE),
                           ("/rear_camera/camera_info", CAMERA_INFO_TYPE),
                           ("/ground_truth/cap_pose", "geometry_msgs/msg/PoseStamped"),
                           ("/ground_truth/head_pose", "geometry_msgs/msg/PoseStamped")):
            bag.add_topic(topic, typ)
        for fr in plan["frames"]:
            i = int(fr["index"])
            radiance = np.load(work / f"frame_{i:05d}.npy").astype(np.float32)
            if lighting in METER_ON_RENDER:
                scale = METER_ON_RENDER[lighting] / _plates_p90(radiance, model, np.asarray(fr["T_cam_cap"]), camera)
            else:
                scale = WHITE_LEVEL[lighting] / float(plan["meter_white"])
            if extra_rel > 0:
                radiance = radiance * (1.0 + extra_rel * extra_rng.standard_normal(radiance.shape)).astype(np.float32)
            lin = radiance * np.float32(scale) + np.float32(flare)
            lin = camera_chain.lens_psf(lin, psf, 0.0)
            rng = np.random.default_rng(int(fr["seed"]))
            image = camera_chain.sensor_and_tone(lin, cfg, exposure_ms, gain, rng)
            ok, jpg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])
            assert ok
            stamp = start + int(round(i * 1e9 / 30.0))
            Tm = np.asarray(fr["T_cam_cap"])
            T_cam_cap = Transform.from_matrix(Tm)
            T_cam_head = Transform(T_cam_cap.rotation * scene.R_cap_head, T_cam_cap.translation_m)
            R_frontal_head = scene.R_cam_frontal.inv() * T_cam_head.rotation
            ypr = yaw_pitch_roll_deg(R_frontal_head)
            head = messages.header(ROSBAGS, stamp, "rear_camera_optical")
            bag.write("/rear_camera/camera_info", stamp, messages.camera_info(ROSBAGS, head, camera))
            bag.write("/rear_camera/image_raw/compressed", stamp,
                      messages.compressed_image(ROSBAGS, head, jpg.tobytes()))
            bag.write("/ground_truth/cap_pose", stamp, messages.pose_stamped(ROSBAGS, head, T_cam_cap))
            bag.write("/ground_truth/head_pose", stamp, messages.pose_stamped(ROSBAGS, head, T_cam_head))
            facing, angle = _tag_geometry(model, T_cam_cap)
            v = vis[str(i)]
            tags = [{"id": int(t), "facing": bool(facing[k]), "view_angle_deg": float(angle[k]),
                     "centre_visible": bool(v["centre"][k]) and bool(facing[k]),
                     "corners_visible": int(sum(v["corners"][k])) if facing[k] else 0}
                    for k, t in enumerate(model.ids)]
            Th = np.eye(4)
            Th[:3, :3] = T_cam_head.rotation.as_matrix()
            Th[:3, 3] = T_cam_head.translation_m
            frames_gt.append({
                "index": len(frames_gt), "motion_frame": i, "t_s": i / 30.0, "stamp_ns": stamp,
                "stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9},
                "head_yaw_pitch_roll_deg": [float(x) for x in ypr],
                "T_cam_cap": Tm.tolist(), "T_cam_head": Th.tolist(),
                "visible_tag_ids": [t["id"] for t in tags if t["facing"] and t["centre_visible"]],
                "tags": tags, "render_s": float(v["render_s"]),
            })
    K = camera.K
    truth = {
        "name": name, "resolution": [width, height], "lighting": lighting, "cap_variant": "nominal",
        "fps": 30, "n_frames": len(frames_gt), "jpeg_quality": 95,
        "intrinsics": {"width": width, "height": height, "K": K.tolist(), "fx": K[0, 0], "fy": K[1, 1],
                       "cx": K[0, 2], "cy": K[1, 2], "distortion_model": "plumb_bob", "D": [0.0] * 5,
                       "pixel_convention": "OpenCV: pixel centres at integer coordinates; principal "
                                           "point exactly at (W/2, H/2)"},
        "frames_doc": {"camera": "rear_camera_optical: x right, y down, z forward (OpenCV)",
                       "cap": "C (cap-spec.md)", "head": "H: synth.DriveScene's head frame",
                       "T_cam_X": "4x4, metres, p_cam = T_cam_X @ p_X",
                       "head_angles": "ficap_ros.geometry.metrics yaw/pitch/roll of R_frontal_head (REP-103)"},
        "R_head_cap": R_head_cap.as_matrix().tolist(), "T_head_cap": T_head_cap.tolist(),
        "cap_corners_mm": model.corners_mm.reshape(-1, 3).tolist(),
        "cap_corners_nominal_mm": model.corners_mm.reshape(-1, 3).tolist(),
        "cap_corners_doc": "92 x 3, mm, in C; tag id i -> rows 4i..4i+3 = TL, TR, BR, BL (OpenCV ArUco order)",
        "visibility_doc": "tags[]: facing, view angle (normal vs line of sight), centre and the 4 "
                          "corners ray-cast from the camera centre against the whole scene (bpy)",
        "motion": {"generator": "ficap_ros.tools.synth.naturalistic_drive", "seed": seed, "fps": 30,
                   "every_nth_frame": FRAME_STEP, "first_frame": FRAME_STEP // 2},
        "render": {"engine": "Blender Cycles (CPU, 1 thread)", "blender": "bpy 5.0.1",
                   "samples": SAMPLES, "denoise": False, "pixel_filter": "Blackman-Harris 1.5 px (default)",
                   "light": lighting, "psf_sigma_px": psf, "tone": tone_name,
                   "extra_noise_rel": extra_rel,
                   "noise_model": {"gain": gain, "full_well": cfg.full_well_e, "read_noise_e": cfg.read_noise_e,
                                   "exposure": (f"per frame: 90th percentile of the plates' radiance at "
                                                f"{METER_ON_RENDER[lighting]:.2f} of full well"
                                                if lighting in METER_ON_RENDER else
                                                f"white facing the sun at {WHITE_LEVEL[lighting]:.2f} of full well"),
                                   "flare": flare},
                   "script": "datasets/cycles_render.py"},
        "frames": frames_gt,
    }
    (set_dir / "ground_truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def check(name: str, out: Path) -> None:
    """Detected corners vs projected truth on the written set (a flipped axis or half-pixel shows)."""
    from ficap_ros.geometry.transform import Transform
    from ficap_ros.io.sources import decode_raw, open_frames
    from ficap_ros.vision.detector import TagDetector

    truth = json.loads((out / name / "ground_truth.json").read_text())
    corners_mm = np.asarray(truth["cap_corners_mm"], dtype=np.float64).reshape(-1, 4, 3)
    by_stamp = {int(f["stamp_ns"]): f for f in truth["frames"]}
    det = TagDetector()
    errs = []
    frames = 0
    for raw in open_frames(out / name).raw_frames():
        gt = by_stamp.get(int(raw.stamp_ns))
        if gt is None:
            continue
        frames += 1
        T = Transform.from_matrix(np.asarray(gt["T_cam_cap"]))
        px = raw.camera.project(T.apply(corners_mm.reshape(-1, 3) / 1000.0)).reshape(-1, 4, 2)
        clean = {int(t["id"]) for t in gt["tags"]
                 if t["facing"] and t["corners_visible"] == 4 and t["view_angle_deg"] <= 70.0}
        got = {d.tag_id: d.corners_px for d in det.detect(decode_raw(raw))}
        errs += [got[t] - px[t] for t in sorted(clean) if t in got]
    e = np.concatenate(errs) if errs else np.zeros((0, 2))
    dist = np.linalg.norm(e, axis=1)
    print(f"{name}: {frames} frames, {len(errs)} clean tags detected; corner error median "
          f"{np.median(dist):.3f} px, mean dx {e[:, 0].mean():+.3f} dy {e[:, 1].mean():+.3f} px, "
          f"rms {np.sqrt((dist ** 2).mean()):.3f}", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (default: out/cycles_sets)")
    ap.add_argument("--dev-data", type=Path, default=DEFAULT_DEV,
                    help="blender_dev, for the what-if set at its poses (default: ../shared/data/blender_dev)")
    ap.add_argument("--sets", default=",".join(SET_SPECS))
    ap.add_argument("--frames", type=int, default=None, help="frames per set (default: DEFAULT_FRAMES)")
    ap.add_argument("--check", action="store_true", help="only check the written sets' corners")
    ap.add_argument("--finish-only", action="store_true",
                    help="re-run only the camera chain and the set's files on the rendered radiance")
    args = ap.parse_args()
    import cv2

    cv2.setNumThreads(1)  # leave the other core to whoever shares the machine
    for name in args.sets.split(","):
        if args.check:
            check(name, args.out)
            continue
        n = args.frames or DEFAULT_FRAMES[name]
        work = args.out / "_work" / name
        if name in EXTRA_NOISE:  # made from another set's renders, no rendering of its own
            work = args.out / "_work" / EXTRA_NOISE[name][0]
            finish_set(name, json.loads((work / "plan.json").read_text()), args.out)
            check(name, args.out)
            continue
        if args.finish_only:
            finish_set(name, json.loads((work / "plan.json").read_text()), args.out)
            check(name, args.out)
            continue
        plan = make_plan(name, n, work, args.dev_data)
        t0 = time.perf_counter()
        subprocess.run([str(BPY_PYTHON), str(Path(__file__).resolve()), "_bpy", str(work / "plan.json")],
                       check=True)
        print(f"{name}: rendered {n} frames in {time.perf_counter() - t0:.0f} s", flush=True)
        finish_set(name, plan, args.out)
        check(name, args.out)
    if not args.check:
        # The sets in their order.
        (args.out / "sets.txt").write_text("\n".join(
            n for n in SET_SPECS if (args.out / n / "ground_truth.json").is_file()) + "\n")
    return 0


# ------------------------------------------------------------------------------------------------
# bpy venv: build the scene, render linear radiance, ray-cast visibility (numpy + bpy only)
# ------------------------------------------------------------------------------------------------
def _bl(p_cv) -> tuple[float, float, float]:  # noqa: ANN001
    return (float(p_cv[0]), -float(p_cv[1]), -float(p_cv[2]))


def bpy_render(plan_path: str) -> None:  # pragma: no cover - runs under .venv-bpy only
    import bpy
    from mathutils import Matrix, Vector

    plan = json.loads(Path(plan_path).read_text())
    work = Path(plan["work"])
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = int(plan["samples"])
    sc.cycles.use_adaptive_sampling = False
    sc.cycles.use_denoising = False
    sc.cycles.max_bounces = 4
    sc.render.threads_mode = "FIXED"
    sc.render.threads = 1
    sc.render.use_motion_blur = False
    sc.render.resolution_x, sc.render.resolution_y = int(plan["width"]), int(plan["height"])
    sc.render.resolution_percentage = 100
    sc.render.film_transparent = False
    sc.view_settings.view_transform = "Standard"
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_depth = "32"
    sc.render.image_settings.color_mode = "RGB"

    def material(name: str, albedo: float, texture: np.ndarray | None = None):  # noqa: ANN202
        m = bpy.data.materials.new(name)
        m.use_nodes = True
        nt = m.node_tree
        nt.nodes.clear()
        outn = nt.nodes.new("ShaderNodeOutputMaterial")
        bsdf = nt.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Roughness"].default_value = 0.0  # Lambertian
        bsdf.inputs["Color"].default_value = (albedo, albedo, albedo, 1.0)
        nt.links.new(bsdf.outputs["BSDF"], outn.inputs["Surface"])
        if texture is not None:
            h, w = texture.shape
            img = bpy.data.images.new(name, w, h, float_buffer=True)
            img.colorspace_settings.name = "Non-Color"
            rgba = np.ones((h, w, 4), np.float32)
            rgba[..., :3] = texture[::-1, :, None]  # Blender rows run bottom-up
            img.pixels.foreach_set(rgba.ravel())
            img.pack()
            tex = nt.nodes.new("ShaderNodeTexImage")
            tex.image = img
            tex.interpolation = "Closest"
            tex.extension = "EXTEND"
            nt.links.new(tex.outputs["Color"], bsdf.inputs["Color"])
        return m

    cap = bpy.data.objects.new("cap", None)
    sc.collection.objects.link(cap)
    faces = np.asarray(plan["faces_m"])
    for k, tag_id in enumerate(plan["ids"]):
        me = bpy.data.meshes.new(f"plate_{tag_id}")
        # Corners TL, TR, BR, BL of the face seen from outside; UV (0,1) is the texture's top left.
        me.from_pydata([tuple(p) for p in faces[k]], [], [(0, 3, 2, 1)])
        uv = me.uv_layers.new(name="UVMap")
        uv_of = {0: (0.0, 1.0), 1: (1.0, 1.0), 2: (1.0, 0.0), 3: (0.0, 0.0)}
        for loop in me.loops:
            uv.data[loop.index].uv = uv_of[loop.vertex_index]
        me.materials.append(material(f"tag_{tag_id}", 1.0, np.load(plan["textures"][k])))
        ob = bpy.data.objects.new(f"plate_{tag_id}", me)
        ob.parent = cap
        sc.collection.objects.link(ob)
    for part in plan["cap_parts"]:
        bpy.ops.mesh.primitive_uv_sphere_add(segments=96, ring_count=48, radius=1.0)
        ob = bpy.context.active_object
        ob.name = part["name"]
        bpy.ops.object.shade_smooth()
        ob.scale = part["axes"]
        ob.location = part["centre"]
        ob.data.materials.append(material(part["name"], part["albedo"]))
        ob.parent = cap
    # Car-fixed boxes: the frontal frame's axes x, y, z are the camera's z, -x, -y.
    for box in plan["static_boxes"]:
        hx, hy, hz = box["half_f"]
        bpy.ops.mesh.primitive_cube_add(size=2.0)
        ob = bpy.context.active_object
        ob.name = box["name"]
        ob.scale = (hy, hz, hx)  # Blender world: x = cv x (= -F y), y = -cv y (= F z), z = -cv z (= -F x)
        ob.location = _bl(box["centre"])
        ob.data.materials.append(material(box["name"], box["albedo"]))
    cam_data = bpy.data.cameras.new("cam")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.sensor_width = 36.0
    w, h = int(plan["width"]), int(plan["height"])
    cam_data.lens = float(plan["f_px"]) * 36.0 / w
    # Principal point at OpenCV (W/2, H/2): half a pixel right of and below Blender's image centre.
    cam_data.shift_x = -0.5 / w
    cam_data.shift_y = 0.5 / w
    cam_data.clip_start = 0.01
    cam = bpy.data.objects.new("cam", cam_data)
    sc.collection.objects.link(cam)
    sc.camera = cam
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = float(plan["lights"]["sky"])
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    sc.world = world
    lights = plan["lights"]
    if "lamp" in lights:
        ld = bpy.data.lights.new("lamp", "POINT")
        ld.energy = float(lights["lamp"]["power_w"])
        ld.shadow_soft_size = float(lights["lamp"]["radius_m"])
        lo = bpy.data.objects.new("lamp", ld)
        lo.location = _bl(lights["lamp"]["pos_cv"])
        sc.collection.objects.link(lo)
    if "sun" in lights:
        ld = bpy.data.lights.new("sun", "SUN")
        ld.energy = float(lights["sun"]["strength"])
        ld.angle = math.radians(1.0)
        lo = bpy.data.objects.new("sun", ld)
        toward = Vector(_bl(lights["sun"]["toward_cv"]))
        lo.rotation_euler = toward.to_track_quat("Z", "Y").to_euler()  # the sun shines along -Z
        sc.collection.objects.link(lo)
    spots = []
    for j in range(3):
        ld = bpy.data.lights.new(f"spot{j}", "SPOT")
        ld.shadow_soft_size = 0.01
        ld.spot_blend = 0.4
        lo = bpy.data.objects.new(f"spot{j}", ld)
        sc.collection.objects.link(lo)
        spots.append(lo)

    F = Matrix(F_CV_TO_BL.tolist())
    # Frames already rendered by an earlier run of the same plan are kept (a longer drive with the
    # same seed starts with the same frames, and a frame's render is a function of its plan entry).
    vis_path = work / "vis.json"
    vis: dict[str, dict] = json.loads(vis_path.read_text()) if vis_path.is_file() else {}
    for fr in plan["frames"]:
        i = int(fr["index"])
        if str(i) in vis and (work / f"frame_{i:05d}.npy").is_file() and vis[str(i)].get("plan") == fr:
            continue
        T = Matrix(fr["T_cam_cap"])
        cap.matrix_world = F @ T
        for j, lo in enumerate(spots):
            if j < len(fr["spots"]):
                s = fr["spots"][j]
                lo.hide_render = False
                lo.data.energy = float(s["power_w"])
                lo.data.spot_size = math.radians(float(s["cone_deg"]))
                lo.location = _bl(s["pos_cv"])
                lo.rotation_euler = (Vector(_bl(s["pos_cv"])) - Vector(_bl(s["aim_cv"]))).to_track_quat("Z", "Y").to_euler()
            else:
                lo.hide_render = True
                lo.data.energy = 0.0
        sc.cycles.seed = int(fr["seed"])
        bpy.context.view_layer.update()
        dg = bpy.context.evaluated_depsgraph_get()
        Tn = np.asarray(fr["T_cam_cap"])
        corners, centres = [], []
        for k in range(len(plan["ids"])):
            face = faces[k]
            c_face = face.mean(axis=0)
            tag = c_face + (face - c_face) * (32.0 / 40.0)
            pts = (Tn[:3, :3] @ np.vstack([tag, c_face[None]]).T).T + Tn[:3, 3]
            seen = []
            for p in pts:
                pb = Vector(_bl(p))
                dist = pb.length
                hit = sc.ray_cast(dg, Vector((0.0, 0.0, 0.0)), pb / dist, distance=dist - 5e-4)[0]
                seen.append(0 if hit else 1)
            corners.append(seen[:4])
            centres.append(seen[4])
        path = work / f"frame_{i:05d}.exr"
        sc.render.filepath = str(path)
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        render_s = time.perf_counter() - t0
        img = bpy.data.images.load(str(path))
        px = np.empty(w * h * 4, np.float32)
        img.pixels.foreach_get(px)
        bpy.data.images.remove(img)
        grey = px.reshape(h, w, 4)[::-1, :, 0].copy()  # every material is grey: R = G = B
        np.save(work / f"frame_{i:05d}.npy", grey)
        path.unlink()
        vis[str(i)] = {"corners": corners, "centre": centres, "render_s": render_s, "plan": fr}
        vis_path.write_text(json.dumps(vis))
        print(f"frame {i}: {render_s:.1f} s", flush=True)
    vis_path.write_text(json.dumps(vis))


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "_bpy":
        bpy_render(sys.argv[2])
        sys.exit(0)
    sys.exit(main())

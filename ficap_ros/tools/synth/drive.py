"""Naturalistic driver head motion with exact cap poses (``naturalistic_drive``).

A list of ``DriveFrame`` with the true head orientation in the frontal frame F (x forward, y left,
z up), the head angles and the true cap pose in the camera, from a ``DriveScene`` (camera, frontal
frame, neck pivot, true cap-on-head rotation). It starts with ``frontal_s`` seconds of looking
straight ahead, then mixes frontal driving with glances to the mirrors and the instrument cluster
(minimum-jerk transitions, dwells, small roll and translation). ``naturalistic_motion`` is the same
motion as a continuous function of time, which motion blur integrates over an exposure.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform

__all__ = ["RESOLUTIONS", "MOTIONS", "GLANCE_PEAK_DEG_S", "DriveScene", "DriveFrame",
           "default_scene", "DriveMotion", "naturalistic_motion", "glance_motion", "drive_motion",
           "naturalistic_drive"]

#: Named resolutions of ``default_scene``.
RESOLUTIONS: dict[str, tuple[int, int]] = {
    "360p": (640, 360),
    "540p": (960, 540),
    "720p": (1280, 720),
    "1080p": (1920, 1080),
}


@dataclass(frozen=True)
class DriveScene:
    """Fixed geometry of a driving recording.

    Attributes:
        camera: the rear camera.
        R_cam_frontal: orientation of the frontal frame F (head zero pose: x forward, y left, z up)
            in the camera optical frame.
        p_cam_neck_m: neck pivot (the head turns about it) in the camera optical frame, m.
        neck_to_cap_m: vector from the neck pivot to the cap origin in the head frame H, m.
        R_cap_head: true orientation of the head frame H in the cap frame C (how the cap sits on
            the head; what the pipeline's calibration must recover).
    """

    camera: CameraModel
    R_cam_frontal: Rotation = field(default_factory=lambda: CAM_FROM_FORWARD)
    p_cam_neck_m: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.15, 0.43]))
    neck_to_cap_m: np.ndarray = field(default_factory=lambda: np.array([-0.04, 0.0, 0.13]))
    R_cap_head: Rotation = field(
        default_factory=lambda: Rotation.from_rotvec(np.radians([2.0, -9.0, 3.0]))
    )

    def __post_init__(self) -> None:
        for name in ("p_cam_neck_m", "neck_to_cap_m"):
            v = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1).copy()
            if v.size != 3 or not np.all(np.isfinite(v)):
                raise ConfigError(f"DriveScene.{name} must be 3 finite numbers")
            v.setflags(write=False)
            object.__setattr__(self, name, v)

    def cap_pose(self, R_frontal_head: Rotation, t_frontal_head_m: np.ndarray | None = None) -> Transform:
        """T_cam_cap for a head orientation in F and a head translation in F (m, default none).

        R_cam_cap = R_cam_frontal R_frontal_head R_cap_head^-1; the cap origin is the neck pivot
        plus ``neck_to_cap_m`` turned with the head, plus the translation.
        """
        shift = np.zeros(3) if t_frontal_head_m is None else np.asarray(t_frontal_head_m, np.float64)
        rotation = self.R_cam_frontal * R_frontal_head * self.R_cap_head.inv()
        p_frontal = shift + R_frontal_head.apply(np.array(self.neck_to_cap_m))
        return Transform(rotation, self.p_cam_neck_m + self.R_cam_frontal.apply(p_frontal))


@dataclass(frozen=True)
class DriveFrame:
    """One frame of a drive with its exact ground truth.

    Attributes:
        index: frame number from 0.
        stamp_ns: ``round(index * 1e9 / fps)``.
        R_frontal_head: true head orientation in the frontal frame F.
        ypr_deg: (yaw, pitch, roll) of ``R_frontal_head``, deg (ficap_ros.geometry.metrics convention).
        t_frontal_head_m: head translation (lean) in F, m.
        T_cam_cap: true cap pose in the camera optical frame, m.
        frontal: inside the initial looking-straight-ahead segment (for calibration).
        target: what the head is looking at or moving to: ``frontal``, ``left_mirror``,
            ``right_mirror``, ``rear_mirror`` or ``cluster``.
    """

    index: int
    stamp_ns: int
    R_frontal_head: Rotation
    ypr_deg: np.ndarray
    t_frontal_head_m: np.ndarray
    T_cam_cap: Transform
    frontal: bool
    target: str


def default_scene(resolution: str | tuple[int, int] = "540p") -> DriveScene:
    """The default rear-camera scene.

    A 60 deg hfov pinhole about 0.45 m behind the back of the cap (0.54 m behind the cap origin)
    and 6 cm above it, looking straight forward; the 32 mm centre tag is about 59 px wide at 540p
    when frontal.

    Args:
        resolution: ``'360p'``, ``'540p'``, ``'720p'``, ``'1080p'`` or (width, height).
    """
    if isinstance(resolution, str):
        if resolution not in RESOLUTIONS:
            raise ConfigError(f"unknown resolution {resolution!r}; use {', '.join(RESOLUTIONS)} or (W, H)")
        width, height = RESOLUTIONS[resolution]
    else:
        width, height = (int(v) for v in resolution)
    camera = CameraModel.pinhole(width, height, hfov_deg=60.0)
    neck_to_cap = np.array([-0.04, 0.0, 0.13])
    # Frontal cap origin in F relative to the camera: ahead by 0.45 m + sphere radius, 6 cm lower.
    p_frontal_cap = np.array([0.542, 0.0, -0.06])
    p_cam_neck = CAM_FROM_FORWARD.apply(p_frontal_cap - neck_to_cap)
    return DriveScene(camera=camera, R_cam_frontal=CAM_FROM_FORWARD, p_cam_neck_m=p_cam_neck,
                      neck_to_cap_m=neck_to_cap)


def _min_jerk(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10.0 - 15.0 * s + 6.0 * s * s)


# Glance targets: (label, sampler of (yaw, pitch, roll deg, tx, ty, tz m)); REP-103 angles: yaw
# positive to the left, pitch positive nose down (the cluster is below: +20), roll positive to the
# right shoulder.
def _glance_target(label: str, rng: np.random.Generator) -> np.ndarray:
    u = rng.uniform
    if label == "left_mirror":
        return np.array([u(45, 60), u(2, 8), u(-4, 0), u(0.0, 0.01), u(0.005, 0.02), 0.0])
    if label == "right_mirror":
        return np.array([u(-60, -45), u(2, 8), u(0, 4), u(0.0, 0.01), u(-0.02, -0.005), 0.0])
    if label == "rear_mirror":
        return np.array([u(-28, -22), u(-7, -3), u(-2, 2), u(0.0, 0.01), u(-0.01, 0.0), u(0.0, 0.01)])
    if label == "cluster":
        return np.array([u(-4, 4), u(17, 23), u(-1.5, 1.5), u(0.005, 0.015), 0.0, u(-0.01, 0.0)])
    raise ConfigError(f"unknown glance target {label!r}")


@dataclass(frozen=True)
class DriveMotion:
    """Naturalistic head motion as a continuous function of time (see ``naturalistic_motion``).

    Attributes:
        scene: the geometry the cap poses are computed in.
        frontal_s: length of the initial looking-straight-ahead segment, s.
        segments: (t_start_s, t_end_s, pose_from, pose_to, label) keyframe segments; a pose is
            (yaw, pitch, roll deg, tx, ty, tz m) in F, interpolated with the minimum-jerk profile.
        sway: (amplitudes (6, 2), frequencies Hz (6, 2), phases rad (6, 2)) of the natural sway
            added to every pose.
    """

    scene: DriveScene
    frontal_s: float
    segments: tuple[tuple[float, float, np.ndarray, np.ndarray, str], ...]
    sway: tuple[np.ndarray, np.ndarray, np.ndarray]

    def pose_vector_at(self, t_s: float) -> tuple[np.ndarray, str]:
        """(yaw, pitch, roll deg, tx, ty, tz m) of the head in F at time ``t_s``, and the label."""
        starts = [seg[0] for seg in self.segments]
        j = int(np.searchsorted(starts, t_s, side="right") - 1)
        t0, t1, p0, p1, label = self.segments[max(j, 0)]
        s = _min_jerk(np.array((t_s - t0) / (t1 - t0) if t1 > t0 else 1.0))
        p = p0 + (p1 - p0) * float(s)
        amps, freqs, phases = self.sway
        return p + np.sum(amps * np.sin(2 * math.pi * freqs * t_s + phases), axis=1), label

    def T_cam_cap_at(self, t_s: float) -> Transform:
        """The true cap pose in the camera at time ``t_s`` (s from the drive's start)."""
        p, _ = self.pose_vector_at(t_s)
        return self.scene.cap_pose(rotation_from_ypr_deg(*p[:3]), p[3:])

    def cap_velocity_at(self, t_s: float, h_s: float = 1e-4) -> np.ndarray:
        """The cap's true velocity at ``t_s`` as ``CapPose.velocity`` gives it: (6,), ROS twist
        order in the camera's axes: the cap origin's linear velocity (m/s), then the angular
        velocity (rad/s: ``R(t + dt) = exp([w] dt) R(t)``); central differences over ``h_s``."""
        a, b = self.T_cam_cap_at(t_s - h_s), self.T_cam_cap_at(t_s + h_s)
        v = (b.translation_m - a.translation_m) / (2.0 * h_s)
        w = (b.rotation * a.rotation.inv()).as_rotvec() / (2.0 * h_s)
        return np.concatenate([v, w])

    def angular_speed_deg_s(self, t_s: float) -> float:
        """The head's (and cap's) angular speed at ``t_s``, deg/s."""
        return float(np.degrees(np.linalg.norm(self.cap_velocity_at(t_s)[3:])))

    def around(self, t_s: float) -> Callable[[float], Transform]:
        """The pose function ``render`` integrates over an exposure centred on ``t_s``:
        ``dt`` (s from mid-exposure) -> T_cam_cap."""
        return lambda dt_s: self.T_cam_cap_at(t_s + dt_s)

    def frame(self, index: int, fps: float) -> DriveFrame:
        """Frame ``index`` of the drive at ``fps`` (its truth is the pose at ``index / fps``)."""
        ts = index / fps
        p, label = self.pose_vector_at(ts)
        ypr = p[:3].copy()
        R_frontal_head = rotation_from_ypr_deg(*ypr)
        return DriveFrame(
            index=index,
            stamp_ns=int(round(index * 1e9 / fps)),
            R_frontal_head=R_frontal_head,
            ypr_deg=ypr,
            t_frontal_head_m=p[3:].copy(),
            T_cam_cap=self.scene.cap_pose(R_frontal_head, p[3:]),
            frontal=ts < self.frontal_s,
            target=label,
        )


def naturalistic_motion(
    duration_s: float, seed: int = 0, scene: DriveScene | None = None, frontal_s: float = 3.0,
) -> DriveMotion:
    """The continuous head motion behind ``naturalistic_drive`` (same seed, same motion).

    ``naturalistic_drive(n, fps, seed, scene, frontal_s)[i]`` equals
    ``naturalistic_motion(n / fps, seed, scene, frontal_s).frame(i, fps)``; the motion also
    answers between frames (``T_cam_cap_at``, ``around``), which motion blur needs.

    Args:
        duration_s: keyframes are drawn until this time (later times hold the last pose).
        seed: random seed.
        scene: geometry (default ``default_scene()``).
        frontal_s: length of the initial frontal segment, s.
    """
    if not duration_s >= 0 or not frontal_s >= 0:
        raise ConfigError("naturalistic_motion needs duration_s >= 0 and frontal_s >= 0")
    scene = scene or default_scene()
    rng = np.random.default_rng(seed)
    # Natural sway: two slow sinusoids per axis, under 0.3 deg and 2 mm each (drawn first, so a
    # longer drive with the same seed starts with the same frames).
    freqs = rng.uniform(0.08, 0.5, (6, 2))
    phases = rng.uniform(0.0, 2 * math.pi, (6, 2))
    amps = np.concatenate([rng.uniform(0.1, 0.3, (3, 2)), rng.uniform(0.0005, 0.002, (3, 2))])
    # Keyframes: piecewise min-jerk between poses p = (yaw, pitch, roll, tx, ty, tz).
    # Each segment: (t_start, t_end, pose_from, pose_to, label).
    segments: list[tuple[float, float, np.ndarray, np.ndarray, str]] = []
    pose = np.zeros(6)
    t = frontal_s
    segments.append((0.0, t, pose, pose, "frontal"))
    labels = ["left_mirror", "right_mirror", "rear_mirror", "cluster"]
    bag: list[str] = []
    while t < duration_s:
        # Frontal driving: drift to a slightly off-centre frontal pose, dwell.
        wander = np.array([rng.normal(0, 2.0), rng.normal(0, 1.5), rng.normal(0, 1.0),
                           rng.normal(0, 0.004), rng.normal(0, 0.004), rng.normal(0, 0.003)])
        move = 0.35 + 0.006 * float(np.abs(wander[:3] - pose[:3]).max())
        dwell = rng.uniform(1.5, 4.0)
        segments.append((t, t + move, pose, wander, "frontal"))
        segments.append((t + move, t + move + dwell, wander, wander, "frontal"))
        pose, t = wander, t + move + dwell
        if not bag:
            bag = list(rng.permutation(labels))
        label = bag.pop()
        target = _glance_target(label, rng)
        move = 0.35 + 0.006 * float(np.abs(target[:3] - pose[:3]).max())
        dwell = rng.uniform(0.4, 1.2)
        segments.append((t, t + move, pose, target, label))
        segments.append((t + move, t + move + dwell, target, target, label))
        pose, t = target, t + move + dwell
    return DriveMotion(scene=scene, frontal_s=float(frontal_s), segments=tuple(segments),
                       sway=(amps, freqs, phases))


#: Peak head angular speeds of ``glance_motion``'s turns, deg/s (drawn uniformly per turn).
GLANCE_PEAK_DEG_S = (150.0, 250.0)


def _turn_s(pose_from: np.ndarray, pose_to: np.ndarray, peak_deg_s: float) -> float:
    """How long a minimum-jerk turn between two poses (yaw, pitch, roll deg, ...) takes to peak
    at ``peak_deg_s``: its path sampled at unit duration, the fastest geodesic rate scaled."""
    s = _min_jerk(np.linspace(0.0, 1.0, 201))
    path = [rotation_from_ypr_deg(*(pose_from[:3] + (pose_to[:3] - pose_from[:3]) * float(k)))
            for k in s]
    rate = max(np.degrees((b * a.inv()).magnitude()) for a, b in zip(path, path[1:])) * 200.0
    return max(float(rate) / peak_deg_s, 1e-3)


def glance_motion(
    duration_s: float, seed: int = 0, scene: DriveScene | None = None, frontal_s: float = 3.0,
    peak_deg_s: tuple[float, float] = GLANCE_PEAK_DEG_S,
) -> DriveMotion:
    """Glance-heavy head motion: the hardest stretches of a drive for the labels, back to back.

    After ``frontal_s`` seconds looking straight ahead (natural sway, as ``naturalistic_motion``),
    glances follow each other: a turn to a target of ``naturalistic_motion``'s (each block of four
    visits the left and right mirrors, the rear-view mirror and the cluster), 0.2-0.6 s there, the
    turn back and 0.3-0.8 s looking ahead (a degree or two off centre). Every turn follows the
    minimum-jerk profile and peaks at an angular speed drawn uniformly from ``peak_deg_s``: the
    side mirrors' turns take 0.4-0.7 s, the rear-view mirror's and the cluster's 0.1-0.3 s.

    Args:
        duration_s, seed, scene, frontal_s: as ``naturalistic_motion``.
        peak_deg_s: (low, high) peak angular speed of the turns, deg/s.
    """
    if not duration_s >= 0 or not frontal_s >= 0 or not 0 < peak_deg_s[0] <= peak_deg_s[1]:
        raise ConfigError("glance_motion needs duration_s >= 0, frontal_s >= 0 and "
                          "0 < peak_deg_s[0] <= peak_deg_s[1]")
    scene = scene or default_scene()
    rng = np.random.default_rng(seed)
    freqs = rng.uniform(0.08, 0.5, (6, 2))
    phases = rng.uniform(0.0, 2 * math.pi, (6, 2))
    amps = np.concatenate([rng.uniform(0.1, 0.3, (3, 2)), rng.uniform(0.0005, 0.002, (3, 2))])
    pose = np.zeros(6)
    t = frontal_s
    segments: list[tuple[float, float, np.ndarray, np.ndarray, str]] = [(0.0, t, pose, pose, "frontal")]
    labels = ["left_mirror", "right_mirror", "rear_mirror", "cluster"]
    bag: list[str] = []
    while t < duration_s:
        for label in (None, "frontal"):
            if label is None:
                bag = bag or list(rng.permutation(labels))
                label = str(bag.pop())
                target, dwell = _glance_target(label, rng), rng.uniform(0.2, 0.6)
            else:
                target = np.array([rng.normal(0, 1.0), rng.normal(0, 1.0), rng.normal(0, 0.5),
                                   rng.normal(0, 0.003), rng.normal(0, 0.003), 0.0])
                dwell = rng.uniform(0.3, 0.8)
            move = _turn_s(pose, target, rng.uniform(*peak_deg_s))
            segments.append((t, t + move, pose, target, label))
            segments.append((t + move, t + move + dwell, target, target, label))
            pose, t = target, t + move + dwell
    return DriveMotion(scene=scene, frontal_s=float(frontal_s), segments=tuple(segments),
                       sway=(amps, freqs, phases))


#: Head motions of a drive by name (``drive_motion``).
MOTIONS = ("naturalistic", "glances")


def drive_motion(kind: str, duration_s: float, seed: int = 0, scene: DriveScene | None = None,
                 frontal_s: float = 3.0) -> DriveMotion:
    """The head motion named ``kind`` (``MOTIONS``): ``naturalistic_motion`` or
    ``glance_motion``."""
    if kind == "naturalistic":
        return naturalistic_motion(duration_s, seed, scene, frontal_s)
    if kind == "glances":
        return glance_motion(duration_s, seed, scene, frontal_s)
    raise ConfigError(f"unknown head motion {kind!r}; expected one of {', '.join(MOTIONS)}")


def naturalistic_drive(
    n_frames: int, fps: float = 30.0, seed: int = 0, scene: DriveScene | None = None,
    frontal_s: float = 3.0,
) -> list[DriveFrame]:
    """Naturalistic driver head motion with exact cap poses.

    The first ``frontal_s`` seconds look straight ahead (natural sway under 1 deg). Then frontal
    driving (a few degrees of wander, 1.5-4 s dwells) alternates with glances in random order, each
    block of four glances visiting the left mirror (yaw +45..+60), the right mirror (-45..-60), the
    rear-view mirror (about -25 yaw, 5 deg up: pitch -5, REP-103) and the instrument cluster (20 deg
    down: pitch +20), with small roll and 1-2 cm of lean. Transitions follow the minimum-jerk profile 10s^3 - 15s^4 + 6s^5 and
    take 0.35 s + 6 ms per degree; the head turns about the neck pivot of ``scene``. For motion
    blur, render with ``naturalistic_motion(...).around(frame.stamp_ns / 1e9)`` instead of the
    frame's pose (same seed, same motion).

    Args:
        n_frames: number of frames.
        fps: frame rate, Hz.
        seed: random seed (the whole drive is a function of the arguments).
        scene: geometry (default ``default_scene()``).
        frontal_s: length of the initial frontal segment, s.

    Returns:
        ``n_frames`` ``DriveFrame`` s.
    """
    if n_frames < 0 or not fps > 0 or frontal_s < 0:
        raise ConfigError("naturalistic_drive needs n_frames >= 0, fps > 0 and frontal_s >= 0")
    motion = naturalistic_motion(n_frames / fps, seed, scene, frontal_s)
    return [motion.frame(index, fps) for index in range(n_frames)]

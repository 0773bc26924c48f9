"""Cap-to-head calibration (the paper's section 3.3): how the cap sits on the head.

Frames (all right-handed):
    C  cap frame (x forward/nose, y left, z up, origin at the cap sphere centre).
    H  head frame (x forward, y left, z up); its origin is taken at the cap origin.
    F  frontal frame: the head's zero pose, usually the vehicle's axes (x forward, y left, z up).
    cam  camera optical frame (x right, y down, z forward).
    ref  the frame a reference head-pose source (face tracker, laser rig) reports in.

Two ways to find ``R_cap_head``:
    * frontal: the wearer looks straight ahead for a few seconds. Then ``R_cam_head = R_cam_frontal``
      in every frame, so ``R_cap_head_i = R_cam_cap_i^-1 R_cam_frontal``, robustly averaged.
    * reference: a reference source gives ``R_ref_head_i`` for frames paired by stamp. The unknown
      ``R_cap_head`` (Y) and ``R_cam_reference`` (X) satisfy ``X R_ref_head_i = R_cam_cap_i Y`` (the
      robot-world/hand-eye form ``A X = Z B``), solved by OpenCV's ``calibrateRobotWorldHandEye``
      and refined by robust nonlinear least squares. The reference's head frame must use the same
      axes as H (x forward, y left, z up).

Pure core: no files, no ROS; the live node, ``ficap calibrate`` and replay share it. Calibration
files are ``ficap_ros.io.calibration_file``'s; the node's calibration state is
``ficap_ros.ros.live_calibration``'s; the head pose of a frame is composed in ``ficap_ros.io.labels``.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ficap_ros.errors import CalibrationError
from ficap_ros.geometry.metrics import angle_deg, robust_mean_rotation
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.stamps import pair_by_stamp, window_mask

__all__ = [
    "HeadCalibration",
    "CalibrationResult",
    "MIN_RELIABILITY",
    "frontal_frames",
    "reference_pairs",
    "calibrated_frontal",
    "CalibrationRecorder",
    "calibrate_frontal",
    "calibrate_reference",
    "frontal_from_camera_mount",
]

#: Least rotation excursion of the reference (second singular value of the rotation vectors about
#: their mean, RMS degrees) that makes the reference problem well posed: with the head held still
#: any rotation about the motion axis can move between X and Y.
MIN_REFERENCE_EXCITATION_DEG = 2.0


@dataclass(frozen=True)
class HeadCalibration:
    """How the cap sits on the head, and how the head's zero pose sits in the camera.

    Attributes:
        R_cap_head: orientation of the head frame H (x forward, y left, z up) in the cap frame C.
            Identity until calibrated.
        R_cam_frontal: orientation of the frontal frame F (the head's zero pose: x forward, y left,
            z up, usually the vehicle's axes) in the camera optical frame. Default: the camera looks
            straight forward, so F's x is the optical axis.
        calibrated: whether ``R_cap_head`` came from a calibration.
    """

    R_cap_head: Rotation = field(default_factory=Rotation.identity)
    R_cam_frontal: Rotation = field(default_factory=lambda: CAM_FROM_FORWARD)
    calibrated: bool = False


@dataclass(frozen=True)
class CalibrationResult:
    """A computed cap-to-head calibration.

    Attributes:
        R_cap_head: orientation of the head frame H in the cap frame C.
        frames_used: frames (frontal) or pairs (reference) kept as inliers.
        spread_deg: RMS geodesic residual of the kept frames, degrees. Frontal: angle between each
            frame's R_cap_head_i and the mean (how still and how frontal the wearer was).
            Reference: angle of ``(X R_ref_head_i)^-1 R_cam_cap_i Y`` (reference noise + cap noise).
        mode: ``frontal`` or ``reference``.
        R_cam_reference: orientation of the reference frame in the camera optical frame
            (reference mode only, else None).
        uncertainty_deg: predicted 1-sigma error of ``R_cap_head`` about its worst axis, degrees
            (frontal: spread / sqrt(frames); reference: Gauss-Newton covariance of the fit).
    """

    R_cap_head: Rotation
    frames_used: int
    spread_deg: float
    mode: str
    R_cam_reference: Rotation | None = None
    uncertainty_deg: float = float("nan")


def frontal_from_camera_mount(T_parent_cam: Transform | None) -> Rotation:
    """R_cam_frontal: the frontal frame F (x forward, y left, z up) in the camera optical frame.

    F takes the axes of the camera mount's parent frame (the vehicle's ``base_link`` in REP-103's
    x forward, y left, z up): ``T_parent_cam`` is the ``camera_mount`` transform, the camera's
    optical frame in that frame (``static_transform_publisher``'s convention). Without a mount the
    camera is taken to look straight ahead: ``CAM_FROM_FORWARD``.
    """
    if T_parent_cam is None:
        return CAM_FROM_FORWARD
    return T_parent_cam.rotation.inv()


#: Frames less reliable than this are left out of a frontal calibration, live and offline (the
#: node's ``calibration.min_reliability`` default).
MIN_RELIABILITY = 0.5


def frontal_frames(stamps_ns: np.ndarray, reliability: np.ndarray, window_ns: tuple[int, int],
                   min_reliability: float = MIN_RELIABILITY) -> np.ndarray:
    """Indices of the frames a frontal calibration uses: in the window (``ficap_ros.stamps``'
    ``window_from_start_ns`` offline, ``last_window_ns`` live) and at least ``min_reliability``
    reliable (NaN reliability counts as reliable: labels of other tools may not carry it)."""
    rel = np.asarray(reliability, dtype=np.float64)
    ok = window_mask(stamps_ns, window_ns) & ~(rel < min_reliability)
    return np.nonzero(ok)[0]


def reference_pairs(cap_stamps_ns: np.ndarray, ref_stamps_ns: np.ndarray, max_dt_ns: int,
                    first: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(i_cap, i_ref) of the cap poses and reference poses a reference calibration pairs: nearest
    stamps within ``max_dt_ns``, one-to-one (``ficap_ros.stamps.pair_by_stamp``), in cap order;
    only the first ``first`` pairs when ``first`` > 0. Both stamp arrays must be sorted."""
    i_cap, i_ref = pair_by_stamp(cap_stamps_ns, ref_stamps_ns, max_dt_ns)
    if first > 0:
        i_cap, i_ref = i_cap[:first], i_ref[:first]
    return i_cap, i_ref


def calibrated_frontal(result: CalibrationResult | None, T_parent_cam: Transform | None) -> Rotation:
    """R_cam_frontal to use with a calibration: the one rule of the node, the CLI and replay.

    A ``camera_mount`` (``T_parent_cam``) fixes the frontal frame to its parent's axes. Without
    one, a reference calibration makes the reference frame the frontal frame (head angles then
    read in the reference's axes, comparable with it); otherwise the camera looks straight ahead.
    """
    if T_parent_cam is None and result is not None and result.R_cam_reference is not None:
        return result.R_cam_reference
    return frontal_from_camera_mount(T_parent_cam)


class CalibrationRecorder:
    """Cap poses and reference head poses by stamp, kept for a calibration (thread-safe: the
    node's worker adds frames while its service thread calibrates).

    Args:
        max_frames: most cap poses (and reference poses) kept; the oldest go first.
    """

    def __init__(self, max_frames: int = 20000) -> None:
        self._lock = threading.Lock()
        self._caps: deque[tuple[int, np.ndarray, float]] = deque(maxlen=max_frames)
        self._refs: deque[tuple[int, np.ndarray]] = deque(maxlen=max_frames)

    def add_cap(self, stamp_ns: int, R_cam_cap: Rotation, reliability: float) -> None:
        with self._lock:
            self._caps.append((int(stamp_ns), R_cam_cap.as_quat(), float(reliability)))

    def add_reference(self, stamp_ns: int, q_xyzw: np.ndarray) -> None:
        with self._lock:
            self._refs.append((int(stamp_ns), np.asarray(q_xyzw, dtype=np.float64)))

    @property
    def references(self) -> int:
        with self._lock:
            return len(self._refs)

    def _caps_sorted(self) -> list[tuple[int, np.ndarray, float]]:
        with self._lock:
            caps = list(self._caps)
        caps.sort(key=lambda e: e[0])
        return caps

    def frontal(self, window_s: float, R_cam_frontal: Rotation, min_frames: int,
                max_spread_deg: float, min_reliability: float = MIN_RELIABILITY) -> CalibrationResult:
        """``calibrate_frontal`` over the reliable frames of the last ``window_s`` seconds."""
        from ficap_ros.stamps import last_window_ns

        caps = [c for c in self._caps_sorted() if not c[2] < min_reliability]
        if not caps:
            raise CalibrationError("no reliable frames buffered for frontal calibration")
        stamps = np.array([c[0] for c in caps], dtype=np.int64)
        sel = frontal_frames(stamps, np.array([c[2] for c in caps]),
                             last_window_ns(int(stamps[-1]), window_s), min_reliability)
        if sel.size == 0:
            raise CalibrationError("no reliable frames in the calibration window")
        return calibrate_frontal(Rotation.from_quat(np.array([caps[i][1] for i in sel])),
                                 R_cam_frontal, min_frames=min_frames,
                                 max_spread_deg=max_spread_deg)

    def pairs(self, max_dt_ns: int, max_pairs: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(q_cam_cap, q_ref_head), (N, 4) xyzw each, of the poses ``reference_pairs`` pairs.

        Raises:
            CalibrationError: no cap pose or no reference pose recorded.
        """
        caps = self._caps_sorted()
        with self._lock:
            refs = sorted(self._refs, key=lambda e: e[0])
        if not caps or not refs:
            raise CalibrationError(
                f"reference mode has {len(caps)} cap poses and {len(refs)} reference poses")
        i_cap, i_ref = reference_pairs(np.array([c[0] for c in caps], dtype=np.int64),
                                       np.array([r[0] for r in refs], dtype=np.int64),
                                       max_dt_ns, max_pairs)
        return (np.array([caps[i][1] for i in i_cap]).reshape(-1, 4),
                np.array([refs[i][1] for i in i_ref]).reshape(-1, 4))

    def reference(self, max_dt_ns: int, min_pairs: int, max_pairs: int = 0) -> CalibrationResult:
        """``calibrate_reference`` over the cap and reference poses paired by stamp."""
        q_cap, q_ref = self.pairs(max_dt_ns, max_pairs)
        if len(q_cap) < min_pairs:
            raise CalibrationError(
                f"reference mode matched {len(q_cap)} pairs by stamp, needs {min_pairs}")
        return calibrate_reference(Rotation.from_quat(q_cap), Rotation.from_quat(q_ref),
                                   min_pairs=min_pairs)


def _count(rotations: Rotation) -> int:
    return 1 if rotations.single else len(rotations)


def _as_stack(rotations: Rotation) -> Rotation:
    return Rotation.concatenate([rotations]) if rotations.single else rotations


def calibrate_frontal(
    R_cam_cap: Rotation,
    R_cam_frontal: Rotation,
    min_frames: int = 30,
    max_spread_deg: float = 3.0,
) -> CalibrationResult:
    """R_cap_head from frames in which the wearer looked straight ahead.

    Args:
        R_cam_cap: stacked cap orientations in the camera optical frame.
        R_cam_frontal: the frontal frame in the camera frame (``frontal_from_camera_mount``).
        min_frames: least number of inlier frames.
        max_spread_deg: largest accepted RMS geodesic residual of the inliers, degrees.
    Returns:
        The calibration (``spread_deg`` = RMS angle of the inliers to the robust mean).
    Raises:
        CalibrationError: too few frames or inliers, or the spread is too large.
    """
    n = _count(R_cam_cap)
    if n < min_frames:
        raise CalibrationError(f"frontal calibration needs {min_frames} frames, got {n}")
    per_frame = _as_stack(R_cam_cap).inv() * R_cam_frontal
    mean, inliers = robust_mean_rotation(per_frame)
    used = int(np.count_nonzero(inliers))
    if used < min_frames:
        raise CalibrationError(
            f"frontal calibration kept {used} of {n} frames as inliers, needs {min_frames}"
        )
    resid = np.atleast_1d(angle_deg(mean, per_frame[inliers]))
    spread = float(np.sqrt(np.mean(resid**2)))
    if spread > max_spread_deg:
        raise CalibrationError(
            f"frontal calibration spread {spread:.2f} deg exceeds {max_spread_deg:.2f} deg "
            "(the head moved or was not frontal)"
        )
    return CalibrationResult(mean, used, spread, "frontal", None, spread / math.sqrt(used))


def _hand_eye_initial(A: Rotation, B: Rotation) -> tuple[Rotation, Rotation]:
    """Closed-form start of ``Z B_i = A_i X`` (OpenCV's robot-world/hand-eye, Shah's method).

    Returns (X, Z) = (R_cap_head, R_cam_reference).
    """
    import cv2  # local: keep import of the module light

    zeros = [np.zeros((3, 1)) for _ in range(len(A))]
    R_base2world, _, R_gripper2cam, _ = cv2.calibrateRobotWorldHandEye(
        list(A.as_matrix()), zeros, list(B.as_matrix()), zeros,
        method=cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH,
    )
    return Rotation.from_matrix(R_base2world), Rotation.from_matrix(R_gripper2cam)


def calibrate_reference(
    R_cam_cap: Rotation,
    R_ref_head: Rotation,
    min_pairs: int = 10,
    loss_scale_deg: float = 2.0,
) -> CalibrationResult:
    """R_cap_head and R_cam_reference together from a reference head-pose source.

    Solves ``R_cam_reference R_ref_head_i = R_cam_cap_i R_cap_head`` for pairs matched by stamp:
    OpenCV's ``calibrateRobotWorldHandEye`` (Shah) as the start, then ``least_squares`` over both
    rotation vectors with a soft-L1 loss so gross reference failures do not pull the answer.
    Accuracy is limited by the head motion: rotation of Y about an axis the head barely turned
    about is only seen through the other axes, so the calibration session should look around in
    yaw *and* pitch (``uncertainty_deg`` of the result says how well it worked).

    Args:
        R_cam_cap: stacked cap orientations in the camera optical frame.
        R_ref_head: stacked reference head orientations, paired element-wise with ``R_cam_cap``.
        min_pairs: least number of pairs.
        loss_scale_deg: least residual size beyond which the loss grows linearly, degrees (the
            scale used is the larger of this and 3x the robust residual sigma at the start).
    Returns:
        The calibration; ``frames_used`` = pairs whose residual is within 3x the RMS of the median,
        ``spread_deg`` = RMS residual over those pairs.
    Raises:
        CalibrationError: too few pairs, different lengths, or too little head motion to separate
            the two rotations.
    """
    A, B = _reference_pairs_checked(R_cam_cap, R_ref_head, min_pairs)
    residuals = _reference_residuals(A, B)
    x0 = np.concatenate([r.as_rotvec() for r in _reference_start(A, B)])
    # Soft-L1 beyond 3 sigma of the start's residuals (robust MAD estimate): about as efficient as
    # least squares for Gaussian reference noise, while gross reference failures stay bounded.
    sigma0 = float(np.median(np.abs(residuals(x0)))) / 0.6745
    f_scale = max(loss_scale_deg, 3.0 * sigma0) if np.isfinite(sigma0) else loss_scale_deg
    x = least_squares(residuals, x0, loss="soft_l1", f_scale=f_scale, x_scale=1.0).x
    resid = np.linalg.norm(residuals(x).reshape(-1, 3), axis=1)
    rms_med = max(float(np.median(resid)), 1e-9)
    keep = resid <= 3.0 * rms_med + 1e-9
    spread = float(np.sqrt(np.mean(resid[keep] ** 2)))
    return CalibrationResult(Rotation.from_rotvec(x[:3]), int(np.count_nonzero(keep)), spread,
                             "reference", Rotation.from_rotvec(x[3:]),
                             _reference_uncertainty_deg(residuals, x, keep))


def _reference_pairs_checked(R_cam_cap: Rotation, R_ref_head: Rotation,
                             min_pairs: int) -> tuple[Rotation, Rotation]:
    """The paired rotations as stacks, checked: as many of each, ``min_pairs`` at least, and head
    motion about two axes (else a rotation about the one axis could move between X and Y)."""
    n = _count(R_cam_cap)
    if _count(R_ref_head) != n:
        raise CalibrationError(
            f"reference calibration needs paired rotations, got {n} cap and "
            f"{_count(R_ref_head)} reference"
        )
    if n < min_pairs:
        raise CalibrationError(f"reference calibration needs {min_pairs} pairs, got {n}")
    B = _as_stack(R_ref_head)
    rv = (B.mean().inv() * B).as_rotvec(degrees=True)
    sv = np.linalg.svd(rv - rv.mean(axis=0), compute_uv=False) / math.sqrt(n)
    if sv[1] < MIN_REFERENCE_EXCITATION_DEG:
        raise CalibrationError(
            f"reference calibration needs head rotation about two axes: motion spread "
            f"{sv[0]:.1f}/{sv[1]:.1f} deg, needs {MIN_REFERENCE_EXCITATION_DEG:.1f} deg on the second"
        )
    return _as_stack(R_cam_cap), B


def _reference_start(A: Rotation, B: Rotation) -> tuple[Rotation, Rotation]:
    """(Y, X) = (R_cap_head, R_cam_reference) to start the fit from: OpenCV's closed form, or the
    mean rotations and the identity where it fails or gives no finite answer."""
    try:
        Y0, X0 = _hand_eye_initial(A, B)
    except Exception:  # noqa: BLE001 - OpenCV's solver can fail on odd data; start elsewhere
        Y0 = A.mean().inv() * B.mean()
        X0 = Rotation.identity()
    if not (np.all(np.isfinite(Y0.as_quat())) and np.all(np.isfinite(X0.as_quat()))):
        Y0, X0 = A.mean().inv() * B.mean(), Rotation.identity()
    return Y0, X0


def _reference_residuals(A: Rotation, B: Rotation) -> Callable[[np.ndarray], np.ndarray]:
    """Residuals (3 per pair, deg) of ``X B_i = A_i Y`` at the parameters (rotvec Y, rotvec X)."""
    def residuals(params: np.ndarray) -> np.ndarray:
        Y = Rotation.from_rotvec(params[:3])
        X = Rotation.from_rotvec(params[3:])
        return np.degrees(((X * B).inv() * (A * Y)).as_rotvec()).reshape(-1)

    return residuals


def _reference_uncertainty_deg(residuals: Callable[[np.ndarray], np.ndarray], x: np.ndarray,
                               keep: np.ndarray) -> float:
    """1-sigma error of Y about its worst axis, deg: the covariance of the parameters from the
    plain (unweighted) central-difference Jacobian of the kept pairs (inf when singular)."""
    rows = np.repeat(keep, 3)
    step = 1e-6
    jac = np.empty((int(rows.sum()), 6))
    for j in range(6):
        dx = np.zeros(6)
        dx[j] = step
        jac[:, j] = (residuals(x + dx)[rows] - residuals(x - dx)[rows]) / (2 * step)
    dof = max(int(rows.sum()) - 6, 1)
    s2 = float(np.sum(residuals(x)[rows] ** 2)) / dof
    try:
        cov = s2 * np.linalg.inv(jac.T @ jac)
        return float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0))))
    except np.linalg.LinAlgError:
        return float("inf")

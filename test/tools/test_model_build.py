"""As-built cap model by bundle adjustment: recovery of a perturbed cap from frames with exact truth,
with unbiased corners and with corners biased inward and outward (the scale must not come from the
tag side alone), the builder's own doubts, and the replay check against the nominal model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError, ModelError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel, load_model, nominal_model
from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.tools.model_build import (
    BuildConfig,
    CoverageError,
    align_model,
    assembly_size_sigma,
    build_model,
    depth_change_limit,
    edge_shift_px,
    replay_check,
    size_ratio,
    tag_frames,
)
from ficap_ros.vision.detector import TagDetection
from ficap_ros.vision.pose import estimate_cap_pose

CAMERA = CameraModel.pinhole(1280, 960, hfov_deg=60.0)


def perturbed_model(seed: int, shift_rms_mm: float = 0.5, turn_sigma_deg: float = 1.0) -> CapModel:
    """The nominal cap with every tag shifted (``shift_rms_mm`` rms) and turned about its normal.

    The result is aligned to the nominal (the unobservable rigid motion of the whole cap removed),
    so it can be compared with a built model directly.
    """
    rng = np.random.default_rng(seed)
    nom = nominal_model()
    corners = []
    for c, centre, normal in zip(nom.corners_mm, nom.centres_mm, nom.normals):
        turn = Rotation.from_rotvec(normal * np.radians(rng.normal(0.0, turn_sigma_deg)))
        shift = rng.normal(0.0, shift_rms_mm / np.sqrt(3.0), 3)
        corners.append(turn.apply(c - centre) + centre + shift)
    corners = np.array(corners)
    return CapModel(nom.ids, align_model(corners, nom.corners_mm).apply(corners))


def observe(model: CapModel, count: int, seed: int, noise_px: float = 0.15,
            camera: CameraModel = CAMERA) -> list[tuple[Transform, list[TagDetection]]]:
    """Frames of a cap turning in front of a rear camera: exact projections plus pixel noise.

    A tag is seen when it faces the camera (more than ~20 deg from edge-on) and lies in the image.
    """
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(count):
        yaw, pitch, roll = rng.uniform([-45.0, -25.0, -20.0], [45.0, 25.0, 20.0])
        rotation = CAM_FROM_FORWARD * rotation_from_ypr_deg(yaw, pitch, roll)
        t_m = np.array([rng.uniform(-0.04, 0.04), rng.uniform(-0.04, 0.04), rng.uniform(0.45, 0.7)])
        T = Transform(rotation, t_m)
        dets = []
        for tag_id, corners, centre, normal in zip(model.ids, model.corners_mm, model.centres_mm,
                                                   model.normals):
            c_cam = T.apply(centre / 1000.0)
            if np.dot(rotation.apply(normal), c_cam / np.linalg.norm(c_cam)) > -0.35:
                continue
            px = camera.project(T.apply(corners / 1000.0))
            if np.any(px < 0) or np.any(px >= [camera.width_px - 1, camera.height_px - 1]):
                continue
            dets.append(TagDetection(tag_id, px + rng.normal(0.0, noise_px, px.shape)))
        frames.append((T, dets))
    return frames


def corner_rms_mm(a: CapModel, b: CapModel) -> float:
    d = a.corners_mm - b.corners_mm
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))


def rigid_rms_mm(a: CapModel, truth: CapModel) -> float:
    """RMS corner distance after the rigid alignment of ``a`` onto the truth."""
    aligned = align_model(a.corners_mm, truth.corners_mm).apply(a.corners_mm.reshape(-1, 3))
    d = aligned - truth.corners_mm.reshape(-1, 3)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))


def radially_biased(frames: list[tuple[Transform, list[TagDetection]]], radial_px: float) -> list[list[TagDetection]]:
    """Every corner moved ``radial_px`` along its tag's centre -> corner direction in the image
    (negative = inward), the offset ``metrics.corner_errors_px`` measures: not the builder's own
    edge-offset model (on a foreshortened tag the two differ), so the test cannot pass by
    construction."""
    out = []
    for _, dets in frames:
        biased = []
        for d in dets:
            out_dir = d.corners_px - d.corners_px.mean(axis=0)
            out_dir /= np.linalg.norm(out_dir, axis=1, keepdims=True)
            biased.append(TagDetection(d.tag_id, d.corners_px + radial_px * out_dir))
        out.append(biased)
    return out


@pytest.fixture(scope="module")
def built():
    truth = perturbed_model(seed=1)
    frames = observe(truth, count=40, seed=2)
    result = build_model([dets for _, dets in frames], CAMERA)
    return truth, frames, result


def test_recovers_the_perturbed_cap(built) -> None:
    truth, _, result = built
    nominal = nominal_model()
    assert corner_rms_mm(truth, nominal) == pytest.approx(0.55, abs=0.15)  # the test is not trivial
    assert corner_rms_mm(result.model, truth) < 0.1
    assert result.frames_used == 40 and result.converged and result.trusted, result.problems
    # Unbiased corners: the fitted edge offset is (near) zero, so the printed side sets the size.
    assert abs(result.edge_offset_images_px) < 0.05 and result.size_source == "tag side"
    assert "from the tag side" in result.table()
    # A measured size may differ from nominal by what hand assembly does: 3 sigma of the replay
    # check's distance (0.30 % each for 1 mm plates on this cap).
    assert assembly_size_sigma(nominal, BuildConfig()) == pytest.approx(0.003, abs=0.0003)
    assert depth_change_limit(result, BuildConfig()) == pytest.approx(3 * assembly_size_sigma(nominal, BuildConfig()))
    # Reprojection rms matches the injected noise (0.15 px per axis = 0.21 px per corner).
    assert result.rms_px == pytest.approx(0.15 * np.sqrt(2.0), rel=0.2)
    # The reported deviations are the true ones.
    r_nom, c_nom = tag_frames(nominal.corners_mm)
    r_true, c_true = tag_frames(truth.corners_mm)
    true_turn_deg = -np.degrees((r_nom.inv() * r_true).as_rotvec()[:, 2])
    got_turn = np.array([d.about_normal_deg for d in result.deviations])
    np.testing.assert_allclose(got_turn, true_turn_deg, atol=0.15)
    got_offset = np.array([d.offset_mm for d in result.deviations])
    np.testing.assert_allclose(got_offset, c_true - c_nom, atol=0.15)
    assert [d.tag_id for d in result.deviations] == list(nominal.ids)
    assert all(d.frames >= 3 for d in result.deviations)
    # The stated uncertainties are honest: the actual corner errors are about that size.
    errors = np.sqrt(np.mean(np.sum((result.model.corners_mm - truth.corners_mm) ** 2, axis=-1), axis=1))
    sigmas = np.array([d.corner_sigma_mm for d in result.deviations])
    assert 0.4 < float(np.sqrt(np.mean((errors / sigmas) ** 2))) < 2.0
    assert all(10.0 < d.view_spread_deg < 180.0 for d in result.deviations)
    assert all(0.0 <= d.view_angle_min_deg <= d.view_angle_max_deg < 90.0 for d in result.deviations)
    # Every tag stays a rigid 32 mm square.
    sides = np.linalg.norm(np.roll(result.model.corners_mm, -1, axis=1) - result.model.corners_mm, axis=-1)
    np.testing.assert_allclose(sides, 32.0, atol=1e-6)
    assert "reprojection rms" in result.table()
    assert result.to_dict()["tags"][11]["id"] == 11


def test_built_model_gives_better_poses_than_nominal(built) -> None:
    truth, _, result = built
    test_frames = observe(truth, count=30, seed=7)
    errors = {}
    for name, model in (("nominal", nominal_model()), ("built", result.model)):
        rot_deg, trans_mm = [], []
        for T_true, dets in test_frames:
            pose = estimate_cap_pose(dets, model, CAMERA).pose
            assert pose is not None
            delta = T_true.inv() * pose.T_cam_cap
            rot_deg.append(np.degrees(delta.rotation.magnitude()))
            trans_mm.append(1000.0 * np.linalg.norm(delta.translation_m))
        errors[name] = (float(np.sqrt(np.mean(np.square(rot_deg)))),
                        float(np.sqrt(np.mean(np.square(trans_mm)))))
    assert errors["built"][0] < 0.5 * errors["nominal"][0], errors
    assert errors["built"][1] < 0.5 * errors["nominal"][1], errors


def test_result_is_a_normal_model_file(built, tmp_path) -> None:
    _, _, result = built
    path = tmp_path / "cap_asbuilt.yaml"
    result.model.save(path)
    loaded = load_model(path)
    assert loaded.ids == nominal_model().ids
    np.testing.assert_allclose(loaded.corners_mm, result.model.corners_mm, atol=1e-9)


def test_robust_to_a_wrong_tag(built) -> None:
    truth, frames, _ = built
    dets_per_frame = [list(dets) for _, dets in frames]
    # One frame where tag 11's corners are 8 px off (a bad detection).
    dets_per_frame[5] = [TagDetection(d.tag_id, d.corners_px + (8.0 if d.tag_id == 11 else 0.0))
                         for d in dets_per_frame[5]]
    result = build_model(dets_per_frame, CAMERA)
    assert corner_rms_mm(result.model, truth) < 0.1
    # The bad observation is left out (by the start pose's outlier rejection or the adjustment's).
    clean = build_model([dets for _, dets in frames], CAMERA)
    assert result.observations + result.observations_dropped < clean.observations


def test_refuses_when_a_tag_is_not_covered() -> None:
    truth = perturbed_model(seed=3)
    frames = [dets for _, dets in observe(truth, count=20, seed=4)]
    # Tag 0 only ever seen in frames with too few other tags.
    no_zero = [[d for d in dets if d.tag_id != 0] for dets in frames]
    no_zero[0] = [d for d in frames[0] if d.tag_id in (0, 1, 2)]
    with pytest.raises(CoverageError, match=r"tag\(s\) 0 \(0\)"):
        build_model(no_zero, CAMERA)
    # allow_partial: built, with tag 0 resting on its prior and the reason listed.
    partial = build_model(no_zero, CAMERA, allow_partial=True)
    assert not partial.trusted
    assert any("tag(s) 0 (0)" in p for p in partial.problems)
    assert partial.deviations[0].problem.startswith("seen in 0 frame(s)")
    assert partial.deviations[0].corner_sigma_mm > 0.25
    with pytest.raises(CoverageError, match="frame"):
        build_model(frames[:1], CAMERA)
    assert issubclass(CoverageError, ModelError)
    with pytest.raises(ConfigError):
        BuildConfig(min_tags_per_frame=1)
    with pytest.raises(ConfigError):
        build_model(frames, [CAMERA])


def test_cli_builds_from_a_bag_of_rendered_frames(tmp_path, capsys) -> None:
    """End to end: synth renders the perturbed cap (held in the hand: no head) through the realistic
    image chain (lens PSF in linear light, sensor noise, sRGB tone curve: today's corners come out
    biased inward), frames go into a real MCAP bag with CameraInfo, ``ficap model build`` detects,
    adjusts and replays with both models."""
    import json

    from ficap_ros.cli.main import main
    from ficap_ros.io import messages
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.io.messages import ROSBAGS
    from ficap_ros.tools.synth import REALISTIC, RenderConfig, render

    camera = CameraModel.pinhole(960, 720, hfov_deg=50.0)
    truth = perturbed_model(seed=11)
    rng = np.random.default_rng(12)
    bag = tmp_path / "cap_views"
    with BagWriter(bag) as writer:
        writer.add_topic("/cam/image_raw", "sensor_msgs/msg/Image")
        writer.add_topic("/cam/camera_info", "sensor_msgs/msg/CameraInfo")
        for k in range(24):
            yaw, pitch, roll = rng.uniform([-50.0, -40.0, -20.0], [50.0, 40.0, 20.0])
            T = Transform(CAM_FROM_FORWARD * rotation_from_ypr_deg(yaw, pitch, roll),
                          [rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), rng.uniform(0.38, 0.48)])
            frame = render(truth, camera, T, RenderConfig(head=False, **REALISTIC), seed=k)
            stamp = 1_000_000_000 + k * 100_000_000
            head = messages.header(ROSBAGS, stamp, "cam")
            writer.write("/cam/camera_info", stamp, messages.camera_info(ROSBAGS, head, camera))
            writer.write("/cam/image_raw", stamp, messages.image(ROSBAGS, head, frame.image, "mono8"))
    out = tmp_path / "cap_asbuilt.yaml"
    report = tmp_path / "report.json"
    plot = tmp_path / "deviations.png"
    assert main(["model", "build", str(bag), "--out", str(out), "--report", str(report),
                 "--plot", str(plot), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "reprojection rms" in printed and str(out) in printed
    assert "replay check" in printed and "nominal" in printed and "built" in printed
    built_model = load_model(out)
    print(f"rendered: built {rigid_rms_mm(built_model, truth):.3f} mm rigid rms from the truth, "
          f"edge offset {json.loads(report.read_text())['edge_offset_px']:+.3f} px")
    assert rigid_rms_mm(built_model, truth) < 0.1 < 0.2 < corner_rms_mm(nominal_model(), truth)
    data = json.loads(report.read_text())
    assert len(data["tags"]) == 23 and data["rms_px"] < 1.0 and data["trusted"]
    assert data["replay_check"]["problems"] == [] and abs(data["replay_check"]["depth_change"]) < 1e-3
    assert plot.read_bytes().startswith(b"\x89PNG")
    # Too strict a coverage demand: one clear line, non-zero exit, no file written.
    refused = tmp_path / "refused.yaml"
    assert main(["model", "build", str(bag), "--out", str(refused), "--min-frames-per-tag", "30",
                 "--quiet"]) == 1
    assert "seen in too few frames" in capsys.readouterr().err
    assert not refused.exists()


def test_distorted_camera_and_per_frame_cameras() -> None:
    """Corners in a distorted image are undistorted with each frame's own intrinsics."""
    truth = perturbed_model(seed=5)
    k = CAMERA.K
    wide = CameraModel(1280, 960, k, [-0.25, 0.08, 0.0005, -0.0004, 0.0], "plumb_bob")
    fisheye = CameraModel(1280, 960, k, [0.05, -0.01, 0.002, 0.0], "equidistant")
    frames = observe(truth, 20, seed=6, camera=wide) + observe(truth, 20, seed=8, camera=fisheye)
    cameras = [wide] * 20 + [fisheye] * 20
    result = build_model([dets for _, dets in frames], cameras)
    assert corner_rms_mm(result.model, truth) < 0.2
    assert result.rms_px == pytest.approx(0.15 * np.sqrt(2.0), rel=0.25)
    # Camera poses are reported in the built cap frame, metres.
    for (T_true, _), T in zip(frames, result.T_cam_cap):
        assert 1000.0 * np.linalg.norm(T.translation_m - T_true.translation_m) < 1.0


def test_edge_shift_moves_each_border_line_by_the_offset() -> None:
    """The builder's corner-bias model: both lines through a corner move by the offset."""
    square = np.array([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]])
    np.testing.assert_allclose(edge_shift_px(square, 0.5), square + 0.5 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]))
    np.testing.assert_allclose(edge_shift_px(square[::-1], -0.5), (square + 0.5 * np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]))[::-1])
    # A skewed quad: every shifted edge line is parallel to the original, 0.3 px out.
    quad = np.array([[0.0, 0.0], [30.0, 4.0], [26.0, 19.0], [3.0, 15.0]])
    shifted = edge_shift_px(quad, 0.3)
    for k in range(4):
        a, b = quad[k], quad[(k + 1) % 4]
        n = np.array([b[1] - a[1], a[0] - b[0]]) / np.linalg.norm(b - a)
        n *= np.sign(np.dot((a + b) / 2 - quad.mean(axis=0), n))
        for corner in (shifted[k], shifted[(k + 1) % 4]):
            assert np.dot(corner - a, n) == pytest.approx(0.3, abs=1e-9)


@pytest.mark.parametrize("radial_px", [-0.4, 0.3])
def test_biased_corners_do_not_change_the_scale(built, radial_px) -> None:
    """Corners biased inward 0.4 px / outward 0.3 px plus 0.15 px noise: the built corners are
    within 0.1 mm rms of the truth after a rigid alignment, where a builder whose only scale is
    the printed tag side grows (shrinks) the cap and is several times farther off."""
    truth, frames, _ = built
    biased = radially_biased(frames, radial_px)
    result = build_model(biased, CAMERA)
    assert rigid_rms_mm(result.model, truth) < 0.1
    assert result.converged and result.trusted, result.problems
    # The nuisance is reported with the bias's sign; for a head-on square a radial offset r is an
    # edge offset r / sqrt(2), foreshortened tags make it somewhat smaller.
    assert result.size_source == "nominal layout"
    assert depth_change_limit(result, BuildConfig()) == BuildConfig().max_depth_change
    assert np.sign(result.edge_offset_px) == np.sign(radial_px)
    assert 0.4 < result.edge_offset_px / (radial_px / np.sqrt(2.0)) < 1.1
    assert result.size_ratio == pytest.approx(1.0, abs=1e-4)
    assert "edge offset of the detected corners" in result.table()
    side_only = build_model(biased, CAMERA, config=BuildConfig(fit_edge_offset=False, anchor_size=False,
                                                               size="fixed"))
    assert rigid_rms_mm(side_only.model, truth) > 2.0 * rigid_rms_mm(result.model, truth) + 0.1
    assert np.sign(side_only.size_ratio - 1.0) == -np.sign(radial_px)  # inward bias grows the cap
    # The replay check sees the side-only model move the cap along the line of sight; ours not.
    check = replay_check(biased, CAMERA, side_only.model)
    ours = replay_check(biased, CAMERA, result.model)
    assert np.sign(check.depth_change) == -np.sign(radial_px)
    # Ours moves it a tenth as far at most (0.02 % of the distance with the pose's per-tag weights,
    # which differ between the two models' residuals; the side-only model 0.5-0.6 %).
    assert abs(check.depth_change) > 0.002 and abs(ours.depth_change) < 0.1 * abs(check.depth_change)
    assert ours.ok and not check.warnings


def test_replay_check_compares_with_the_nominal(built) -> None:
    truth, frames, result = built
    dets = [d for _, d in frames]
    check = replay_check(dets, CAMERA, result.model)
    assert check.ok and check.frames == 40
    assert check.rms_px_built < check.rms_px_nominal
    assert abs(check.depth_change) < 5e-4
    assert "nominal" in check.table() and check.to_dict()["problems"] == []
    # A cap grown by 1 % around its centre would place the cap ~5 mm too far: refused.
    c = result.model.corners_mm
    grown = CapModel(result.model.ids, c.mean(axis=(0, 1)) + 1.01 * (c - c.mean(axis=(0, 1))))
    assert size_ratio(grown.corners_mm, c) == pytest.approx(1.01)
    bad = replay_check(dets, CAMERA, grown)
    assert bad.depth_change == pytest.approx(0.01, abs=0.002) and bad.translation_change_mm > 3.0
    assert bad.problems
    # A model with every plate moved ~1.5 mm more fits the frames worse than the nominal: a warning.
    moved = c + np.random.default_rng(3).normal(0.0, 1.5 / np.sqrt(3.0), (len(c), 1, 3))
    worse = replay_check(dets, CAMERA, CapModel(result.model.ids, moved))
    assert worse.warnings and "fits the recording worse" in worse.warnings[0]
    assert worse.rms_px_built > worse.rms_px_nominal


def test_unconverged_build_exits_non_zero(tmp_path, capsys) -> None:
    """A solver that runs out of budget is not trusted: exit 1 and no file, unless --allow-partial."""
    from ficap_ros.cli.main import main
    from ficap_ros.io import messages
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.io.messages import ROSBAGS
    from ficap_ros.tools.synth import RenderConfig, render

    camera = CameraModel.pinhole(640, 480, hfov_deg=50.0)
    truth = perturbed_model(seed=21)
    rng = np.random.default_rng(22)
    bag = tmp_path / "few_views"
    with BagWriter(bag) as writer:
        writer.add_topic("/cam/image_raw", "sensor_msgs/msg/Image")
        writer.add_topic("/cam/camera_info", "sensor_msgs/msg/CameraInfo")
        for k in range(8):
            yaw, pitch = rng.uniform([-40.0, -30.0], [40.0, 30.0])
            T = Transform(CAM_FROM_FORWARD * rotation_from_ypr_deg(yaw, pitch, 0.0), [0.0, 0.0, 0.42])
            frame = render(truth, camera, T, RenderConfig(head=False, supersample=2), seed=k)
            stamp = 1_000_000_000 + k * 100_000_000
            head = messages.header(ROSBAGS, stamp, "cam")
            writer.write("/cam/camera_info", stamp, messages.camera_info(ROSBAGS, head, camera))
            writer.write("/cam/image_raw", stamp, messages.image(ROSBAGS, head, frame.image, "mono8"))
    out = tmp_path / "cap.yaml"
    args = ["model", "build", str(bag), "--out", str(out), "--max-nfev", "2", "--min-frames-per-tag", "1",
            "--quiet"]
    assert main(args) == 1
    captured = capsys.readouterr()
    assert "NOT CONVERGED" in captured.out and "did not converge" not in captured.out
    assert "without converging" in captured.err and "not writing" in captured.err
    assert not out.exists()
    assert main(args + ["--allow-partial"]) == 0
    captured = capsys.readouterr()
    assert "warning: the solver stopped at its budget" in captured.err
    assert out.exists() and "partial" in captured.out


def test_cli_builds_from_a_synth_drive(tmp_path, capsys) -> None:
    """``ficap synth --model`` renders a drive of a hand-built cap on a head (occluder, car interior,
    the realistic image chain: PSF in linear light, sensor noise, sRGB tone curve, JPEG);
    ``ficap model build`` on that bag is within 0.1 mm of the truth and its replay check passes."""
    import json

    from ficap_ros.cli.main import main

    truth = perturbed_model(seed=11)
    truth_path = tmp_path / "truth.yaml"
    truth.save(truth_path)
    bag = tmp_path / "drive"
    # One frame a second of a 30 s drive: glances at mirrors, cluster and screen.
    assert main(["synth", "--out", str(bag), "--model", str(truth_path), "--resolution", "540p",
                 "--frames", "30", "--fps", "1", "--seed", "3", "--quiet"]) == 0
    capsys.readouterr()
    out = tmp_path / "cap_asbuilt.yaml"
    report = tmp_path / "report.json"
    assert main(["model", "build", str(bag), "--out", str(out), "--report", str(report), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "replay check" in printed
    built_model = load_model(out)
    assert rigid_rms_mm(built_model, truth) < 0.1 < 0.3 < rigid_rms_mm(nominal_model(), truth)
    data = json.loads(report.read_text())
    assert data["trusted"] and data["frames_used"] >= 25
    check = data["replay_check"]
    assert check["rms_px_built"] < check["rms_px_nominal"] and not check["problems"]
    assert abs(data["edge_offset_px"]) < 0.6
    print(f"synth drive: built {rigid_rms_mm(built_model, truth):.3f} mm rigid rms from the truth, "
          f"edge offset {data['edge_offset_px']:+.3f} px")


def test_cli_bad_numbers_are_argparse_errors_naming_the_flag(tmp_path, capsys) -> None:  # noqa: ANN001
    """Exit 2 with the flag named (they were exit 1 naming BuildConfig's fields, and --fps nan
    was taken), before any input is read."""
    from ficap_ros.cli.main import main

    for flag, value in (("--every", "0"), ("--max-frames", "1"), ("--min-tags", "0"),
                        ("--min-frames-per-tag", "-1"), ("--max-nfev", "0"),
                        ("--assembly-sigma-mm", "nan"), ("--assembly-sigma-mm", "-1"), ("--fps", "nan")):
        with pytest.raises(SystemExit) as exc:
            main(["model", "build", str(tmp_path / "none.mcap"), "--out", str(tmp_path / "m.yaml"),
                  flag, value])
        assert exc.value.code == 2, (flag, value)
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert f"argument {flag}:" in err, err

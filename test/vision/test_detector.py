"""The tag detector: corner conventions, recall and false positives on real photos, inputs and
settings, and the search on frames that must be searched (decimation by image size, a second reading
of the quads ArUco rejects, the search completed at the pose of the tags it found)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from tag_images import DICT, oblique_tag, random_tag

from ficap_ros.cli.main import main as cli_main
from ficap_ros.errors import ConfigError, ImageError
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.tag36h11 import tag_cells
from ficap_ros.tools.synth import (
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.detector import (
    DetectorConfig,
    TagDetector,
    _auto_decimate,
    as_gray,
)
from ficap_ros.vision.pipeline import FrameProcessor


def test_apriltag_backend_corners_on_rendered_tag():
    """The AprilTag convention conversion (order p1 p0 p3 p2, -0.5 px) lands on the true corners."""
    det = TagDetector(DetectorConfig(backend="apriltag", corner_refine="none"))
    rng = np.random.default_rng(3)
    errs = []
    for _ in range(6):
        img, truth = random_tag(rng, 60.0)
        (found,) = det.detect(img)
        errs.append(found.corners_px - truth)
    rms = float(np.sqrt(np.mean(np.sum(np.concatenate(errs) ** 2, axis=1))))
    assert rms <= 0.2, rms  # a wrong order or a missed half-pixel shift gives >= 0.7 px


def test_corner_order_upright_marker_c0_top_left():
    canvas = np.full((200, 200), 255, np.uint8)
    canvas[50:130, 60:140] = cv2.aruco.generateImageMarker(DICT, 5, 80, borderBits=1)
    expected = np.array([[59.5, 49.5], [139.5, 49.5], [139.5, 129.5], [59.5, 129.5]])
    # AprilTag 3's refine_edges lands up to ~0.2 px off on this perfectly sharp edge.
    for cfg, tol in ((DetectorConfig(), 0.02), (DetectorConfig(corner_refine="apriltag"), 0.02),
                     (DetectorConfig(backend="apriltag", corner_refine="none"), 0.25)):
        (d,) = TagDetector(cfg).detect(canvas)
        assert d.tag_id == 5
        np.testing.assert_allclose(d.corners_px, expected, atol=tol)


@pytest.mark.parametrize(
    "config,min_recall",
    # test/data holds every 6th photo of the set (12 photos, 37 tags). On them ArUco finds 33,
    # AprilTag 3 35; the bars allow one more miss each (the whole set: docs/detection.md).
    [(DetectorConfig(), 32 / 37 - 1e-9),
     (DetectorConfig(backend="apriltag", corner_refine="none"), 34 / 37 - 1e-9)],
    ids=["opencv", "apriltag"],
)
def test_recall_and_false_positives_on_real_photos(mapping_photos, config, min_recall):
    root, truth = mapping_photos
    det = TagDetector(config)
    found = false_pos = 0
    for name, ids in truth.items():
        got = [d.tag_id for d in det.detect(cv2.imread(str(root / name), cv2.IMREAD_GRAYSCALE))]
        found += len(set(got) & ids)
        false_pos += len(set(got) - ids) + len(got) - len(set(got))
    total = sum(len(v) for v in truth.values())
    assert found / total >= min_recall, f"recall {found}/{total}"
    assert false_pos == 0


def _swarmathon(real_apriltag_dir: Path):
    root = real_apriltag_dir / "apriltag_swarmathon"
    for txt in sorted(root.glob("*.txt")):
        if txt.name == "SOURCE_README.md":
            continue
        refs = []
        for line in txt.read_text().splitlines():
            nums = line.replace("(", " ").replace(")", " ").replace(",", " ").split()
            p = np.array(list(map(float, nums[1:]))).reshape(4, 2)
            refs.append(p[[1, 0, 3, 2]] - 0.5)  # AprilTag order/pixels -> OpenCV's
        yield cv2.imread(str(txt.with_suffix(".jpg")), cv2.IMREAD_GRAYSCALE), refs


@pytest.mark.parametrize(
    "backend,refine,centre_tol_px",
    [("apriltag", "none", 0.25), ("opencv", "edge", 0.25), ("opencv", "apriltag", 0.05)],
)
def test_corners_agree_with_apriltag_reference(real_apriltag_dir, backend, refine, centre_tol_px):
    """The reference is AprilTag 3 without edge refinement on small blurred JPEG tags; ours and
    AprilTag's own refined corners scatter ~0.3 px per corner around it, so compare tag centres
    and the mean offset (a convention error would shift every corner by >= 0.5 px)."""
    det = TagDetector(DetectorConfig(backend=backend, corner_refine=refine))
    centre_err, offsets = [], []
    for img, refs in _swarmathon(real_apriltag_dir):
        dets = det.detect(img)
        for ref in refs:
            best = min(dets, key=lambda d: np.abs(d.corners_px - ref).max())
            if np.abs(best.corners_px - ref).max() < 2.0:
                centre_err.append(np.linalg.norm(best.corners_px.mean(0) - ref.mean(0)))
                offsets.append(best.corners_px - ref)
    assert len(centre_err) >= 20
    assert np.median(centre_err) <= centre_tol_px
    assert np.all(np.abs(np.concatenate(offsets).mean(axis=0)) <= centre_tol_px)


def test_roi_matches_full_frame(real_apriltag_dir):
    img = cv2.imread(str(real_apriltag_dir / "apriltags_jl" / "tagtest.jpg"), cv2.IMREAD_GRAYSCALE)
    det = TagDetector()
    full = {d.tag_id: d.corners_px for d in det.detect(img)}
    c = full[6]
    x0, y0 = (c.min(axis=0) - 30).astype(int)
    part = det.detect(img, roi=(x0, y0, 80, 80))
    assert [d.tag_id for d in part] == [6]
    np.testing.assert_allclose(part[0].corners_px, c, atol=0.05)


@pytest.mark.parametrize(
    "bad", [None, np.zeros((0, 0), np.uint8), np.zeros((50, 50), np.float32), np.zeros((50, 50, 2), np.uint8),
            np.zeros((4, 4), np.uint8)]
)
def test_bad_images_raise_image_error(bad):
    with pytest.raises(ImageError):
        TagDetector().detect(bad)
    with pytest.raises(ImageError):
        as_gray(bad)


def test_bad_config_and_roi():
    with pytest.raises(ConfigError):
        DetectorConfig(backend="nope")
    with pytest.raises(ConfigError):
        DetectorConfig(corner_refine="magic")
    with pytest.raises(ImageError):
        TagDetector().detect(np.zeros((50, 50), np.uint8), roi=(100, 100, 10, 10))


@pytest.mark.parametrize("settings", [dict(corner_refine="subpix"), dict(corner_refine="apriltag"),
                                      dict(corner_refine="none"), dict(edge_fit=False)])
def test_photometric_without_the_cell_edge_fit_is_refused(settings, real_apriltag_dir, capsys):
    # The photometric fit runs only after the cell-edge fit (edge refine): asked for without it,
    # it would silently do nothing (ficap detect --refine subpix --photometric, the node's
    # detector.corner_refine: subpix with detector.photometric: true).
    with pytest.raises(ConfigError, match="photometric"):
        DetectorConfig(edge_photometric=True, **settings)
    DetectorConfig(**settings)  # fine without it
    if "corner_refine" in settings:
        path = str(real_apriltag_dir / "apriltags_jl" / "tagtest.jpg")
        assert cli_main(["detect", "--refine", settings["corner_refine"], "--photometric", path]) == 1
        assert "photometric" in capsys.readouterr().err


def test_second_reading_finds_tags_aruco_rejects() -> None:
    """Small, blurred, oblique tags: the rejected quads read again at refined corners add tags,
    with sub-pixel corners and never a wrong id."""
    rng = np.random.default_rng(2026)
    plain = TagDetector(DetectorConfig(decode_rejected=False))
    ours = TagDetector(DetectorConfig())
    found_plain = found_ours = 0
    err_both, err_second = [], []  # corner errors, px: tags ArUco read, tags only read again
    for _ in range(60):
        tag_id = int(rng.integers(0, 587))
        img, truth = oblique_tag(tag_id, rng.uniform(14, 26), rng.uniform(0, 360), rng.uniform(0.0, 0.45),
                                rng.uniform(0.6, 1.4), rng)
        a = [d for d in plain.detect(img) if d.tag_id == tag_id]
        b = ours.detect(img)
        assert all(d.tag_id == tag_id for d in b), [d.tag_id for d in b]
        found_plain += bool(a)
        found_ours += bool(b)
        for d in b:
            (err_both if a else err_second).append(np.linalg.norm(d.corners_px - truth, axis=1).mean())
    assert found_ours >= found_plain + 3, (found_ours, found_plain)
    # Sub-pixel corners (the same edge fit as ArUco's tags get, at full size), on the hardest
    # tags of the set: docs/detection.md has 0.2-0.4 px for 20-40 px tags under sigma 1.5 blur.
    assert np.median(err_second) < 0.5 and max(err_second) < 1.0, err_second
    assert np.median(err_both) < 0.5


def test_auto_decimation_by_image_size() -> None:
    assert _auto_decimate((1080, 1920), 960) == 2
    assert _auto_decimate((2160, 3840), 960) == 4
    assert _auto_decimate((612, 816), 960) == 1 and _auto_decimate((720, 1280), 960) == 1
    with pytest.raises(ConfigError):
        DetectorConfig(search_decimate=5)
    with pytest.raises(ConfigError):
        DetectorConfig(decode_max_bit_errors=4)


@pytest.fixture(scope="module")
def frames_1080p():
    scene = default_scene("1080p")
    model = nominal_model()
    drive = naturalistic_drive(700, 30.0, 0, scene)[30::220]  # 4 poses, a glance among them
    return scene.camera, [render(model, scene.camera, d.T_cam_cap, RenderConfig(), seed=d.index)
                          for d in drive]


def test_searched_1080p_frames_find_at_least_apriltag3s_tags(frames_1080p) -> None:
    """Every frame searched (no earlier frame): the decimated search completed at its pose finds
    no fewer tags than AprilTag 3 decimate 1, and only tags that face the camera."""
    camera, frames = frames_1080p
    model = nominal_model()
    at3 = TagDetector(DetectorConfig(backend="apriltag", corner_refine="apriltag"))
    for f in frames:
        proc = FrameProcessor(model)  # a fresh processor: the frame is searched
        gray = f.image if f.image.ndim == 2 else cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY)
        r = proc.process(gray, camera, 0)
        ours = {d.tag_id for d in r.detections}
        theirs = {d.tag_id for d in at3.detect(gray) if d.tag_id in model}
        assert r.search == "image" and proc.tracker.full_searches == 1
        assert len(ours) >= len(theirs), (sorted(ours), sorted(theirs))
        assert ours <= set(f.corners_px), sorted(ours - set(f.corners_px))
        assert len(ours & set(f.visible_ids(0.999))) >= 0.95 * len(f.visible_ids(0.999))
        assert r.pose is not None and r.pose.tags_used >= 4


def test_decimated_search_resamples_cells_coarser_and_keeps_its_tags(frames_1080p) -> None:
    """A decimated search reads candidates at ``decimated_pixel_per_cell`` (a full-size one at
    ``perspective_remove_pixel_per_cell``) and finds every tag the finer reading finds, at the
    same search corners."""
    _, frames = frames_1080p
    coarse, fine = TagDetector(), TagDetector(DetectorConfig(decimated_pixel_per_cell=8))
    for f in frames:
        gray = f.image if f.image.ndim == 2 else cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY)
        got = {int(i): c for i, c in zip(*coarse._search_full_size(gray, None, 2)[:2])}
        want = {int(i): c for i, c in zip(*fine._search_full_size(gray, None, 2)[:2])}
        assert coarse._aruco.getDetectorParameters().perspectiveRemovePixelPerCell == 4
        assert set(want) <= set(got) and len(want) >= 10
        for i in want:
            np.testing.assert_array_equal(got[i], want[i])
    coarse._search_full_size(frames[0].image if frames[0].image.ndim == 2 else
                             cv2.cvtColor(frames[0].image, cv2.COLOR_BGR2GRAY), None, 1)
    assert coarse._aruco.getDetectorParameters().perspectiveRemovePixelPerCell == 8
    with pytest.raises(ConfigError):
        DetectorConfig(decimated_pixel_per_cell=-1)


def test_searched_frames_skip_the_second_reading_without_losing_tags(frames_1080p, monkeypatch) -> None:
    """A decimated search that found enough model tags skips the second reading of rejected
    quads; the completion at their pose reads every tag the second reading would have found."""
    camera, frames = frames_1080p
    model = nominal_model()
    det = TagDetector()
    calls = []
    second_chance = TagDetector._second_chance
    monkeypatch.setattr(TagDetector, "_second_chance", lambda self, *a: calls.append(1) or second_chance(self, *a))
    for f in frames:
        gray = f.image if f.image.ndim == 2 else cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY)
        plain = {d.tag_id for d in det.detect(gray) if d.tag_id in model}
        calls.clear()
        lean = {d.tag_id for d in det.detect(gray, wanted_ids=model, enough_tags=2) if d.tag_id in model}
        assert not calls and lean <= plain and len(lean) >= 2
        calls.clear()
        r = FrameProcessor(model).process(gray, camera, 0)  # searched: no earlier frame
        assert not calls, "the tracker's search read the rejected quads again"
        assert {d.tag_id for d in r.detections} >= plain, sorted(plain - {d.tag_id for d in r.detections})
    # A full-resolution search always reads them again (it finds small tags the completion skips).
    small = cv2.resize(gray, (960, 540), interpolation=cv2.INTER_AREA)
    calls.clear()
    det.detect(small, wanted_ids=model, enough_tags=2)
    assert calls


def test_search_corners_match_a_full_resolution_search(frames_1080p) -> None:
    """Decimation only changes where the refinement starts: a tag gets the same corners."""
    camera, frames = frames_1080p
    full = TagDetector(DetectorConfig(search_decimate=1, decode_rejected=False))
    dec = TagDetector(DetectorConfig())
    f = frames[0]
    gray = f.image if f.image.ndim == 2 else cv2.cvtColor(f.image, cv2.COLOR_BGR2GRAY)
    a = {d.tag_id: d.corners_px for d in full.detect(gray)}
    b = {d.tag_id: d.corners_px for d in dec.detect(gray)}
    common = set(a) & set(b)
    assert len(common) >= 10
    diff = max(np.abs(a[i] - b[i]).max() for i in common)
    assert diff < 0.05, diff
    assert tag_cells(0).shape == (8, 8)


def test_detecting_turns_opencv_ipp_off_in_the_detecting_thread() -> None:
    """OpenCV's IPP switch is per thread: a detector built in one thread and used in another (the
    node's worker) turns it off where it detects; the tags are the same."""
    import threading

    rng = np.random.default_rng(3)
    img, truth = oblique_tag(42, 60.0, 10.0, 0.1, 0.8, rng)
    det = TagDetector()
    here = det.detect(img)
    seen: list[tuple[bool, list]] = []

    def work() -> None:
        cv2.ipp.setUseIPP(True)
        found = det.detect(img)
        seen.append((cv2.ipp.useIPP(), found))

    t = threading.Thread(target=work)
    t.start()
    t.join()
    after, there = seen[0]
    assert not after
    assert [d.tag_id for d in there] == [d.tag_id for d in here] == [42]
    np.testing.assert_array_equal(there[0].corners_px, here[0].corners_px)


def test_search_keeps_its_recall_on_the_real_mapping_photos(mapping_photos) -> None:
    """The default search on test/data's mapping photos (every 6th of the hand-labelled set, 37
    tags): every tag AprilTag 3 decimate 1 finds and more, no false positive. The second reading
    of rejected quads is what lifts it (without it: 33 of 37)."""
    root, truth = mapping_photos
    images = {name: cv2.imread(str(root / name), cv2.IMREAD_GRAYSCALE) for name in truth}
    counts = {}
    for name, cfg in (("ours", DetectorConfig()),
                      ("apriltag", DetectorConfig(backend="apriltag", corner_refine="none"))):
        det = TagDetector(cfg)
        got = {image_name: [d.tag_id for d in det.detect(images[image_name])] for image_name in truth}
        counts[name] = (sum(len(set(got[n]) & ids) for n, ids in truth.items()),
                        sum(len(set(got[n]) - ids) + len(got[n]) - len(set(got[n])) for n, ids in truth.items()))
    assert sum(len(v) for v in truth.values()) == 37
    assert counts["ours"][1] == 0 and counts["apriltag"][1] == 0
    # Measured: ours 37, AprilTag 3 35; one miss of slack for a library update.
    assert counts["ours"][0] >= max(counts["apriltag"][0], 36), counts


def test_the_apriltag_backend_without_its_package_is_a_config_error(monkeypatch) -> None:
    """pupil-apriltags is optional: without it the apriltag backend says what to install in one
    line (a FicapError: the node and the CLI print it), not an ImportError traceback."""
    import sys

    from ficap_ros.vision.detector import (
        DetectorConfig,
        TagDetector,
        _apriltag_detector_class,
    )

    _apriltag_detector_class.cache_clear()
    monkeypatch.setitem(sys.modules, "pupil_apriltags", None)
    try:
        with pytest.raises(ConfigError, match="pip install pupil-apriltags"):
            TagDetector(DetectorConfig(backend="apriltag"))
    finally:
        _apriltag_detector_class.cache_clear()

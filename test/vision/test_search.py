"""The search on frames that must be searched: decimation by image size, a second reading of the
quads ArUco rejects, and the search completed at the pose of the tags it found."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.tag36h11 import decode_tags, tag_cells
from ficap_ros.tools.synth import (
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.detection import DetectorConfig, TagDetector, _auto_decimate
from ficap_ros.vision.pipeline import FrameProcessor

DICT = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)


def _tag_image(tag_id: int, side_px: float, angle_deg: float, tilt: float, blur: float,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A tag (with its white margin) on grey, under a perspective, exact corners (OpenCV order)."""
    w = h = 200
    ss = 8
    marker = cv2.aruco.generateImageMarker(DICT, tag_id, 8 * 16, borderBits=1)
    p = marker.shape[0]
    pad = p // 8
    face = np.full((p + 2 * pad, p + 2 * pad), 255, np.uint8)
    face[pad:pad + p, pad:pad + p] = marker
    src = np.array([[-0.5, -0.5], [p - 0.5, -0.5], [p - 0.5, p - 0.5], [-0.5, p - 0.5]]) + pad
    a = np.radians(angle_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * side_px / 2
    square[:, 0] *= np.where(square[:, 1] < 0, 1 - tilt, 1 + tilt)  # a trapezoid: seen obliquely
    corners = square @ rot.T + np.array([w, h]) / 2 + rng.uniform(-0.5, 0.5, 2)
    hom = cv2.getPerspectiveTransform(src.astype(np.float32), ((corners + 0.5) * ss - 0.5).astype(np.float32))
    hi = cv2.warpPerspective(face, hom, (w * ss, h * ss), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=120)
    img = cv2.resize(hi, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    img = 30 + 190 * img / 255
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    img += rng.normal(0, 2.0, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), corners


def test_decode_tags_reads_every_corner_order_and_returns_opencv_order() -> None:
    rng = np.random.default_rng(5)
    img, truth = _tag_image(17, 60.0, 20.0, 0.1, 0.6, rng)
    for r in range(4):
        ok, ids, errors, ordered = decode_tags(img, np.roll(truth, r, axis=0)[None])
        assert ok[0] and ids[0] == 17 and errors[0] == 0
        np.testing.assert_allclose(ordered[0], truth)  # c0 back at the tag's top-left


def test_decode_tags_rejects_what_is_not_a_tag() -> None:
    """Random quads on noise, on a textured render and on a tag's inner squares read as nothing."""
    rng = np.random.default_rng(11)
    noise = cv2.GaussianBlur(rng.integers(0, 256, (480, 640)).astype(np.uint8), (0, 0), 1.5)
    scene = default_scene("540p")
    frame = render(nominal_model(), scene.camera, naturalistic_drive(2, 30.0, 0, scene)[0].T_cam_cap,
                   RenderConfig(), seed=0).image
    quads = []
    for _ in range(3000):
        centre = rng.uniform(40, 440, 2)
        quads.append(centre + rng.uniform(-30, 30, (4, 2)) + np.array([[-20, -20], [20, -20], [20, 20], [-20, 20]]))
    quads = np.array(quads)
    for image in (noise, cv2.resize(frame, (640, 480)) if frame.ndim == 2 else
                  cv2.cvtColor(cv2.resize(frame, (640, 480)), cv2.COLOR_BGR2GRAY)):
        ok, *_ = decode_tags(image, quads)
        assert not ok.any()
    # The inner 6x6 data square of a real tag is not a tag either (its border is not black).
    img, truth = _tag_image(3, 80.0, 0.0, 0.0, 0.0, rng)
    centre = truth.mean(axis=0)
    ok, *_ = decode_tags(img, (centre + (truth - centre) * 6 / 8)[None])
    assert not ok[0]


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
        img, truth = _tag_image(tag_id, rng.uniform(14, 26), rng.uniform(0, 360), rng.uniform(0.0, 0.45),
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
    img, truth = _tag_image(42, 60.0, 10.0, 0.1, 0.8, rng)
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

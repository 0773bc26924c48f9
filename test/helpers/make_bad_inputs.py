"""Write the bad-input corpus in test/data/bad_inputs/ (small, deterministic; committed).

    .venv/bin/python test/make_bad_inputs.py

Every file is something a user may hand ficap: damaged containers, broken images, wrong
encodings, impossible intrinsics, binary and non-UTF-8 YAML, torn CSV, duplicated and foreign tag
ids. test_bad_inputs.py runs each against every reader and verb that takes it.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from ficap_ros.geometry.camera import CameraModel  # noqa: E402
from ficap_ros.geometry.cap_model import nominal_model  # noqa: E402
from ficap_ros.io import messages  # noqa: E402
from ficap_ros.io.bag_writer import BagWriter  # noqa: E402
from ficap_ros.io.messages import ROSBAGS  # noqa: E402
from ficap_ros.io.sources import CAMERA_INFO_TYPE, COMPRESSED_TYPE, IMAGE_TYPE  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "data" / "bad_inputs"
W, H = 96, 72
T0 = 1_700_000_000_000_000_000
DT = 33_333_333
CAM = CameraModel.pinhole(W, H, f_px=80.0)
DICT = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)


def _tags(ids: list[int]) -> np.ndarray:
    """A grey image with tag36h11 markers of ``ids`` side by side (the same id may repeat)."""
    img = np.full((H, W), 255, np.uint8)
    size = 28
    for k, tag_id in enumerate(ids):
        x = 4 + k * (size + 4)
        img[20:20 + size, x:x + size] = cv2.aruco.generateImageMarker(DICT, tag_id, size,
                                                                     borderBits=1)
    return img


def _noise(i: int) -> np.ndarray:
    return np.random.default_rng(i).integers(0, 256, (H, W), dtype=np.uint8)


def _bag(path: Path, frames: list[dict], storage: str = "mcap", layout: str = "folder") -> None:
    """A bag of ``frames``: each {'image': array | bytes, 'encoding', 'info': CameraModel|msg}."""
    compressed = any(isinstance(f["image"], bytes) for f in frames)
    topic = "/cam/image_raw/compressed" if compressed else "/cam/image_raw"
    with BagWriter(path, storage=storage, layout=layout) as w:
        w.add_topic(topic, COMPRESSED_TYPE if compressed else IMAGE_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i, f in enumerate(frames):
            stamp = T0 + i * DT
            info = f.get("info", CAM)
            head = messages.header(ROSBAGS, stamp, "cam")
            w.write("/cam/camera_info", stamp, messages.camera_info(ROSBAGS, head, info)
                    if isinstance(info, CameraModel) else info(stamp))
            if compressed:
                w.write(topic, stamp, messages.compressed_image(ROSBAGS, head, f["image"]))
            else:
                msg = messages.image(ROSBAGS, head, f["image"], "mono8")
                msg.encoding = f.get("encoding", "mono8")
                w.write(topic, stamp, msg)


def _info_with(k: list[float], p: list[float] | None = None):  # noqa: ANN202
    def make(stamp: int):  # noqa: ANN202
        msg = messages.camera_info(ROSBAGS, messages.header(ROSBAGS, stamp, "cam"), CAM)
        msg.k = np.asarray(k, dtype=np.float64)
        if p is not None:
            msg.p = np.asarray(p, dtype=np.float64)
        return msg
    return make


def main() -> None:
    shutil.rmtree(OUT, ignore_errors=True)
    OUT.mkdir(parents=True)
    rng = np.random.default_rng(2013)
    good_jpeg = cv2.imencode(".jpg", _tags([3, 7]))[1].tobytes()
    good_png = cv2.imencode(".png", _tags([3, 7]))[1].tobytes()

    # Images.
    (OUT / "jpeg_truncated.jpg").write_bytes(good_jpeg[: len(good_jpeg) // 2])
    (OUT / "jpeg_corrupt.jpg").write_bytes(good_jpeg[:300] + bytes(200) + good_jpeg[500:])
    (OUT / "png_truncated.png").write_bytes(good_png[: len(good_png) // 2])
    (OUT / "png_header_only.png").write_bytes(good_png[:33])
    (OUT / "empty.jpg").write_bytes(b"")
    (OUT / "tags_duplicated_ids.png").write_bytes(cv2.imencode(".png", _tags([5, 5]))[1].tobytes())
    (OUT / "tags_foreign_ids.png").write_bytes(cv2.imencode(".png", _tags([300, 586]))[1]
                                               .tobytes())

    # Bags: a good one to damage, then damaged containers and bad contents.
    good = [{"image": _tags([3, 7])} for _ in range(6)] + [{"image": _noise(i)} for i in range(4)]
    _bag(OUT / "good_bag", good)
    mcap = next((OUT / "good_bag").glob("*.mcap")).read_bytes()
    (OUT / "mcap_truncated.mcap").write_bytes(mcap[: len(mcap) * 6 // 10])
    (OUT / "mcap_magic_only.mcap").write_bytes(mcap[:8])
    (OUT / "mcap_garbage.mcap").write_bytes(mcap[:8] + rng.integers(0, 256, 2000, np.uint8)
                                            .tobytes())
    flipped = bytearray(mcap)
    for pos in rng.integers(100, len(mcap) - 100, 40):
        flipped[pos] ^= 0xFF
    (OUT / "mcap_bitflips.mcap").write_bytes(bytes(flipped))
    (OUT / "not_a_bag.mcap").write_bytes(b"this is not an mcap file\n" * 20)
    _bag(OUT / "sqlite_torn", good, storage="sqlite3")
    db = next((OUT / "sqlite_torn").glob("*.db3"))
    db.write_bytes(db.read_bytes()[: db.stat().st_size * 7 // 10])
    _bag(OUT / "sqlite_garbage", good[:2], storage="sqlite3")
    db = next((OUT / "sqlite_garbage").glob("*.db3"))
    db.write_bytes(bytes(100) + db.read_bytes()[100:1500])
    shutil.rmtree(OUT / "good_bag")
    (OUT / "metadata_binary").mkdir()
    (OUT / "metadata_binary" / "metadata.yaml").write_bytes(rng.integers(0, 256, 400, np.uint8)
                                                            .tobytes())
    _bag(OUT / "bag_wrong_encoding.mcap", [{"image": _tags([3]), "encoding": "bgr8"}] * 3,
         layout="file")
    _bag(OUT / "bag_unknown_encoding.mcap", [{"image": _tags([3]), "encoding": "h265"}] * 3,
         layout="file")
    _bag(OUT / "bag_broken_jpeg.mcap", [{"image": good_jpeg}, {"image": good_jpeg[:400]},
                                        {"image": b""}, {"image": good_jpeg}], layout="file")
    _bag(OUT / "bag_camera_info_zero.mcap", [{"image": _tags([3]), "info": _info_with([0.0] * 9,
                                                                                      [0.0] * 12)}] * 3,
         layout="file")
    _bag(OUT / "bag_camera_info_nan.mcap",
         [{"image": _tags([3]), "info": _info_with([float("nan")] * 9)}] * 3, layout="file")
    _bag(OUT / "bag_camera_info_p_only.mcap", [{"image": _tags([3]), "info": _info_with(
        [0.0] * 9, [80.0, 0, 47.5, 0, 0, 80.0, 35.5, 0, 0, 0, 1, 0])}] * 3, layout="file")
    _bag(OUT / "bag_duplicated_and_foreign_ids.mcap",
         [{"image": _tags([5, 5])}, {"image": _tags([300, 586])}, {"image": _tags([3, 300])}],
         layout="file")
    (OUT / "metadata.yaml").unlink()  # left by the single-file bags; each names its own file

    # YAML: intrinsics, calibration, cap model.
    cam = CAM.to_camera_yaml()
    for name, k in (("zero", [0.0] * 9), ("nan", [float("nan")] * 9),
                    ("inf", [float("inf"), 0, 47.5, 0, 80.0, 35.5, 0, 0, 1])):
        bad = {**cam, "camera_matrix": {"rows": 3, "cols": 3, "data": k}}
        (OUT / f"intrinsics_{name}.yaml").write_text(yaml.safe_dump(bad))
    (OUT / "intrinsics_missing_fields.yaml").write_text("image_width: 96\n")
    (OUT / "intrinsics_list.yaml").write_text("- 1\n- 2\n")
    (OUT / "intrinsics_huge_size.yaml").write_text(yaml.safe_dump(
        {**cam, "image_width": 10**30}))
    binary = rng.integers(0, 256, 300, np.uint8).tobytes()
    for stem in ("intrinsics", "calibration", "model"):
        (OUT / f"{stem}_binary.yaml").write_bytes(binary)
        (OUT / f"{stem}_utf16.yaml").write_text("key: [1, 0, 0, 0]\n", encoding="utf-16")
        (OUT / f"{stem}_invalid_yaml.yaml").write_text("key: [1, 0\n  - : :\n")
    (OUT / "calibration_bad_quaternion.yaml").write_text(
        "R_cap_head_q_wxyz: [0, 0, 0, 0]\ncalibrated: true\n")
    (OUT / "calibration_nan.yaml").write_text("R_cap_head_q_wxyz: [.nan, 0, 0, 1]\n")
    (OUT / "calibration_calibrated_maybe.yaml").write_text(
        "R_cap_head_q_wxyz: [1, 0, 0, 0]\ncalibrated: maybe\n")
    model = nominal_model().to_dict()
    dup = {**model, "tags": [model["tags"][0], model["tags"][0]] + model["tags"][2:]}
    (OUT / "model_duplicated_ids.yaml").write_text(yaml.safe_dump(dup))
    (OUT / "model_no_tags.yaml").write_text("frame: cap\nunits: mm\n")
    (OUT / "model_wrong_units.yaml").write_text(yaml.safe_dump({**model, "units": "inch"}))
    nan = {**model, "tags": [{"id": 0, "corners_mm": [[float("nan")] * 3] * 4}]}
    (OUT / "model_nan.yaml").write_text(yaml.safe_dump(nan))

    # Labels CSV.
    header = ("frame,stamp_ns,frame_id,tags_detected,tags_used,rms_px,reliability,cap_qw,cap_qx,"
              "cap_qy,cap_qz,cap_x_m,cap_y_m,cap_z_m,head_qw,head_qx,head_qy,head_qz,"
              "head_yaw_deg,head_pitch_deg,head_roll_deg,calibrated,detected_ids,reason\n")
    row = "0,1000,cam,2,2,0.1,0.9,1,0,0,0,0,0,0.6,1,0,0,0,0,0,0,0,3 7,\n"
    (OUT / "labels_torn_row.csv").write_text(header + row + row[:20])
    (OUT / "labels_wrong_header.csv").write_text("a,b,c\n1,2,3\n")
    (OUT / "labels_binary.csv").write_bytes(binary)
    (OUT / "labels_bad_numbers.csv").write_text(header + row.replace("1000", "soon"))
    (OUT / "labels_ragged.csv").write_text(header + "0,1000\n" + row)
    total = sum(p.stat().st_size for p in OUT.rglob("*") if p.is_file())
    print(f"{sum(1 for p in OUT.rglob('*') if p.is_file())} files, {total / 1024:.0f} kB in {OUT}")


if __name__ == "__main__":
    main()

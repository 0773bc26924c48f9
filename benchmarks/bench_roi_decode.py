"""Feasibility of decoding only the tracked region of each JPEG frame (issue 15), one core.

On a tracked frame the pipeline reads pixels only near the predicted tags, yet the replay decodes
the whole 1920x1080 JPEG (``cv2.imdecode`` grey, ~32 % of a frame's CPU). libjpeg-turbo 3's
TurboJPEG API can decompress a cropping region (``tj3SetCroppingRegion``): the rows above it are
entropy-decoded but not inverse-DCT'd, the rows below are not read, the columns beside it are
entropy-decoded only. Neither Python wrapper on PyPI exposes that for decompression (pyturbojpeg
2.6.1 wraps the lossless transform crop; turbojpeg 0.0.2 only full decompression), so this script
calls the library with ctypes; ``--lib`` names a libturbojpeg >= 3 (Debian 12's is 2.1.5, which has
no tj3 API). OpenCV has no cropped decode (``IMREAD_REDUCED_*`` scales).

1. ``ficap synth`` renders the continuous 1080p drive of bench_replay_command (or ``--bag``).
2. The frames are replayed in order through ``FrameProcessor`` (tracking on, default settings, full
   ``cv2.imdecode`` frames, so the labels are those of ``ficap replay``). Before each frame the
   region a region-decode would ask for is taken from the tracker's own state:
   - ``tags``: the bounding box of the tags ``predict_tags`` puts in the frame at the extrapolated
     pose (the tags a tracked frame refines and verifies) plus ``--tag-margin`` px (default 32: the
     edge search's 8 px, the coarse passes' shifts and the cell windows),
   - ``region``: ``Tracker._predict_roi`` (every front-facing tag at the last pose plus the motion
     margin: the region a region search uses),
   each widened outwards to the JPEG's iMCU grid (8 or 16 px; TurboJPEG refuses a left edge off the
   grid). After the frame: how it was found (tracked / region / image search), and whether its
   found tags' corners (+ 8 px) lie inside each region.
3. Timing, interleaved frame by frame on the same core, ``--rounds`` rounds, CPU time
   (``time.process_time``): ``cv2.imdecode`` grey (the replay's decode), TurboJPEG full grey, and
   TurboJPEG grey cropped to each region. Per frame the median of the rounds.
4. Bit-identity: every cropped decode is compared with the full ``cv2.imdecode`` image's window.

The whole-frame estimate applies the measured saving to bench_replay_command's in-pipeline figures
(``--command-ms``, ``--decode-ms``, ``--at3-ms``: 15.62, 4.82 and 104.8 ms per frame, the run recorded
in docs/benchmarks.md): the decode's ms become decode_ms * (cropped / full cv2) on the frames whose
prediction exists (a search frame decodes everything).

Usage: .venv/bin/python benchmarks/bench_roi_decode.py --lib /path/libturbojpeg.so.0.3.0
       [--seconds 20] [--rounds 3] [--core 0] [--bag EXISTING_SYNTH_BAG]
"""

from __future__ import annotations

import argparse
import ctypes
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent
FPS = 30

# TurboJPEG 3 constants (turbojpeg.h).
_TJINIT_DECOMPRESS = 1
_TJPARAM_SUBSAMP, _TJPARAM_JPEGWIDTH, _TJPARAM_JPEGHEIGHT = 4, 5, 6
_TJPF_GRAY = 6
#: iMCU width / height in px by TJSAMP (444, 422, 420, GRAY, 440, 411, 441).
_MCU_W = {0: 8, 1: 16, 2: 16, 3: 8, 4: 8, 5: 32, 6: 8}
_MCU_H = {0: 8, 1: 8, 2: 16, 3: 8, 4: 16, 5: 8, 6: 32}


class _Region(ctypes.Structure):
    _fields_ = [("x", ctypes.c_int), ("y", ctypes.c_int), ("w", ctypes.c_int), ("h", ctypes.c_int)]


class TurboGray:
    """Grey decode of a whole JPEG or of a region, through libturbojpeg >= 3 (ctypes)."""

    def __init__(self, lib_path: str) -> None:
        lib = ctypes.CDLL(lib_path)
        if not hasattr(lib, "tj3SetCroppingRegion"):
            raise SystemExit(f"{lib_path} has no tj3 API (libjpeg-turbo >= 3 needed)")
        lib.tj3Init.restype = ctypes.c_void_p
        lib.tj3Init.argtypes = [ctypes.c_int]
        lib.tj3DecompressHeader.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t]
        lib.tj3Get.argtypes = [ctypes.c_void_p, ctypes.c_int]
        lib.tj3SetCroppingRegion.argtypes = [ctypes.c_void_p, _Region]
        lib.tj3Decompress8.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t,
                                       ctypes.c_void_p, ctypes.c_int, ctypes.c_int]
        lib.tj3GetErrorStr.restype = ctypes.c_char_p
        lib.tj3GetErrorStr.argtypes = [ctypes.c_void_p]
        self.lib = lib
        self.handle = lib.tj3Init(_TJINIT_DECOMPRESS)
        self.full = _Region(0, 0, 0, 0)  # TJUNCROPPED

    def _check(self, rc: int) -> None:
        if rc != 0:
            raise RuntimeError(self.lib.tj3GetErrorStr(self.handle).decode())

    def header(self, buf: np.ndarray) -> tuple[int, int, int]:
        """(width, height, TJSAMP) of the JPEG in ``buf``."""
        self._check(self.lib.tj3DecompressHeader(self.handle, buf.ctypes.data, buf.size))
        g = self.lib.tj3Get
        return g(self.handle, _TJPARAM_JPEGWIDTH), g(self.handle, _TJPARAM_JPEGHEIGHT), \
            g(self.handle, _TJPARAM_SUBSAMP)

    def decode(self, buf: np.ndarray, region: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Grey pixels of the whole image, or of ``region`` (x, y, w, h; x on the iMCU grid)."""
        lib, h_ = self.lib, self.handle
        self._check(lib.tj3DecompressHeader(h_, buf.ctypes.data, buf.size))
        if region is None:
            w, h = lib.tj3Get(h_, _TJPARAM_JPEGWIDTH), lib.tj3Get(h_, _TJPARAM_JPEGHEIGHT)
            self._check(lib.tj3SetCroppingRegion(h_, self.full))
        else:
            w, h = region[2], region[3]
            self._check(lib.tj3SetCroppingRegion(h_, _Region(*region)))
        out = np.empty((h, w), np.uint8)
        self._check(lib.tj3Decompress8(h_, buf.ctypes.data, buf.size, out.ctypes.data, w, _TJPF_GRAY))
        return out


    def decode_into(self, buf: np.ndarray, region: tuple[int, int, int, int], out: np.ndarray) -> None:
        """Decode ``region`` straight into its window of the full-size C-contiguous ``out``."""
        lib, h_ = self.lib, self.handle
        x, y = region[0], region[1]
        self._check(lib.tj3DecompressHeader(h_, buf.ctypes.data, buf.size))
        self._check(lib.tj3SetCroppingRegion(h_, _Region(*region)))
        dst = out.ctypes.data + y * out.strides[0] + x
        self._check(lib.tj3Decompress8(h_, buf.ctypes.data, buf.size, dst, out.strides[0], _TJPF_GRAY))


def aligned(box: tuple[float, float, float, float], width: int, height: int, mcu_w: int,
            mcu_h: int) -> tuple[int, int, int, int] | None:
    """(x0, y0, x1, y1) px widened outwards to the iMCU grid and clipped: (x, y, w, h), or None."""
    x0, y0, x1, y1 = box
    x0 = max(0, int(np.floor(x0 / mcu_w)) * mcu_w)
    y0 = max(0, int(np.floor(y0 / mcu_h)) * mcu_h)
    x1 = min(width, int(np.ceil(x1 / mcu_w)) * mcu_w)
    y1 = min(height, int(np.ceil(y1 / mcu_h)) * mcu_h)
    if x1 - x0 < mcu_w or y1 - y0 < mcu_h:
        return None
    return x0, y0, x1 - x0, y1 - y0


def tags_region(tracker, camera, stamp_ns: int, margin_px: float,  # noqa: ANN001
                info: dict) -> tuple[int, int, int, int] | None:
    """The region of the tags ``predict_tags`` puts in the frame at the tracker's extrapolated pose,
    + ``margin_px``, on the iMCU grid (what a tracked frame refines and verifies), or None."""
    from ficap_ros.vision.tracking import predict_tags

    predicted = tracker._predict_pose(camera, stamp_ns)
    if predicted is None:
        return None
    _, corners = predict_tags(tracker.model, camera, predicted, tracker.config)
    if not len(corners):
        return None
    lo, hi = corners.reshape(-1, 2).min(axis=0), corners.reshape(-1, 2).max(axis=0)
    return aligned((lo[0] - margin_px, lo[1] - margin_px, hi[0] + margin_px, hi[1] + margin_px),
                   info["width"], info["height"], *info["mcu"])


def regions(bag: Path, tj: TurboGray, tag_margin_px: float) -> tuple[list, list, dict]:
    """Replay the drive (tracking on) and collect, per frame, the regions a cropped decode would
    ask for before it, and how the frame was then found."""
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.sources import open_frames
    from ficap_ros.vision.pipeline import FrameProcessor

    raws = list(open_frames(bag).raw_frames())
    bufs = [np.frombuffer(r.payload, np.uint8) for r in raws]
    width, height, samp = tj.header(bufs[0])
    mcu_w, mcu_h = _MCU_W[samp], _MCU_H[samp]
    info = {"width": width, "height": height, "samp": samp, "mcu": (mcu_w, mcu_h)}
    proc = FrameProcessor(nominal_model(), tracking=True)
    tracker = proc.tracker
    rows = []
    for raw, buf in zip(raws, bufs):
        gray = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        cam, stamp = raw.camera, raw.stamp_ns
        tags, region = tags_region(tracker, cam, stamp, tag_margin_px, info), None
        roi = tracker._predict_roi(cam, stamp, gray.shape)
        if roi is not None:
            x, y, w, h = roi
            region = aligned((x, y, x + w, y + h), width, height, mcu_w, mcu_h)
        r = proc.process(gray, cam, stamp)
        pts = np.concatenate([d.corners_px for d in r.detections]) if r.detections else np.zeros((0, 2))

        def holds(box):  # noqa: ANN001, ANN202
            if box is None or not len(pts):
                return None
            x, y, w, h = box
            return bool(np.all((pts[:, 0] - 8 >= x) & (pts[:, 0] + 8 <= x + w)
                               & (pts[:, 1] - 8 >= y) & (pts[:, 1] + 8 <= y + h)))

        rows.append({"tags": tags, "region": region, "search": r.search.name,
                     "tags_in": holds(tags), "region_in": holds(region), "n": len(r.detections)})
    return raws, bufs, rows, info


def _fingerprint(r) -> bytes:  # noqa: ANN001
    """Every number of a frame result that reaches the labels, as bytes (exact comparison)."""
    parts = [np.array([d.tag_id for d in r.detections], np.int64).tobytes()]
    parts += [np.asarray(d.corners_px, np.float64).tobytes() for d in r.detections]
    p = r.pose
    if p is not None:
        parts += [p.T_cam_cap.rotation.as_quat().tobytes(), np.asarray(p.T_cam_cap.translation_m).tobytes(),
                  np.asarray(p.covariance).tobytes(),
                  np.array([p.rms_px, p.reliability, p.rot_err95_deg, p.trans_err95_mm]).tobytes(),
                  repr(p.used_ids).encode()]
    return b"".join(parts)


def pipeline_check(bufs: list, raws: list, tj: TurboGray, info: dict, tag_margin_px: float) -> dict:
    """Two trackers side by side, frame by frame: one fed ``cv2.imdecode`` (the replay), one fed a
    zeroed frame with only its own predicted tags' region decoded (the whole frame when it has no
    prediction). Are the results identical, and what does each decode cost inside the loop?"""
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.vision.pipeline import FrameProcessor

    width, height = info["width"], info["height"]
    ref, roi = FrameProcessor(nominal_model(), tracking=True), FrameProcessor(nominal_model(), tracking=True)
    pt = time.process_time
    same, cropped, ms_ref, ms_roi = 0, 0, [], []
    for raw, buf in zip(raws, bufs):
        cam, stamp = raw.camera, raw.stamp_ns
        t0 = pt()
        gray = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        ms_ref.append((pt() - t0) * 1e3)
        r_ref = ref.process(gray, cam, stamp)
        t0 = pt()
        box = tags_region(roi.tracker, cam, stamp, tag_margin_px, info)
        if box is None:
            img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        else:
            img = np.zeros((height, width), np.uint8)
            tj.decode_into(buf, box, img)
            cropped += 1
        ms_roi.append((pt() - t0) * 1e3)
        r_roi = roi.process(img, cam, stamp)
        same += _fingerprint(r_ref) == _fingerprint(r_roi)
    return {"frames": len(bufs), "identical": same, "cropped": cropped,
            "ms_ref": float(np.mean(ms_ref)), "ms_roi": float(np.mean(ms_roi))}


def time_decodes(bufs: list, rows: list, tj: TurboGray, n_rounds: int) -> dict[str, np.ndarray]:
    """Per frame and round, ms of CPU for each decode, interleaved frame by frame; also checks
    that every cropped decode equals the window of the full ``cv2.imdecode``."""
    kinds = ("cv2 full", "tj full", "tj tags", "tj region", "tj floor")
    ms = {k: np.full((n_rounds, len(bufs)), np.nan) for k in kinds}
    mismatches = {"tj full": 0, "tj tags": 0, "tj region": 0}
    pt = time.process_time
    for rnd in range(n_rounds):
        for k, (buf, row) in enumerate(zip(bufs, rows)):
            t0 = pt()
            ref = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
            t1 = pt()
            full = tj.decode(buf)
            t2 = pt()
            ms["cv2 full"][rnd, k], ms["tj full"][rnd, k] = (t1 - t0) * 1e3, (t2 - t1) * 1e3
            if rnd == 0 and not np.array_equal(full, ref):
                mismatches["tj full"] += 1
            # The floor of any crop: one iMCU at the bottom right, i.e. every row entropy-decoded
            # (Huffman cannot skip) and almost nothing inverse-DCT'd.
            fh, fw = ref.shape
            t0 = pt()
            tj.decode(buf, (fw - fw % 16 - 16, fh - 16, 16, 16))
            ms["tj floor"][rnd, k] = (pt() - t0) * 1e3
            for name, box in (("tj tags", row["tags"]), ("tj region", row["region"])):
                if box is None:
                    continue
                t0 = pt()
                crop = tj.decode(buf, box)
                ms[name][rnd, k] = (pt() - t0) * 1e3
                if rnd == 0:
                    x, y, w, h = box
                    if not np.array_equal(crop, ref[y:y + h, x:x + w]):
                        mismatches[name] += 1
    return {**{k: np.median(v, axis=0) for k, v in ms.items()}, "mismatches": mismatches}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lib", required=True, help="path of a libturbojpeg >= 3 shared library")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of the rendered drive, s")
    ap.add_argument("--rounds", type=int, default=3, help="timed rounds over the frames")
    ap.add_argument("--core", type=int, default=0, help="the one core everything runs on")
    ap.add_argument("--bag", type=Path, help="an existing ficap synth bag (skips rendering)")
    ap.add_argument("--tag-margin", type=float, default=32.0, help="px around the predicted tags")
    ap.add_argument("--command-ms", type=float, default=15.62, help="whole command, ms a frame")
    ap.add_argument("--decode-ms", type=float, default=4.82, help="its JPEG decode, ms a frame")
    ap.add_argument("--at3-ms", type=float, default=104.8, help="AprilTag 3 decimate 1, ms a frame")
    args = ap.parse_args()
    os.sched_setaffinity(0, {args.core})
    started = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    load0 = os.getloadavg()
    tj = TurboGray(args.lib)
    with tempfile.TemporaryDirectory() as tmp:
        bag = args.bag
        if bag is None:
            bag = Path(tmp) / "drive"
            frames = int(round(args.seconds * FPS))
            subprocess.run([sys.executable, "-m", "ficap_ros.cli", "synth", "--out", str(bag),
                            "--resolution", "1080p", "--frames", str(frames), "--fps", str(FPS),
                            "--seed", "0", "--quiet"], check=True)
        raws, bufs, rows, info = regions(bag, tj, args.tag_margin)
    res = time_decodes(bufs, rows, tj, args.rounds)
    check = pipeline_check(bufs, raws, tj, info, args.tag_margin)
    load1 = os.getloadavg()
    n = len(rows)
    area = info["width"] * info["height"]
    searches = {s: sum(r["search"] == s for r in rows) for s in ("TRACKED", "REGION", "IMAGE")}
    commit = subprocess.run(["git", "-C", str(HERE.parent), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(HERE.parent), "status", "--porcelain"],
                           capture_output=True, text=True).stdout.strip()
    print(f"{started} UTC, commit {commit}{'+dirty' if dirty else ''}, OpenCV {cv2.__version__}, "
          f"lib {Path(args.lib).name}; load {load0[0]:.1f}/{load0[1]:.1f} -> {load1[0]:.1f}/{load1[1]:.1f}")
    print(f"{n} frames {info['width']}x{info['height']}, TJSAMP {info['samp']}, iMCU {info['mcu']}; "
          f"found by {searches}; {args.rounds} rounds; mismatching frames {res['mismatches']}")
    cv_full = float(np.mean(res["cv2 full"]))
    print("| decode | frames | region area share (mean / max) | found tags inside | CPU ms/frame "
          "(mean of per-frame medians) | x cv2 full on the same frames |")
    print("|---|---|---|---|---|---|")
    print(f"| cv2.imdecode grey, full | {n} | 100 % | - | {cv_full:.2f} | 1.00 |")
    print(f"| TurboJPEG grey, full | {n} | 100 % | - | {np.mean(res['tj full']):.2f} | "
          f"{np.mean(res['tj full']) / cv_full:.2f} |")
    est = {}
    for name, key in (("tj tags", "tags"), ("tj region", "region")):
        have = np.array([r[key] is not None for r in rows])
        shares = np.array([r[key][2] * r[key][3] / area for r in rows if r[key] is not None])
        inside = [r[f"{key}_in"] for r in rows if r[f"{key}_in"] is not None]
        crop = res[name][have]
        ratio = float(np.mean(crop) / np.mean(res["cv2 full"][have]))
        # The in-pipeline decode scaled by the measured ratio on the frames that have a region.
        decode_new = args.decode_ms * (have.mean() * ratio + (1 - have.mean()))
        cmd_new = args.command_ms - (args.decode_ms - decode_new)
        est[name] = (cmd_new, args.at3_ms / cmd_new)
        print(f"| TurboJPEG grey, {key} region | {have.sum()} | {100 * shares.mean():.1f} % / "
              f"{100 * shares.max():.1f} % | {sum(inside)} of {len(inside)} | {np.mean(crop):.2f} | "
              f"{ratio:.2f} |")
    print(f"| TurboJPEG grey, 16x16 px at the bottom right (floor: every row entropy-decoded) | {n} | "
          f"0.01 % | - | {np.mean(res['tj floor']):.2f} | {np.mean(res['tj floor']) / cv_full:.2f} |")
    for key in ("tags", "region"):
        boxes = np.array([r[key] for r in rows if r[key] is not None], dtype=float)
        print(f"{key} region: mean x {boxes[:, 0].mean():.0f}-{(boxes[:, 0] + boxes[:, 2]).mean():.0f}, "
              f"y {boxes[:, 1].mean():.0f}-{(boxes[:, 1] + boxes[:, 3]).mean():.0f} px")
    print(f"in the loop (two trackers side by side, one pass): {check['identical']} of {check['frames']} "
          f"frame results identical with only the tags region decoded ({check['cropped']} frames cropped, "
          f"zeros elsewhere); decode {check['ms_ref']:.2f} (cv2 full) vs {check['ms_roi']:.2f} ms a frame "
          f"(prediction, zeroed frame and cropped decode)")
    for name, (cmd_new, x) in est.items():
        print(f"estimate with {name}: whole command {args.command_ms:.2f} -> {cmd_new:.2f} ms a frame, "
              f"{args.at3_ms / args.command_ms:.1f}x -> {x:.1f}x AprilTag 3")
    return 0


if __name__ == "__main__":
    sys.exit(main())

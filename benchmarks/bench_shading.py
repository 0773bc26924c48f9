"""Why blender_dev's neutral sets carry a depth error no residual shows: the corners of each oblique
tag shift along its foreshortening (toward its nearer side), a shift the pose takes into the depth.
Measured here: how unevenly each face is lit (a lamp at the camera makes the nearer side brighter),
how large the shift is, and (``--mechanism``) what makes it: the lens blur on small foreshortened
cells first, the uneven light on top.

Per set, over the tags the pose used (``ficap joint``, default settings) whose view angle is over
24 deg (sin > 0.4):
    contrast ratio: the quiet zone's grey level minus the black border's, on the side of the tag
        its foreshortening points to (``uncertainty._tilt_mode``'s direction: the image direction of the
        tag's inward normal, toward the middle of the cap) over the opposite side (medians over
        the sides' sample points and over the tags; from the image, truth corners);
    point light at the camera: the same ratio for irradiance from a point source at the camera
        centre (inverse square times the cosine of incidence; geometry only, no image);
    tilt shift: the true corner errors (detected minus projected truth) fitted by the shift of
        every tag along its foreshortening times the sine of its view angle
        (``uncertainty._tilt_mode``, px at a tag seen edge-on) and the tags' common radial offset,
        per frame; the depth error the tilt share causes through the fit (``A d``, mm);
    tag by tag: the same shift fitted to each tag alone (its 8 corner errors on its own tilt
        mode), averaged over the tags whose corners the cell-edge fit made and over those left
        with their outer-line corners (``edge_shift_px`` NaN: cells too small or the fit refused).
Synth rows: ``ficap synth``'s realistic chain, one frame a second of a naturalistic drive; and
"synth as <set>": ``synth.render`` at each blender_dev set's true poses, camera K, lighting preset,
PSF and tone curve (as in bench_realism.py), the direct renderer-to-renderer check.

What makes the shift (``--mechanism``): noise-free ``synth.render`` frames (no JPEG) at the true
poses of every 2nd of blender_dev 540p neutral's first 20 frames, each detected whole-image
(``TagDetector``, default ``edge`` corners), the true corner errors of the clean tags (view < 75
deg) fitted as above at the true pose: with the neutral light as ``ficap synth`` renders it (a lamp
at the camera) and with the lamp's light spread evenly (flat: the same mean level, no fall-off
across a face), over tone curves and lens PSFs.

Usage: .venv/bin/python benchmarks/bench_shading.py [--frames 25] [--blender-dev PATH] [--record]
       [--sets dev_540p_neutral,...] [--no-synth-drives] [--mechanism]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import load_avg, machine_line, md_table, record_section  # noqa: E402

from ficap_ros.geometry.cap_model import nominal_model  # noqa: E402
from ficap_ros.vision import pose as pose_mod  # noqa: E402
from ficap_ros.vision import uncertainty as unc_mod  # noqa: E402
from ficap_ros.vision.pipeline import FrameProcessor  # noqa: E402
from ficap_ros.vision.reprojection import (  # noqa: E402
    TagObservations,
    project_px,
    residuals_and_jacobian,
)

MODEL = nominal_model()
_CAPTURED: dict = {}
_TERMS = pose_mod.uncertainty_terms


def _capture(obs, T, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
    """The pose's own observations and weights at its final pose (wraps ``uncertainty_terms``)."""
    _CAPTURED.update(obs=obs, T=T, sigma=args[0] if args else kwargs.get("tag_sigma_px"),
                     edge_shift=args[1] if len(args) > 1 else kwargs.get("edge_shift_px"))
    return _TERMS(obs, T, *args, **kwargs)


def _sample(img: np.ndarray, pts: np.ndarray) -> float:
    x = pts[:, 0].reshape(1, -1).astype(np.float32)
    y = pts[:, 1].reshape(1, -1).astype(np.float32)
    return float(np.median(cv2.remap(img.astype(np.float32), x, y, cv2.INTER_LINEAR)))


def side_contrast(img: np.ndarray, corners_px: np.ndarray, model_m: np.ndarray, T, K: np.ndarray):  # noqa: ANN001
    """(image contrast ratio, point-light ratio, sin view) of one tag: the side its foreshortening
    points to over the opposite side. Tag coordinates: border corners at +-4 cells; quiet zone
    sampled at 4.5 cells, black border at 3.5 cells, along the middle 5 cells of each side."""
    H = cv2.getPerspectiveTransform(np.array([[-4, -4], [4, -4], [4, 4], [-4, 4]], np.float32),
                                    corners_px.astype(np.float32))
    ctr = model_m.mean(axis=0)
    ua = (model_m[1] - model_m[0]) / np.linalg.norm(model_m[1] - model_m[0])
    va = (model_m[3] - model_m[0]) / np.linalg.norm(model_m[3] - model_m[0])
    inward = np.cross(ua, va)  # u x v = -n (cap-spec.md): toward the sphere's centre
    R, t = T.rotation_matrix, T.translation_m
    p0, p1 = K @ (R @ ctr + t), K @ (R @ (ctr + 1e-3 * inward) + t)
    u = p1[:2] / p1[2] - p0[:2] / p0[2]
    u /= max(np.linalg.norm(u), 1e-12)
    cc = R @ ctr + t
    sin_view = float(np.sqrt(max(0.0, 1.0 - (abs((R @ inward) @ cc) / np.linalg.norm(cc)) ** 2)))
    centre_px = cv2.perspectiveTransform(np.zeros((1, 1, 2), np.float32), H)[0, 0]
    sides = []
    s = np.linspace(-2.5, 2.5, 11)
    for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        def at(r: float) -> np.ndarray:
            pts = np.stack([dx * r + (dy != 0) * s, dy * r + (dx != 0) * s], 1)
            return cv2.perspectiveTransform(pts[None].astype(np.float32), H)[0]

        mid = cv2.perspectiveTransform(np.array([[[dx * 4.0, dy * 4.0]]], np.float32), H)[0, 0]
        contrast = _sample(img, at(4.5)) - _sample(img, at(3.5))
        q = ctr + (dx * ua + dy * va) * 0.018  # the quiet zone's middle, 18 mm from the centre
        P = R @ q + t
        irradiance = abs((R @ inward) @ P) / np.linalg.norm(P) / float(P @ P)
        sides.append((float((mid - centre_px) @ u), contrast, irradiance))
    far, near = max(sides), min(sides)
    if near[1] <= 1.0:
        return None
    return far[1] / near[1], far[2] / near[2], sin_view


def measure(frames, camera, label: str) -> dict:  # noqa: ANN001
    proc = FrameProcessor(MODEL)
    K = camera.K
    ratios, light, tilts, radials, depth = [], [], [], [], []
    by_fit: dict[bool, list[float]] = {True: [], False: []}  # per-tag shift: cell-fitted or not
    pose_mod.uncertainty_terms = _capture
    try:
        for image, truth, stamp in frames:
            _CAPTURED.clear()
            r = proc.process(image, camera, stamp)
            if r.pose is None or "obs" not in _CAPTURED:
                continue
            obs, T = _CAPTURED["obs"], _CAPTURED["T"]
            d = (obs.image_px - project_px(K, truth, obs.model_m)).reshape(-1)
            tilt = unc_mod._tilt_mode(obs, T)
            radial = (2.0 * unc_mod._tag_basis(obs.image_px)[:, :, 2]).reshape(-1)
            coef, *_ = np.linalg.lstsq(np.stack([tilt, radial], 1), d, rcond=None)
            res, J = residuals_and_jacobian(T, obs)
            sigma = _CAPTURED["sigma"]
            rel = np.ones(len(obs)) if sigma is None else sigma / np.median(sigma)
            w = np.repeat(1.0 / rel**2, 8)
            A = np.linalg.solve(J.T @ (w[:, None] * J), J.T * w)
            tz = (A @ (coef[0] * tilt))[5]  # x = (d_theta, t): t_z
            es = _CAPTURED["edge_shift"]
            fitted = np.ones(len(obs), bool) if es is None else np.isfinite(np.asarray(es, float))
            for k, (d_t, t_t) in enumerate(zip(d.reshape(-1, 8), tilt.reshape(-1, 8))):
                if t_t @ t_t > 4 * 0.4**2:  # sin view > 0.4 (4 corners)
                    by_fit[bool(fitted[k])].append(float(d_t @ t_t / (t_t @ t_t)))
            tilts.append(coef[0])
            radials.append(coef[1])
            depth.append(1e3 * tz)
            gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            true_px = project_px(K, truth, obs.model_m)
            for k in range(len(obs)):
                out = side_contrast(gray, true_px[k], obs.model_m[k], truth, K)
                if out is not None and out[2] > 0.4:
                    ratios.append(out[0])
                    light.append(out[1])
    finally:
        pose_mod.uncertainty_terms = _TERMS
    row = {"frames": len(tilts), "tags": len(ratios), "ratio": float(np.median(ratios)),
           "light": float(np.median(light)), "tilt": float(np.mean(tilts)), "tilt_sd": float(np.std(tilts)),
           "depth": float(np.median(depth)), "radial": float(np.mean(radials)),
           "fitted": (len(by_fit[True]), float(np.mean(by_fit[True])) if by_fit[True] else float("nan")),
           "line": (len(by_fit[False]), float(np.mean(by_fit[False])) if by_fit[False] else float("nan"))}
    print(f"{label:30s} {row}", file=sys.stderr, flush=True)
    return row


def synth_as(name: str, root: Path | None) -> tuple:
    """``synth.render`` frames at a blender_dev set's true poses, camera and render chain."""
    import blender_dev
    from bench_realism import tone_of

    from ficap_ros.tools.synth import RenderConfig, render

    ds = blender_dev.load_set(name, root or blender_dev.BLENDER_DEV)
    tone, gamma = tone_of(ds.tone)
    cfg = RenderConfig(lighting=ds.lighting, tone=tone, gamma=gamma, psf_sigma_px=ds.psf_sigma_px,
                       jpeg_quality=95)

    def frames(offset: int = 0):  # noqa: ANN202
        for f in ds.frames:
            yield render(ds.true_model, ds.camera, f.T_cam_cap, cfg, seed=f.index + 1 + offset).image, \
                f.T_cam_cap, f.stamp_ns

    return frames, ds.camera


def mechanism(root: Path | None) -> str:
    """The ``--mechanism`` table (module docstring)."""
    import dataclasses

    import blender_dev

    from ficap_ros.tools.synth import RenderConfig, lighting, render
    from ficap_ros.vision.detector import TagDetector
    from ficap_ros.vision.tracking import view_angles_deg

    ds = blender_dev.load_set("dev_540p_neutral", root or blender_dev.BLENDER_DEV)
    model, K = ds.true_model, ds.camera.K
    lamp = lighting.LIGHTS["neutral"]
    # Flat: the lamp's light at a face seen at ~40 deg, spread evenly (one level per face).
    flat = dataclasses.replace(lamp, ambient=lamp.ambient + 0.75 * lamp.camera_lamp, camera_lamp=0.0)
    detector = TagDetector()
    rows = []
    for tone, gamma, psf in (("linear", 2.2, 0.0), ("linear", 2.2, 0.6), ("gamma", 1.8, 0.0),
                             ("gamma", 1.8, 0.6), ("gamma", 1.8, 1.0)):
        row = [f"{tone}{'' if tone == 'linear' else ' ' + str(gamma)}", f"{psf:.1f}"]
        for light in (flat, lamp):
            lighting.LIGHTS["neutral"] = light
            try:
                cfg = RenderConfig(lighting="neutral", tone=tone, gamma=gamma, psf_sigma_px=psf, noise=False)
                coefs = []
                for f in ds.frames[:20:2]:
                    frame = render(model, ds.camera, f.T_cam_cap, cfg, seed=f.index + 1)
                    angles = dict(zip(model.ids, view_angles_deg(model, f.T_cam_cap)))
                    got = {d.tag_id: d.corners_px for d in detector.detect(frame.image)}
                    ids = [t for t in frame.visible_ids(0.999) if t in got and angles[t] < 75.0]
                    if len(ids) < 4:
                        continue
                    obs = TagObservations.of({t: got[t] for t in ids}, model, K)
                    d = (obs.image_px - project_px(K, f.T_cam_cap, obs.model_m)).reshape(-1)
                    tilt = unc_mod._tilt_mode(obs, f.T_cam_cap)
                    radial = (2.0 * unc_mod._tag_basis(obs.image_px)[:, :, 2]).reshape(-1)
                    coef, *_ = np.linalg.lstsq(np.stack([tilt, radial], 1), d, rcond=None)
                    coefs.append(coef)
            finally:
                lighting.LIGHTS["neutral"] = lamp
            c = np.mean(coefs, axis=0)
            row += [f"{c[0]:+.3f}", f"{c[1]:+.3f}"]
        print(row, file=sys.stderr, flush=True)
        rows.append(row)
    return md_table(["tone", "PSF sigma px", "tilt shift px, flat light", "common radial px, flat light",
                     "tilt shift px, lamp at the camera", "common radial px, lamp at the camera"], rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=25, help="synth frames per condition (default 25)")
    ap.add_argument("--blender-dev", type=Path, default=None)
    ap.add_argument("--record", action="store_true")
    ap.add_argument("--sets", default=None, help="blender_dev sets (default: all but the as-built one)")
    ap.add_argument("--no-synth-drives", action="store_true")
    ap.add_argument("--mechanism", action="store_true", help="also the noise-free what-makes-the-shift table")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    import bench_uncertainty as bu

    t0 = time.time()
    load_before = load_avg()
    sets = bu.blender_sets(args.blender_dev)
    sets.pop("blender dev_1080p_neutral_asbuilt", None)  # its plates are off by ~1 mm: not a corner shift
    if args.sets:
        sets = {k: v for k, v in sets.items() if k.split(" ", 1)[1] in args.sets.split(",")}
    for name in list(sets):
        sets["synth as " + name.split(" ", 1)[1]] = synth_as(name.split(" ", 1)[1], args.blender_dev)
    if not args.no_synth_drives:
        sets.update(bu.synth_sets(args.frames, ["540p", "1080p"], ["neutral", "high", "low"]))
    rows = []
    for name, (frames, camera) in sets.items():
        m = measure(frames() if callable(frames) else frames, camera, name)
        rows.append([name, m["frames"], m["tags"], f"{m['ratio']:.3f}", f"{m['light']:.3f}",
                     f"{m['tilt']:+.3f} ± {m['tilt_sd']:.3f}", f"{m['depth']:+.2f}", f"{m['radial']:+.3f}",
                     f"{m['fitted'][1]:+.3f} ({m['fitted'][0]}) / {m['line'][1]:+.3f} ({m['line'][0]})"])
    table = md_table(["set", "frames", "tags (view > 24 deg)", "contrast ratio, foreshortened side / opposite",
                      "point light at the camera", "tilt shift px (mean ± sd over frames)",
                      "depth error it causes, median mm", "common radial px",
                      "tag by tag: shift of cell-fitted / line-only tags px (tags)"], rows)
    if args.mechanism:
        table += ("\n\nWhat makes the shift (noise-free synth at 540p neutral's poses, `--mechanism`):\n\n"
                  + mechanism(args.blender_dev))
    print(table)
    if args.record:
        body = (f"Machine: {machine_line()}; {load_avg()} ({load_before} at the start); "
                f"{(time.time() - t0) / 60:.1f} min. `benchmarks/bench_shading.py --frames {args.frames}"
                f"{' --mechanism' if args.mechanism else ''}`.\n\n"
                + (__doc__ or "").split("\n\nUsage:")[0] + "\n\n" + table)
        record_section("Uneven light across a face (bench_shading.py)", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Calibrated uncertainty: do the 95 % error bounds cover the true errors, how sharp are they, and
does reliability rank frames by error?

For every frame with a pose, the pose's ``rot_err95_deg`` / ``trans_err95_mm`` (``ficap_ros.vision.pose``:
per-tag residuals, uneven light, floors propagated through the weighted fit) against the true
error of ``T_cam_cap``: the geodesic rotation angle and the translation length. Per set:
    coverage: share of frames whose true error is within the bound (target 90-99 %);
    sharpness: median bound / median true error (target <= 3);
    ideal: the sharpness a perfectly calibrated Gaussian with each frame's covariance shape would
        give (median over frames of the bound / the median of its error norm): ~1.9 for an
        isotropic 3-D error, 2.9 for a 1-D one (translation is mostly depth: 2.4-2.9);
    Spearman: rank correlation of ``reliability`` with minus the rotation error, and of minus the
        translation bound with minus the translation error (target >= 0.6);
    ceiling (synth): rank correlation of the errors of two independent noise realisations of the
        same poses (same drive, another render seed). The error's reproducible share: no
        predictor of a frame's expected error ranks the realised errors better than about its
        square root (``sqrt(ICC)``); near 0, the frames are equally good within their noise.
        Under ``high`` light the spotlights are part of the realisation (drawn per render), so
        there it is not a ceiling for a predictor that sees them (``light_gradient_px`` does);
    and, beside it, the residual-only bound (sigma_res^2 (J^T J)^-1, the covariance of old).
Rows: ours (``joint``, tags weighted by their corner noise), ours with equal tag weights (the pose
before the weights: accuracy beside it), and the naive peer (OpenCV sub-pixel corners + SQPnP/LM),
whose worse corners the bounds must follow too.
Second table: what the translation bound is made of (``pose.uncertainty_sources``, grouped): per
source, the median over frames of its share of the translation variance.
What-ifs (not recorded): ``--tilt-shift-px`` (a floor for the shift along the foreshortening),
``--per-tag-offset`` (the measured radial offset's pose error taken tag by tag instead of as the
tags' mean, ``per_tag_offset_terms``); ``--photometric`` (ours also with the tag-level photometric
corner fit, ``DetectorConfig(edge_photometric=True)``, beside the default corners; the equal-weights
row left out; docs/benchmarks.md "Calibrated uncertainty with photometric corners"); ``--at KEY=VALUE,...`` (ours' coverage
and sharpness with other ``UncertaintyConfig`` values, from the same kept terms); ``--grid``
(the synth calibration again, from each frame's kept uncertainty terms, no re-fit: every
``GRID`` combination of the light-gradient gains and the residual inflation; the pick is the one
with the smallest bounds, mean log sharpness over rotation and translation of the synth rows,
whose rotation and translation bounds cover >= 90 % on every synth row; blender rows shown at
it, a check); ``--offset-gain-grid`` (``--grid`` also over a gain on the measured common radial
offset, ``OFFSET_GAINS``: is that offset, counted as a known mean, overstated?); ``--scale-shape`` (per set, the factor on the
bounds that covers exactly 90 % and the sharpness at it: is a set's miss the bounds' overall scale
or their frame-to-frame shape?); ``--synth-as``
adds ``synth.render`` at every blender_dev set's poses and chain (``bench_shading.synth_as``).
Sets: every ``../shared/data/blender_dev`` set (independent renders; a check, nothing is tuned to
them) and ``ficap synth`` drives (540p/1080p x neutral/high/low, one frame a second of a
naturalistic drive, seed per condition, the realistic image chain ``ficap synth`` renders). The
synth rows are what ``UncertaintyConfig`` was calibrated on; ``--seed-offset`` renders another
noise realisation of them (a held-out check).

Usage: .venv/bin/python benchmarks/bench_uncertainty.py [--frames 60] [--record] [--dump FILE]
       [--blender-dev PATH] [--seed-offset N] [--no-ceiling] [--tilt-shift-px PX] [--synth-as]
       [--per-tag-offset] [--photometric] [--grid] [--offset-gain-grid] [--at KEY=VALUE,...]
       [--scale-shape]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Progress, load_avg, machine_line, md_table, record_section  # noqa: E402

from ficap_ros.geometry.cap_model import nominal_model  # noqa: E402
from ficap_ros.geometry.metrics import angle_deg  # noqa: E402
from ficap_ros.vision import pose as pose_mod  # noqa: E402
from ficap_ros.vision import uncertainty as unc_mod  # noqa: E402
from ficap_ros.vision.detector import DetectorConfig  # noqa: E402
from ficap_ros.vision.pipeline import FrameProcessor, pose_config_for  # noqa: E402
from ficap_ros.vision.pose import PoseConfig  # noqa: E402
from ficap_ros.vision.reprojection import (  # noqa: E402
    TagObservations,
    residuals_and_jacobian,
)
from ficap_ros.vision.uncertainty import UncertaintyConfig  # noqa: E402

METHODS = {
    "ficap joint": (DetectorConfig(), PoseConfig(method="joint")),
    "ficap, equal weights": (DetectorConfig(),
                             PoseConfig(method="joint", uncertainty=UncertaintyConfig(weight_tags=False))),
    "naive peer": (DetectorConfig(corner_refine="subpix"), PoseConfig(method="naive")),
}
#: ``--photometric``: ours with the tag-level photometric corner fit.
PHOTOMETRIC = "ficap joint, photometric"
#: ``--grid``: the UncertaintyConfig values searched (light_gradient_gain, light_gradient_tilt_gain,
#: residual_inflation), as the defaults were calibrated.
GRID = {
    "light_gradient_gain": (0.0, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0),
    "light_gradient_tilt_gain": (0.0, 0.1, 0.2, 0.35, 0.5, 0.7, 1.0),
    "residual_inflation": (1.0, 1.1, 1.25, 1.5),
}
#: ``--offset-gain-grid``: what-if gains on the measured common radial offset (``seen["bias_common"]``,
#: as a mean in the bounds and as its square in the covariance), searched with ``GRID``; 1 is ours.
OFFSET_GAINS = (0.0, 0.25, 0.5, 0.75, 1.0)
#: Second-realisation render seeds: seed * 10_000 + frame index + this (frame indices stay < 5000).
CEILING_SEED_OFFSET = 5000


def residual_only_bound(result, camera, model) -> float:  # noqa: ANN001
    """The rotation bound of the covariance of old: sigma_res^2 (J^T J)^-1 (``residuals_and_jacobian``,
    ``TagObservations`` are the estimator's own)."""
    pose = result.pose
    corners = {}
    for d in result.detections:
        if d.tag_id in pose.used_ids and d.tag_id not in corners:
            corners[d.tag_id] = camera.undistort_px(d.corners_px)
    obs = TagObservations.of(corners, model, camera.K)
    res, J = residuals_and_jacobian(pose.T_cam_cap, obs)
    sigma2 = float(res @ res) / max(len(res) - 6, 1)
    try:
        cov = np.linalg.inv(J.T @ J) * sigma2
    except np.linalg.LinAlgError:
        return float("inf")
    order = [3, 4, 5, 0, 1, 2]
    return unc_mod.error_bound95(cov[np.ix_(order, order)])[0]


def ideal_ratio(covs: list[np.ndarray], rows: slice, scale: float, rng: np.random.Generator) -> float:
    """The sharpness (median bound / median error) of errors drawn from the covariances themselves."""
    bounds, norms = [], []
    for cov in covs:
        block = cov[rows, rows] * scale**2
        lam = np.clip(np.linalg.eigvalsh(0.5 * (block + block.T)), 0.0, None)
        bounds.append(unc_mod._bound95(block, np.zeros(3), float("inf")))
        norms.append(np.linalg.norm(rng.standard_normal((200, 3)) * np.sqrt(lam), axis=1))
    return float(np.median(bounds) / np.median(np.concatenate(norms)))


KEYS = ("rot_err", "trans_err", "rot95", "trans95", "rel", "rot95_res", "tags", "cov", "key", "sources",
        "terms")
#: What the translation bound is made of: groups of ``uncertainty.uncertainty_sources``.
SOURCE_GROUPS = {
    "residuals: per-tag shift": ("residual_shift",),
    "residuals: per-tag scale": ("residual_scale",),
    "residuals: turn, shear, projective": ("residual_turn", "residual_shear", "residual_projective"),
    "light gradient: tilt": ("light_tilt",),
    "light gradient: noise": ("light_noise",),
    "measured common offset": ("common_offset",),
    "floors": ("floor_noise", "floor_bias", "floor_tilt", "floor_model", "floor_intrinsics"),
}
_CAPTURED: dict = {}
_TERMS = pose_mod.uncertainty_terms


def _capture(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
    """Keep the last pose's terms (wraps ``pose.uncertainty_terms``)."""
    out = _TERMS_IMPL[0](*args, **kwargs)
    _CAPTURED["terms"] = out
    return out


def per_tag_offset_terms(obs, T, tag_sigma_px=None, edge_shift_px=None, at=None):  # noqa: ANN001, ANN201
    """What-if (``--per-tag-offset``): the measured radial offset's pose error from each tag's own
    radial residual instead of the tags' mean (the special case of one offset shared by all).
    Each tag's radial coefficient of the residuals, through the fit, scaled back by the share the
    fit leaves of a common radial offset; per block (translation, rotation) shrunk by what the
    tags' random scale noise alone gives (the ``scale`` term carries that as a spread). Passed
    on as the ``bias_common`` mode (unit 1: its floor then adds 0.002^2 of it, negligible)."""
    terms, seen = _TERMS(obs, T, tag_sigma_px, edge_shift_px, at=at)
    res, J = residuals_and_jacobian(T, obs) if at is None else at
    n = len(obs)
    rel = (np.ones(n) if tag_sigma_px is None
           else np.asarray(tag_sigma_px, float) / max(float(np.median(tag_sigma_px)), 1e-12))
    w = np.repeat(1.0 / rel**2, 8)
    try:
        A = np.linalg.solve(J.T @ (w[:, None] * J), J.T * w)
    except np.linalg.LinAlgError:
        return terms, seen
    B = unc_mod._tag_basis(obs.image_px)[:, :, 2]
    coef = np.einsum("tj,tj->t", B, -res.reshape(n, 8))
    radial = 2.0 * B.reshape(-1)
    left = max(1.0 - float(radial @ (w * (J @ (A @ radial)))) / float(radial @ (w * radial)), 0.1)
    o = (A @ (B * coef[:, None]).reshape(-1))[unc_mod._ROS_ORDER] / left
    for rows in (slice(0, 3), slice(3, 6)):
        noise = float(np.trace(terms["scale"][rows, rows])) * seen["scale"] ** 2 / left**2
        size = float(o[rows] @ o[rows])
        o[rows] *= np.sqrt(max(1.0 - noise / size, 0.0)) if size > 0.0 else 0.0
    return {**terms, "bias_common": np.outer(o, o)}, {**seen, "bias_common": 1.0}


_TERMS_IMPL = [_TERMS]


def translation_shares(config: UncertaintyConfig) -> list[float]:
    """Share of the last pose's translation variance (trace) per ``SOURCE_GROUPS`` entry."""
    terms, seen = _CAPTURED["terms"]
    parts = unc_mod.uncertainty_sources(terms, seen, config)
    tr = {k: float(np.trace(v[:3, :3])) for k, v in parts.items()}
    total = max(sum(tr.values()), 1e-300)
    return [sum(tr[k] for k in keys) / total for keys in SOURCE_GROUPS.values()]


def run_frames(frames, camera, model, label: str, methods=METHODS) -> dict[str, dict[str, list]]:  # noqa: ANN001
    """frames: iterable of (image, T_cam_cap truth, stamp_ns); per method, per-frame numbers."""
    procs = {name: FrameProcessor(model, det, pose) for name, (det, pose) in methods.items()}
    out = {name: {k: [] for k in KEYS} for name in methods}
    frames = list(frames)
    prog = Progress(len(frames), label)
    for image, truth, stamp in frames:
        for name, proc in procs.items():
            _CAPTURED.clear()
            pose_mod.uncertainty_terms = _capture
            try:
                r = proc.process(image, camera, stamp)
            finally:
                pose_mod.uncertainty_terms = _TERMS
            if r.pose is None:
                continue
            p = r.pose
            o = out[name]
            o["rot_err"].append(float(angle_deg(p.T_cam_cap.rotation, truth.rotation)))
            o["trans_err"].append(1e3 * float(np.linalg.norm(p.T_cam_cap.translation_m - truth.translation_m)))
            o["rot95"].append(p.rot_err95_deg)
            o["trans95"].append(p.trans_err95_mm)
            o["rel"].append(p.reliability)
            o["rot95_res"].append(residual_only_bound(r, camera, model))
            o["tags"].append(p.tags_used)
            o["cov"].append(p.covariance.tolist())
            o["key"].append(int(stamp))
            o["sources"].append(translation_shares(methods[name][1].uncertainty) if "terms" in _CAPTURED
                                else [float("nan")] * len(SOURCE_GROUPS))
            o["terms"].append(_CAPTURED.get("terms"))
        prog.update()
    prog.close()
    return out


def summarize(o: dict[str, list], twin: dict[str, list] | None = None) -> dict[str, float]:
    e, b, et, bt = (np.asarray(o[k], dtype=float) for k in ("rot_err", "rot95", "trans_err", "trans95"))
    br = np.asarray(o["rot95_res"], dtype=float)
    if e.size < 3:
        return {"n": int(e.size)}
    rng = np.random.default_rng(0)
    covs = [np.asarray(c) for c in o["cov"]]
    s = {
        "n": int(e.size),
        "rot_median_err": float(np.median(e)),
        "rot_median_bound": float(np.median(b)),
        "rot_coverage": float(np.mean(e <= b) * 100),
        "rot_sharpness": float(np.median(b) / np.median(e)),
        "rot_ideal": ideal_ratio(covs, slice(3, 6), np.degrees(1.0), rng),
        "trans_median_err": float(np.median(et)),
        "trans_median_bound": float(np.median(bt)),
        "trans_coverage": float(np.mean(et <= bt) * 100),
        "trans_sharpness": float(np.median(bt) / np.median(et)),
        "trans_ideal": ideal_ratio(covs, slice(0, 3), 1e3, rng),
        "spearman": float(spearmanr(o["rel"], -e).correlation),
        "spearman_trans": float(spearmanr(-bt, -et).correlation),
        "res_only_coverage": float(np.mean(e <= br) * 100),
        "res_only_sharpness": float(np.median(br) / np.median(e)),
        "sources": np.nanmedian(np.asarray(o["sources"], dtype=float), axis=0).tolist(),
        "ceiling_rot": float("nan"),
        "ceiling_trans": float("nan"),
    }
    if twin is not None:
        other = {k: (r, t) for k, r, t in zip(twin["key"], twin["rot_err"], twin["trans_err"])}
        pairs = [(r, t, other[k]) for k, r, t in zip(o["key"], o["rot_err"], o["trans_err"]) if k in other]
        if len(pairs) >= 3:
            s["ceiling_rot"] = float(spearmanr([p[0] for p in pairs], [p[2][0] for p in pairs]).correlation)
            s["ceiling_trans"] = float(spearmanr([p[1] for p in pairs], [p[2][1] for p in pairs]).correlation)
    return s


def bounds_at(o: dict[str, list], config: UncertaintyConfig,
              offset_gain: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Every frame's (rotation deg, translation mm) bounds again under ``config``, from its kept
    terms (``pose.combine_uncertainty`` / ``uncertainty_bounds`` / ``error_bound95``, as
    ``pose.estimate`` does; the pose itself does not depend on these settings); ``offset_gain``
    (what-if, ``--offset-gain-grid``) scales the measured common radial offset."""
    rot, trans = [], []
    for t in o["terms"]:
        if t is None:
            rot.append(float("nan"))
            trans.append(float("nan"))
            continue
        terms, seen = t
        if offset_gain != 1.0:
            seen = {**seen, "bias_common": offset_gain * seen["bias_common"]}
        cov = unc_mod.combine_uncertainty(terms, seen, config)
        r, tr = unc_mod.error_bound95(cov, *unc_mod.uncertainty_bounds(terms, seen, config, cov))
        rot.append(r)
        trans.append(tr)
    return np.asarray(rot), np.asarray(trans)


def grid_search(per_set: dict[str, dict[str, list]], base: UncertaintyConfig,
                offset_gains: tuple[float, ...] = (1.0,),
                calibrate_on: tuple[str, ...] = ("synth",)) -> tuple[dict, list]:
    """``--grid``: (pick, rows). The ``GRID`` combination (times ``offset_gains``, ``bounds_at``)
    with the smallest mean log sharpness (rotation and translation) over the calibration sets
    (``calibrate_on``: the ``synth`` drives and/or the ``cycles`` sets) among those covering >= 90 %
    in both on every calibration set (none: the one with the largest worst coverage); rows: per
    set, coverage and sharpness at the pick."""
    import itertools

    keys = list(GRID)
    synth = [n for n in per_set
             if any(n.startswith(kind + " ") for kind in calibrate_on) and not n.startswith("synth as ")]
    errs = {n: (np.asarray(o["rot_err"], float), np.asarray(o["trans_err"], float))
            for n, o in per_set.items()}
    best, best_key, best_gain = None, None, 1.0
    for values, gain in itertools.product(itertools.product(*(GRID[k] for k in keys)), offset_gains):
        cfg = replace(base, **dict(zip(keys, values)))
        worst, cost = 100.0, 0.0
        for n in synth:
            b = bounds_at(per_set[n], cfg, gain)
            for e, bb in zip(errs[n], b):
                worst = min(worst, float(np.mean(e <= bb) * 100))
                cost += float(np.log(np.median(bb) / np.median(e)))
        key = (worst < 90.0, -worst if worst < 90.0 else cost)
        if best_key is None or key < best_key:
            best, best_key, best_gain = cfg, key, gain
    pick = {k: getattr(best, k) for k in keys}
    if offset_gains != (1.0,):
        pick["common_offset_gain"] = best_gain
    return pick, coverage_rows(per_set, best, best_gain)


def coverage_rows(per_set: dict[str, dict[str, list]], config: UncertaintyConfig,
                  offset_gain: float = 1.0) -> list[list[str]]:
    """Per set: rotation and translation coverage / sharpness with the bounds under ``config``
    (and ``offset_gain``: ``bounds_at``)."""
    rows = []
    for n, o in per_set.items():
        b = bounds_at(o, config, offset_gain)
        e = (np.asarray(o["rot_err"], float), np.asarray(o["trans_err"], float))
        rows.append([n] + [f"{np.mean(ee <= bb) * 100:.0f} % / {np.median(bb) / np.median(ee):.2f}"
                           for ee, bb in zip(e, b)])
    return rows


def scale_shape_rows(per_set: dict[str, dict[str, list]]) -> list[list[str]]:
    """``--scale-shape``: per set, the factor on the bounds that covers exactly 90 % of the frames
    (the 90 % quantile of error / bound: below 1, the bounds are larger than they need to be there)
    and the sharpness the bounds would have at it (that factor x median bound / median error). A
    sharpness <= 3 at the factor says each frame's bound has the right shape and size relative to
    the set's other frames, and only the set's overall scale is off: what would be missing is a
    term whose size changes between conditions as the error does."""
    rows = []
    for n, o in per_set.items():
        cells = []
        for e, b in ((o["rot_err"], o["rot95"]), (o["trans_err"], o["trans95"])):
            e, b = np.asarray(e, float), np.asarray(b, float)
            ok = np.isfinite(e) & np.isfinite(b) & (b > 0)
            if ok.sum() < 3:
                cells += ["-", "-"]
                continue
            s90 = float(np.quantile(e[ok] / b[ok], 0.9))
            cells += [f"{s90:.2f}", f"{s90 * np.median(b[ok]) / np.median(e[ok]):.2f}"]
        rows.append([n] + cells)
    return rows


def dev_format_sets(root: Path, names: Sequence[str], label: str) -> dict[str, tuple]:
    """Sets in blender_dev's format under ``root`` (``blender_dev.load_set``), as "<label> <name>"."""
    from blender_dev import load_set

    out = {}
    for name in names:
        s = load_set(name, root)
        out[f"{label} {name}"] = ([(f.image, f.T_cam_cap, f.stamp_ns) for f in s.frames], s.camera)
    return out


def blender_sets(root: Path | None) -> dict[str, tuple]:
    import blender_dev

    root = root or blender_dev.BLENDER_DEV
    if not root.is_dir():
        print(f"blender_dev not found at {root}: skipped (--blender-dev PATH)", file=sys.stderr)
        return {}
    return dev_format_sets(root, blender_dev.SETS, "blender")


def synth_sets(n_frames: int, resolutions: list[str], lightings: list[str],
               seed_offset: int = 0) -> dict[str, tuple]:
    from ficap_ros.tools.synth import (
        REALISTIC,
        RenderConfig,
        default_scene,
        naturalistic_drive,
        render,
    )

    model = nominal_model()
    out = {}
    for i, res in enumerate(resolutions):
        scene = default_scene(res)
        for j, light in enumerate(lightings):
            seed = 100 + 10 * i + j
            # One frame a second: tracking restarts every frame, as on the irregular blender sets.
            drive = naturalistic_drive(n_frames * 30, fps=30.0, seed=seed, scene=scene)[::30]
            cfg = RenderConfig(lighting=light, **REALISTIC)  # what `ficap synth` renders

            def frames(offset: int = 0, drive=drive, cfg=cfg, scene=scene, seed=seed):  # noqa: ANN001, ANN202
                for d in drive:
                    yield render(model, scene.camera, d.T_cam_cap, cfg,
                                 seed=seed * 10_000 + d.index + seed_offset + offset).image, \
                        d.T_cam_cap, d.stamp_ns

            out[f"synth {res} {light}"] = (frames, scene.camera)
    return out


def _f(x: float, fmt: str = ".2f") -> str:
    return "-" if not np.isfinite(x) else format(x, fmt)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60, help="frames per synth condition (default 60)")
    ap.add_argument("--resolutions", default="540p,1080p")
    ap.add_argument("--lightings", default="neutral,high,low")
    ap.add_argument("--no-blender", action="store_true")
    ap.add_argument("--no-synth", action="store_true")
    ap.add_argument("--no-ceiling", action="store_true",
                    help="skip the second noise realisation of the synth drives")
    ap.add_argument("--seed-offset", type=int, default=0,
                    help="render another noise realisation of the synth drives (held-out check)")
    ap.add_argument("--blender-dev", type=Path, default=None, help="blender_dev folder")
    ap.add_argument("--cycles", type=Path, default=None, metavar="DIR",
                    help="also cycles_render.py's path-traced sets in DIR (rows 'cycles <set>')")
    ap.add_argument("--cycles-sets", default="cyc_540p_neutral,cyc_540p_high,cyc_540p_low,"
                    "cyc_1080p_neutral,cyc_1080p_high",
                    help="which sets of --cycles (default: the five calibration sets, no what-ifs)")
    ap.add_argument("--calibrate-on", action="append", choices=("synth", "cycles", "synth,cycles"),
                    help="--grid's calibration rows (default synth, as the defaults were calibrated; "
                         "repeat for several grids)")
    ap.add_argument("--record", action="store_true", help="write the table into docs/benchmarks.md")
    ap.add_argument("--dump", type=Path, help="per-frame numbers as JSON")
    ap.add_argument("--tilt-shift-px", type=float, default=None,
                    help="ours with this UncertaintyConfig.tilt_shift_px (what a floor for the shift "
                         "along the foreshortening costs; not recorded)")
    ap.add_argument("--synth-as", action="store_true",
                    help="also synth.render at every blender_dev set's poses and chain (bench_shading.synth_as)")
    ap.add_argument("--per-tag-offset", action="store_true",
                    help="what-if: per_tag_offset_terms (each tag's radial offset measured; not recorded)")
    ap.add_argument("--photometric", action="store_true",
                    help="ours also with DetectorConfig(edge_photometric=True), beside the default "
                         "corners (not recorded: docs/benchmarks.md has its own section)")
    ap.add_argument("--scale-shape", action="store_true",
                    help="per set: the factor on the bounds for exactly 90 %% coverage and the sharpness at it")
    ap.add_argument("--grid", action="store_true",
                    help="what-if: the synth calibration grid (GRID) again for each of ours (not recorded)")
    ap.add_argument("--offset-gain-grid", action="store_true",
                    help="what-if: --grid also searches a gain on the measured common radial offset "
                         "(OFFSET_GAINS; --at takes it as common_offset_gain=G)")
    ap.add_argument("--at", type=lambda t: {k: float(v) for k, v in (kv.split("=") for kv in t.split(","))},
                    default=None, metavar="KEY=VALUE,...",
                    help="what-if: also every set's coverage / sharpness for ours with these "
                         "UncertaintyConfig values (e.g. light_gradient_tilt_gain=0.1; not recorded)")
    args = ap.parse_args()
    if args.record and (args.cycles or args.photometric or args.grid or args.at or args.offset_gain_grid
                        or args.scale_shape):
        ap.error("--cycles, --photometric, --grid, --offset-gain-grid, --scale-shape and --at are not "
                 "recorded (the section's "
                 "text is by hand)")
    if args.photometric:
        det, pose = METHODS.pop("ficap joint")
        METHODS.pop("ficap, equal weights")
        naive = METHODS.pop("naive peer")
        METHODS.update({"ficap joint": (det, pose),
                        # The pose settings the pipeline applies to photometric corners (their
                        # uncertainty profile), so the sources, --at and --grid start from them.
                        PHOTOMETRIC: (replace(det, edge_photometric=True),
                                      pose_config_for(pose, replace(det, edge_photometric=True))),
                        "naive peer": naive})
    if args.per_tag_offset:
        if args.record:
            ap.error("--per-tag-offset is a what-if: not recorded")
        _TERMS_IMPL[0] = per_tag_offset_terms
    if args.tilt_shift_px is not None:
        if args.record:
            ap.error("--tilt-shift-px is a what-if: not recorded")
        METHODS["ficap joint"] = (DetectorConfig(), PoseConfig(
            method="joint", uncertainty=UncertaintyConfig(tilt_shift_px=args.tilt_shift_px)))
    cv2.setNumThreads(1)
    model = nominal_model()
    t0 = time.time()
    load_before = load_avg()
    sets: dict[str, tuple] = {}
    if not args.no_blender:
        sets.update(blender_sets(args.blender_dev))
    if args.synth_as:
        from bench_shading import synth_as

        for name in [n for n in sets if n.startswith("blender ")]:
            sets["synth as " + name[len("blender "):]] = synth_as(name[len("blender "):], args.blender_dev)
    if args.cycles:
        # cycles_render.py's path-traced sets (blender_dev's format).
        sets.update(dev_format_sets(args.cycles, args.cycles_sets.split(","), "cycles"))
    if not args.no_synth:
        sets.update(synth_sets(args.frames, args.resolutions.split(","), args.lightings.split(","),
                               args.seed_offset))
    results, dump = [], {}
    ours = {k: v for k, v in METHODS.items() if k.startswith("ficap joint")}
    grids: dict[str, dict[str, dict[str, list]]] = {k: {} for k in ours}
    for name, (frames, camera) in sets.items():
        per = run_frames(frames() if callable(frames) else frames, camera, model, name)
        twin = None
        if callable(frames) and not args.no_ceiling:
            twin = run_frames(frames(CEILING_SEED_OFFSET), camera, model, name + " (2nd noise)", ours)
        for method, o in per.items():
            if method in grids:
                grids[method][name] = o
            s = summarize(o, twin[method] if twin is not None and method in twin else None)
            results.append((name, method, s))
            dump[f"{name} | {method}"] = {k: v for k, v in o.items() if k not in ("cov", "sources", "terms")}
            if s["n"] >= 3:
                print(f"{name:34} {method:20} n {s['n']:3d} rot err {s['rot_median_err']:.4f} cover "
                      f"{s['rot_coverage']:5.1f}% sharp {s['rot_sharpness']:5.2f} (ideal {s['rot_ideal']:.2f}) "
                      f"spearman {s['spearman']:5.2f} (ceiling {_f(s['ceiling_rot'])}) | trans err "
                      f"{s['trans_median_err']:.3f} cover {s['trans_coverage']:5.1f}% sharp "
                      f"{s['trans_sharpness']:5.2f} (ideal {s['trans_ideal']:.2f}) spearman "
                      f"{s['spearman_trans']:5.2f} (ceiling {_f(s['ceiling_trans'])})",
                      file=sys.stderr, flush=True)
    if args.dump:
        args.dump.write_text(json.dumps(dump))
    rows = [[name, method, s["n"],
             f"{s['rot_median_err']:.3f} / {s['rot_median_bound']:.3f}", f"{s['rot_coverage']:.0f} %",
             f"{s['rot_sharpness']:.2f} ({s['rot_ideal']:.1f})", f"{s['spearman']:.2f}",
             f"{s['trans_median_err']:.2f} / {s['trans_median_bound']:.2f}", f"{s['trans_coverage']:.0f} %",
             f"{s['trans_sharpness']:.2f} ({s['trans_ideal']:.1f})", f"{s['spearman_trans']:.2f}",
             f"{_f(s['ceiling_rot'])} / {_f(s['ceiling_trans'])}",
             f"{s['res_only_coverage']:.0f} % / {s['res_only_sharpness']:.2f}"]
            for name, method, s in results if s["n"] >= 3]
    table = md_table(["set", "method", "frames", "rotation: median error / bound (deg)", "coverage",
                      "sharpness (ideal)", "Spearman", "translation: median error / bound (mm)",
                      "coverage", "sharpness (ideal)", "Spearman", "ceiling rot / trans",
                      "residual-only rotation bound: coverage / sharpness"], rows)
    src_rows = [[name] + ([method] if args.photometric else []) + [f"{s['trans_sharpness']:.2f}"]
                + [f"{v:.2f}" for v in s["sources"]]
                for name, method, s in results if s["n"] >= 3 and method in ours]
    src_table = md_table(["set (ours)"] + (["method"] if args.photometric else [])
                         + ["translation sharpness"] + list(SOURCE_GROUPS), src_rows)
    table += ("\n\nWhat the translation bound is made of (ours): per source, the median over frames of "
              "its share of the translation variance (trace of the translation block of "
              "`pose.uncertainty_sources`; shares of a frame sum to 1, their medians need not).\n\n"
              + src_table)
    print(table)
    if args.at:
        for method, per_set in grids.items():
            at = dict(args.at)
            gain = at.pop("common_offset_gain", 1.0)
            cfg = replace(METHODS[method][1].uncertainty, **at)
            print(f"\n{method} at {args.at}\n")
            print(md_table(["set", "rotation coverage / sharpness", "translation coverage / sharpness"],
                           coverage_rows(per_set, cfg, gain)))
    if args.scale_shape:
        for method, per_set in grids.items():
            print(f"\n{method}: scale and shape of the bounds\n")
            print(md_table(["set", "rotation: factor for 90 %", "sharpness at it",
                            "translation: factor for 90 %", "sharpness at it"], scale_shape_rows(per_set)))
    for on in (args.calibrate_on or ["synth"]) if args.grid else []:
        for method, per_set in grids.items():
            pick, grid_rows = grid_search(per_set, METHODS[method][1].uncertainty,
                                          OFFSET_GAINS if args.offset_gain_grid else (1.0,),
                                          tuple(on.split(",")))
            print(f"\n{method}: the grid on {on} picks {pick}\n")
            print(md_table(["set", "rotation coverage / sharpness", "translation coverage / sharpness"],
                           grid_rows))
    print(f"\n{(time.time() - t0) / 60:.1f} min; {load_avg()} ({load_before} at the start)", file=sys.stderr)
    if args.record:
        u = PoseConfig().uncertainty
        body = (f"Machine: {machine_line()}; {load_avg()} ({load_before} at the start); "
                f"{(time.time() - t0) / 60:.1f} min. `benchmarks/bench_uncertainty.py --frames "
                f"{args.frames}" + (f" --seed-offset {args.seed_offset}" if args.seed_offset else "")
                + (" --synth-as" if args.synth_as else "")
                + "`.\n\n"
                "Per frame with a pose: the true error of T_cam_cap (geodesic rotation angle, "
                "translation length) against its predicted 95 % bound (`rot_err95_deg`, "
                "`trans_err95_mm`). Coverage: frames within the bound (target 90-99 %). Sharpness: "
                "median bound / median error (target <= 3), and in brackets the sharpness a perfectly "
                "calibrated Gaussian of the frames' covariance shapes would give. Spearman: "
                "reliability against minus the rotation error, minus the translation bound against "
                "minus the translation error (target >= 0.6). Ceiling (synth): rank correlation of "
                "the errors of two noise realisations of the same poses (about its square root is "
                "the best any predictor of a frame's expected error can reach). Beside it, "
                "the residual-only covariance of old (sigma_res^2 (J^T J)^-1). `UncertaintyConfig` "
                f"defaults: residual-based sigmas x{u.residual_inflation}, light-gradient gains "
                f"{u.light_gradient_gain} (absorbed corner noise) and {u.light_gradient_tilt_gain} "
                f"(shift along the foreshortening), floors: corner noise {u.corner_noise_px} px, "
                f"corner bias {u.corner_bias_px} px per tag and {u.corner_bias_common_px} px common, "
                f"tilt shift {u.tilt_shift_px} px, cap model {u.model_mm} mm / {u.model_deg} deg, "
                f"intrinsics {u.principal_point_px} px / {u.focal_rel}; tags weighted by their "
                "corner noise. Calibrated on the synth rows (seeds 100-122); blender_dev is a check: "
                "nothing is tuned to it. Synth: one frame a second of a naturalistic drive per "
                "condition; 'synth as <set>': `synth.render` at that blender_dev set's true poses, "
                "camera, lighting preset, PSF and tone curve (bench_shading.synth_as), a check of "
                "how much of blender_dev's behaviour synth reproduces, not calibration data.\n\n" + table)
        record_section("Calibrated uncertainty (bench_uncertainty.py)", body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

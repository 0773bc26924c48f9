"""Calibrated uncertainty: do the 95 % error bounds cover the true errors, how sharp are they, and
does ``reliability`` rank frames by error?

For every frame with a pose: the pose's ``rot_err95_deg`` and ``trans_err95_mm`` against its true
error (the geodesic rotation angle and the translation length of ``T_cam_cap``). Per set:

* coverage: the share of frames whose error is within the bound (a calibrated 95 % bound: about
  95 %; the project asks 90-99 %);
* sharpness: median bound / median error (the project asks <= 3), and in brackets the sharpness a
  Gaussian with each frame's own covariance would give (about 1.9 for an isotropic 3-D error, 2.9
  for a 1-D one: translation is mostly depth);
* Spearman: rank correlation of ``reliability`` with minus the rotation error.

Sets: every blender_dev set and ``ficap synth`` drives (540p and 1080p x neutral, high, low light,
one frame a second of a naturalistic drive, seeds 100-122, the realistic chain). Ours and the naive
peer, whose worse corners the bounds must follow too. Each set's frames in order as ``ficap replay``
makes them, ours told the camera's timing where the set states it (the glance sets' exposure and
rolling-shutter readout, as a user who states them: the rolling-shutter pose, the blur's terms, each
frame solved again with the next frame's pose).

Which covariance terms over- or under-state the translation error: per set, each frame's error
along its stated depth direction (the covariance's largest axis) over the stated sigma there (1
for a calibrated term; its mean shows an offset the set shares), with the covariance and with the
residual-based terms alone, and each source's share of the stated depth variance.

Whether the measured common offset's sign predicts the depth error: per set, the error along the
offset's mode against the error the signed offset predicts there (correlation, slope, share
explained), and what correcting the pose by it (shrunk by its standard error) would do.

The light gradient against its noise floor: per set, the measured gradient (``light_gradient_px``)
beside the spread the edge shifts' own scatter gives a plane fitted with no gradient, the error
along the tilt mode per px of gradient (what ``light_gradient_tilt_gain`` states in the gradient
profiles) and per px of the tags' mean edge shift (what ``edge_shift_tilt_gain`` states in the
edge profile, beyond the other terms) and the depth error over the sigma the other terms state.

The leave-one-set-out fit of the shared radial corner offset's gain: one gain on the offset the
residuals show (``UncertaintyConfig.common_offset_gain``, scaled back) and on its standard error
(``common_offset_se_gain`` tied to it), ``shared_bias_gain`` 0: the defaults' rule. Each frame's
covariance terms are recorded once and the bounds recomputed at every point of a grid; for each
blender_dev set, of the points whose translation bounds cover at least 90 % of every *other* set,
the one with the smallest mean log sharpness over those sets, each weighted by its frames (every
frame counts once: a 12-frame set's median ratio does not decide the fit), is taken, and the
set's figures there are its row. The synth drives check the point fitted on all blender_dev sets
(they do not take part in the fit). Then which frames those held-out bounds miss (how many slow,
how many fast, their depth error over the stated sigma, the source stating most of it), and the
same fit over two gains jointly: the measured offset's and ``shared_bias_gain`` (the one that
follows each frame's corner noise over its cell width). Writes
docs/benchmarks/uncertainty.md and uncertainty.png.
"""

from __future__ import annotations

import sys
from collections import deque
from dataclasses import replace

import numpy as np
from scipy.stats import spearmanr

from _lib import bounds_fit, cli, devsets, report
from _lib.methods import OURS, OURS_PHOTOMETRIC, PEER
from _lib.synthdata import drive_frames
from ficap_ros.geometry.camera import CameraTiming
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.tools.synth import REALISTIC, RenderConfig
from ficap_ros.vision.pose import CapPose
from ficap_ros.vision.two_sided import TwoSidedFrames
from ficap_ros.vision.uncertainty import UncertaintyConfig, uncertainty_sources

METHODS = (OURS, PEER)
#: The grid of the two-gain fit beside the defaults': each fitted ``UncertaintyConfig`` gain's values.
FIT_AXES = {"common_offset_gain": np.round(np.arange(0.0, 3.001, 0.25), 2),
            "shared_bias_gain": np.round(np.arange(0.0, 0.601, 0.05), 2)}
#: The defaults' fit: the measured common offset and its standard error at one gain
#: (``common_offset_se_gain`` tied to ``common_offset_gain``), the corner-noise ratio term unused.
ONE_GAIN = {"axes": {"common_offset_gain": FIT_AXES["common_offset_gain"]},
            "tied": {"common_offset_se_gain": "common_offset_gain"}, "fixed": {"shared_bias_gain": 0.0}}


def run_frames(frames, camera, methods=METHODS, timing: CameraTiming | None = None  # noqa: ANN001
               ) -> dict[str, dict[str, list]]:
    """Per method, per frame with a pose: errors, bounds, reliability, covariance; for ours (the
    first method) also the pose's covariance terms (``bounds_fit.FrameTerms``, key ``terms``).

    ``frames``: (image, T_cam_cap truth, stamp ns) in order; ``timing``: the camera's exposure
    and readout as the set states them, given to ours (the peer takes none). Frames are made as
    ``ficap replay`` makes them (``TwoSidedFrames``): where the timing's motion model applies, each
    frame is solved again with the next frame's pose; elsewhere the first result stands."""
    runs = {m.name: TwoSidedFrames(m.processor(timing=None if m is PEER else timing)) for m in methods}
    # A frame finishes while the next one is processed: its terms are in the last two frames' calls.
    calls = {m.name: deque(maxlen=2) for m in methods}
    out = {m.name: {k: [] for k in ("rot", "trans", "rot95", "trans95", "rel", "cov", "terms")} for m in methods}

    def take(name: str, key: tuple, p: CapPose | None) -> None:
        if p is None:
            return
        truth, speed = key
        o = out[name]
        o["rot"].append(float(angle_deg(p.T_cam_cap.rotation, truth.rotation)))
        o["trans"].append(1e3 * float(np.linalg.norm(p.T_cam_cap.translation_m - truth.translation_m)))
        o["rot95"].append(p.rot_err95_deg)
        o["trans95"].append(p.trans_err95_mm)
        o["rel"].append(p.reliability)
        o["cov"].append(np.asarray(p.covariance))
        recorded = (bounds_fit.terms_of([c for chunk in calls[name] for c in chunk], p.T_cam_cap.translation_m)
                    if name == methods[0].name else None)
        if recorded is not None:
            error_mm = 1e3 * (p.T_cam_cap.translation_m - truth.translation_m)
            o["terms"].append(bounds_fit.FrameTerms(*recorded, o["rot"][-1], o["trans"][-1], error_mm, speed))

    before = None
    for image, truth, stamp in frames:
        speed, before = _speed_dps(before, truth, stamp), (truth, stamp)
        for name, run in runs.items():
            with bounds_fit.record_terms() as recorded:
                done = run.process((truth, speed), image, camera, stamp)
            calls[name].append(recorded)
            for key, result in done:
                take(name, key, result.pose)
    for name, run in runs.items():
        for key, result in run.finish():
            take(name, key, result.pose)
    return out


def _speed_dps(before: tuple | None, truth, stamp: int) -> float:  # noqa: ANN001 - a Transform
    """The cap's angular speed (deg/s) from the previous frame's truth ``before`` (truth, stamp),
    NaN without one within 0.1 s."""
    if before is None or not 0 < stamp - before[1] <= 100_000_000:
        return float("nan")
    return float(angle_deg(truth.rotation, before[0].rotation)) / ((stamp - before[1]) * 1e-9)


def _gains_text(gains: dict[str, float]) -> str:
    return " / ".join(f"{v:.2f}" for v in gains.values())


def loso_section(points: dict[str, dict[str, list]], corners: str = "edge") -> str:
    """The leave-one-set-out fits on blender_dev and their synth check, for the profile of the
    corner estimator ``corners`` (``UncertaintyConfig.for_corners``): the shared offset's gain
    (``ONE_GAIN``, the defaults' rule), and the two gains of ``FIT_AXES`` jointly beside it."""
    blender = {k: v["terms"] for k, v in points.items() if k.startswith("blender") and len(v["terms"]) >= 3}
    synth = {k: v["terms"] for k, v in points.items() if k.startswith("synth") and len(v["terms"]) >= 3}
    if len(blender) < 2:
        return "Leave-one-set-out fit: fewer than two blender_dev sets present."
    grids = "; ".join(f"`{k}` {v[0]:.2f}-{v[-1]:.2f} step {v[1] - v[0]:.2f}" for k, v in FIT_AXES.items())
    one, fits = _loso_table(blender, synth, corners, bounds_fit.gain_grid(ONE_GAIN["axes"], ONE_GAIN["tied"],
                                                                           ONE_GAIN["fixed"]))
    joint, _ = _loso_table(blender, synth, corners,
                           bounds_fit.gain_grid(FIT_AXES, fixed={"common_offset_se_gain": 0.0}))
    return (f"### Leave-one-set-out fit of the shared corner offset's gain\n\n"
            "Each blender_dev row: of the gains on the measured common offset and on its standard error "
            "(`common_offset_gain`, `common_offset_se_gain` tied to it; where the offset is below its noise "
            "the estimate reads 0, yet such an offset is not ruled out; `shared_bias_gain` 0), those whose "
            "translation bounds cover at least 90 % of every other blender_dev set, the one with the "
            "smallest mean log sharpness over them, each set weighted by its frames (every frame counts "
            "once; the rule is the same in every fold and for the all-set fit), and the held-out set's "
            "coverage and sharpness there; the synth rows check the gain fitted on all blender_dev sets "
            "(they take no part in the fit). The last two columns: the probability, for a calibrated 95 % "
            "bound, of as many misses as the set has or more (fewer), and of 90-99 % coverage at all for a "
            "set of its size; and, were each frame's bound exact for its covariance at the set's gains "
            "(`bounds_fit.calibrated_target_odds`: Gaussian errors drawn from it, the bound their 95 % "
            "quantile), how often a set of these frames shows sharpness <= 3, and that with 90-99 % "
            f"coverage: the target's odds at perfect calibration.\n\n{one}\n\n"
            f"{_misses_table(blender, fits, corners)}\n\n"
            "#### Two gains: the measured offset and the corner-noise ratio\n\n"
            f"The same rule over the grid {grids}, the standard error unused:\n\n{joint}\n\n"
            "The two gains substitute for each other on the training sets: a set whose depth error "
            "follows the measured offset more than the others' is covered only by the common offset, "
            "and without it in the fold the fit takes the corner-noise ratio instead.\n\n"
            "The translation error is mostly depth, one dimension, where a bound that knows each frame's "
            "sigma exactly has sharpness 2.9 (1.96 / 0.674; the brackets above give it for each set's own "
            "covariances): sharpness <= 3 with 90 % coverage asks every frame's stated depth sigma "
            "between 0.84 and 1.03 times the true one.")


def _loso_table(blender: dict[str, list], synth: dict[str, list], corners: str,
                grid: list[dict[str, float]]) -> tuple[str, list[bounds_fit.SetFit]]:
    """The leave-one-set-out rows over ``grid`` (``bounds_fit.leave_one_set_out``), the synth
    check at the all-set fit, and a line of how many sets meet 90-99 % with sharpness <= 3; and
    the fits."""
    base = UncertaintyConfig.for_corners(corners)
    table = bounds_fit.coverage_table(blender, base, grid)
    counts = {k: len(v) for k, v in blender.items()}
    fits = bounds_fit.leave_one_set_out(table, grid, counts)
    g_all = grid[bounds_fit.fitted_index(table, list(blender), counts)]
    rows = [[f.name, _gains_text(f.gains), f.frames, f"{100 * f.rot_coverage:.0f} %", f"{f.rot_sharpness:.2f}",
             f"{100 * f.trans_coverage:.0f} %", f"{f.trans_sharpness:.2f}",
             bounds_fit.binomial_reading(f.trans_misses, f.frames),
             _odds_text(bounds_fit.calibrated_target_odds(blender[f.name], replace(base, **f.gains)))]
            for f in fits]
    if synth:
        check = bounds_fit.coverage_table(synth, base, [g_all])
        for name, r in check.items():
            rows.append([f"{name} (check)", _gains_text(g_all), len(synth[name]), f"{100 * r[0, 0]:.0f} %",
                         f"{r[0, 1]:.2f}", f"{100 * r[0, 2]:.0f} %", f"{r[0, 3]:.2f}",
                         bounds_fit.binomial_reading(int(r[0, 4]), len(synth[name])),
                         _odds_text(bounds_fit.calibrated_target_odds(synth[name], replace(base, **g_all)))])
    names = " / ".join(f"`{k}`" for k in grid[0])
    head = ["set", f"{names} fitted without it", "frames", "rotation coverage", "sharpness",
            "translation coverage", "sharpness", "translation misses under a calibrated 95 % bound",
            "a calibrated bound's odds: sharpness <= 3 / and 90-99 %"]
    ok = sum(0.9 <= f.trans_coverage <= 0.99 and f.trans_sharpness <= 3 for f in fits)
    low = min(fits, key=lambda f: f.trans_coverage)
    return (f"{report.md_table(head, rows)}\n\nAll sets: {_gains_text(g_all)} (the profile's: "
            f"{_gains_text({k: getattr(base, k) for k in grid[0]})}). Held-out translation coverage "
            f"90-99 % with sharpness <= 3 on {ok} of {len(fits)} blender_dev sets; the lowest held-out "
            f"coverage {100 * low.trans_coverage:.0f} % ({low.name})."), fits


def _odds_text(odds: tuple[float, float]) -> str:
    return f"{odds[0]:.2f} / {odds[1]:.2f}"


def _misses_table(blender: dict[str, list], fits: list[bounds_fit.SetFit], corners: str) -> str:
    """Per blender_dev set, its translation misses at the gains fitted without it: how many, at
    what angular speed, the depth error over the stated sigma (axis toward +z), the source that
    states most of their depth variance, and how often the measured common offset reads 0."""
    rows = []
    for fit in fits:
        config = replace(UncertaintyConfig.for_corners(corners), **fit.gains)
        frames = blender[fit.name]
        bounds = bounds_fit.bounds_at(frames, config)[:, 1]
        missed = [f for f, b in zip(frames, bounds) if f.trans_err_mm > b and f.trans_error_mm is not None]
        speed = np.array([f.speed_dps for f in missed])
        z, top = [], []
        for f in missed:
            parts = {k: 1e6 * p[:3, :3] for k, p in uncertainty_sources(f.terms, f.seen, config).items()}
            axis = np.linalg.eigh(sum(parts.values()))[1][:, -1]
            axis = axis if axis[2] >= 0 else -axis
            var = {k: float(axis @ p @ axis) for k, p in parts.items()}
            z.append(float(f.trans_error_mm @ axis) / np.sqrt(sum(var.values())))
            top.append(max(var, key=var.get))
        common = max(set(top), key=top.count) if top else "-"
        rows.append([fit.name, len(frames), len(missed), int(np.sum(speed < 30.0)), int(np.sum(speed >= 90.0)),
                     f"{np.median(z):+.2f}" if z else "-", f"{common} ({top.count(common)})" if top else "-",
                     sum(f.seen.get("bias_common", 0.0) == 0.0 for f in missed)])
    head = ["set", "frames", "held-out translation misses", "of them under 30 deg/s", "at 90 deg/s or more",
            "depth error / stated sigma (median, toward +z)", "source stating most of their depth variance",
            "measured common offset 0"]
    return ("Which frames the shared offset's fit's held-out bounds miss (at the gains fitted without the set; the "
            "angular speed from the previous frame's truth, unknown where the set's frames are a second "
            f"apart):\n\n{report.md_table(head, rows)}")


def depth_section(points: dict[str, dict[str, list]], corners: str = "edge") -> str:
    """Which terms over- or under-state the translation error: per set, the error along each
    frame's stated depth direction over the stated sigma there (RMS and mean), with every term and
    with the residual-based ones alone, and each source's mean share of the stated depth variance."""
    config = UncertaintyConfig.for_corners(corners)
    groups = {"residual": ("residual_",), "common offset": ("common_offset",),
              "shared bias": ("shared_bias",), "light": ("light_",)}
    rows = []
    for name, v in points.items():
        frames = [f for f in v["terms"] if f.trans_error_mm is not None]
        if len(frames) < 3:
            continue
        z, z_res, shares = [], [], {g: [] for g in (*groups, "other")}
        for f in frames:
            parts = {k: 1e6 * p[:3, :3] for k, p in uncertainty_sources(f.terms, f.seen, config).items()}
            total = sum(parts.values())
            axis = np.linalg.eigh(total)[1][:, -1]
            var = {k: float(axis @ p @ axis) for k, p in parts.items()}
            s2 = sum(var.values())
            z.append(float(f.trans_error_mm @ axis) / np.sqrt(s2))
            res = sum(x for k, x in var.items() if k.startswith(("residual_", "floor_")))
            z_res.append(float(f.trans_error_mm @ axis) / np.sqrt(res))
            share = dict.fromkeys(shares, 0.0)
            for k, x in var.items():
                share[next((g for g, prefixes in groups.items() if k.startswith(prefixes)), "other")] += x / s2
            for g, x in share.items():
                shares[g].append(x)
        z, z_res = np.array(z), np.array(z_res)
        rows.append([name, len(frames), f"{np.sqrt(np.mean(z**2)):.2f} ({np.mean(z):+.2f})",
                     f"{np.sqrt(np.mean(z_res**2)):.2f} ({np.mean(z_res):+.2f})",
                     *(f"{100 * np.mean(x):.0f} %" for x in shares.values())])
    head = ["set", "frames", "depth error / stated sigma: RMS (mean)", "the same, residual-based terms alone",
            *(f"share: {g}" for g in (*groups, "other"))]
    return ("### Which terms state the depth error\n\n"
            "Each frame's translation error along its stated depth direction (the covariance's largest "
            "axis) over the stated sigma there: an RMS of 1 states the error right, under 1 overstates it, "
            "a mean away from 0 is an offset the set shares; with every term of the profile and with the "
            "residual-based terms (and floors) alone; then each source's mean share of the stated depth "
            f"variance.\n\n{report.md_table(head, rows)}")


#: The shrinkage constants shown for a pose corrected by the signed common offset (0: as measured).
SHRINK_K = (0.0, 1.0, 4.0)


def sign_section(points: dict[str, dict[str, list]]) -> str:
    """Whether the measured common offset's sign predicts the depth error: per set, the
    prediction against the translation error along the offset's mode
    (``bounds_fit.signed_offset_fit``), and what a pose corrected by it, shrunk by its standard
    error, would do to the translation error (``bounds_fit.shrunk_correction_ratios``)."""
    rows = []
    for name, v in points.items():
        fit = bounds_fit.signed_offset_fit(v["terms"])
        if not fit:
            continue
        ratios = [bounds_fit.shrunk_correction_ratios(v["terms"], k) for k in SHRINK_K]
        rows.append([name, int(fit["frames"]), f"{fit['corr']:+.2f}", f"{fit['slope']:+.2f}",
                     f"{fit['explained']:+.2f}", f"{fit['mean_error']:+.3f} / {fit['mean_predicted']:+.3f}",
                     f"{100 * fit['above_se']:.0f} %", *(f"{m:.2f} / {p95:.2f}" for m, p95 in ratios)])
    head = ["set", "frames", "correlation", "slope", "share explained at slope 1",
            "mean error / mean prediction (mm)", "offset above its standard error",
            *(f"corrected, k = {k:g}: median / p95 over uncorrected" for k in SHRINK_K)]
    return ("### Does the measured common offset's sign predict the depth error?\n\n"
            "Per frame, the translation error the signed common offset (`bias_common_signed`, outward "
            "positive) predicts along its mode (the pose's response to every tag's corners moved "
            "outward, toward the camera) against the true error along the same direction: their "
            "correlation, the slope of the error on the prediction (1: the offset as measured), the "
            "share of the error's square the prediction explains at slope 1 (negative: a correction by "
            "it adds error) and both means; then the translation error length a pose corrected by it, "
            "to first order, would have (the offset shrunk by its standard error, "
            "offset * max(0, 1 - k se^2 / offset^2)), median and p95 over the uncorrected pose's."
            f"\n\n{report.md_table(head, rows)}")


def light_section(points: dict[str, dict[str, list]], corners: str = "edge") -> str:
    """The light gradient against its noise floor: per set, the median ``light_gradient_px``, the
    median spread the edge shifts' scatter alone gives it (``bounds_fit.light_gradient_floor_px``)
    and the gradient less that floor (in quadrature); the translation error along the tilt mode
    (``uncertainty_terms``' ``tilt``) per px of gradient (RMS over RMS: what
    ``light_gradient_tilt_gain`` states, an upper bound where other errors share the direction)
    and how the size of that error ranks with the gradient and with the fitted tags' mean edge
    shift (Spearman); and the depth error over the stated sigma (RMS) without the light terms."""
    config = UncertaintyConfig.for_corners(corners)
    rows = []
    for name, v in points.items():
        frames = [f for f in v["terms"] if f.trans_error_mm is not None]
        if len(frames) < 3:
            continue
        g = np.array([f.seen.get("light_gradient", 0.0) for f in frames])
        floor = np.array([f.seen.get("light_gradient_floor", 0.0) for f in frames])
        excess = np.sqrt(np.clip(g**2 - floor**2, 0.0, None))
        k, z = [], []
        for f in frames:
            lam, vec = np.linalg.eigh(1e6 * f.terms["tilt"][:3, :3])
            a = vec[:, -1] * np.sqrt(max(lam[-1], 0.0))  # mm per px of tilt
            k.append(float(f.trans_error_mm @ a) / max(float(a @ a), 1e-18))
            parts = {n: 1e6 * p[:3, :3] for n, p in uncertainty_sources(f.terms, f.seen, config).items()}
            dark = sum(p for n, p in parts.items() if not n.startswith("light_"))
            axis = np.linalg.eigh(sum(parts.values()))[1][:, -1]
            z.append(float(f.trans_error_mm @ axis) ** 2 / float(axis @ dark @ axis))
        per_px = np.sqrt(np.mean(np.square(k))) / max(float(np.sqrt(np.mean(g**2))), 1e-12)
        shift = np.array([f.seen.get("edge_shift_mean", np.nan) for f in frames])
        ok = np.isfinite(shift)
        per_shift = (np.sqrt(np.mean(np.square(np.asarray(k)[ok])))
                     / max(float(np.sqrt(np.mean(shift[ok] ** 2))), 1e-12) if ok.any() else float("nan"))
        rho_g = spearmanr(np.abs(k), g).correlation
        rho_s = spearmanr(np.abs(k)[ok], shift[ok]).correlation if ok.sum() >= 3 else float("nan")
        rows.append([name, len(frames), f"{np.median(g):.3f}", f"{np.median(floor):.3f}",
                     f"{np.median(excess):.3f}", f"{per_px:.2f}", f"{rho_g:+.2f}",
                     f"{np.nanmedian(shift) if ok.any() else float('nan'):.2f}", f"{rho_s:+.2f}",
                     f"{per_shift:.3f}", f"{np.sqrt(np.mean(z)):.2f}"])
    head = ["set", "frames", "light gradient (px, median)", "its noise floor", "gradient less floor",
            "error along the tilt per px of gradient", "Spearman: size of that error, gradient",
            "mean edge shift (px, median)", "Spearman: size of that error, mean edge shift",
            "error along the tilt per px of mean edge shift", "depth error / sigma without the light terms"]
    return ("### The light gradient against its noise floor\n\n"
            "Per set: the median measured light gradient (`light_gradient_px`), the median spread the "
            "edge shifts' own scatter gives a fitted plane with no gradient at all (sqrt(2 s^2 / n), s "
            "the shifts' scatter about the plane, n the fitted tags) and the gradient less that floor "
            "(in quadrature); the translation error along the tilt mode per px of gradient (RMS over "
            f"RMS; `light_gradient_tilt_gain` states {config.light_gradient_tilt_gain:.2f}; other errors "
            "along the same direction make it an upper bound), how the size of that error ranks with "
            "the gradient and with the fitted tags' mean edge shift (Spearman over the set's frames), "
            "the same error per px of mean edge shift (RMS over RMS; `edge_shift_tilt_gain` states "
            f"{config.edge_shift_tilt_gain:.3f}, beyond what the other terms state along the tilt) "
            "and the depth error over the sigma the "
            f"other terms state (RMS; above 1: the light terms are needed).\n\n{report.md_table(head, rows)}")


def ideal_sharpness(covs: list[np.ndarray], rows: slice, scale: float, rng: np.random.Generator) -> float:
    """Median 95 % quantile / median of the error norm, for errors drawn from the covariances."""
    bounds, norms = [], []
    for cov in covs:
        block = 0.5 * (cov[rows, rows] + cov[rows, rows].T) * scale**2
        lam = np.clip(np.linalg.eigvalsh(block), 0.0, None)
        n = np.linalg.norm(rng.standard_normal((400, 3)) * np.sqrt(lam), axis=1)
        bounds.append(np.percentile(n, 95))
        norms.append(n)
    return float(np.median(bounds) / np.median(np.concatenate(norms)))


def summary(o: dict[str, list]) -> dict[str, float] | None:
    if len(o["rot"]) < 3:
        return None
    e, b, et, bt = (np.asarray(o[k], float) for k in ("rot", "rot95", "trans", "trans95"))
    rng = np.random.default_rng(0)
    return {
        "n": e.size, "rot_err": float(np.median(e)), "rot_bound": float(np.median(b)),
        "rot_cov": 100 * float(np.mean(e <= b)), "rot_sharp": float(np.median(b) / np.median(e)),
        "rot_ideal": ideal_sharpness(o["cov"], slice(3, 6), np.degrees(1.0), rng),
        "trans_err": float(np.median(et)), "trans_bound": float(np.median(bt)),
        "trans_cov": 100 * float(np.mean(et <= bt)), "trans_sharp": float(np.median(bt) / np.median(et)),
        "trans_ideal": ideal_sharpness(o["cov"], slice(0, 3), 1e3, rng),
        "spearman": float(spearmanr(o["rel"], -e).correlation),
    }


def sets(args) -> dict[str, tuple]:  # noqa: ANN001
    """name -> (frames callable, camera, timing): blender_dev's (with the exposure and readout each
    set states: the glance sets'), then the synth drives (timing not stated)."""
    out = {}
    for name in devsets.present(args.data):
        s = devsets.load_set(args.data, name, 8 if args.quick else None)
        out[f"blender {name.replace('dev_', '')}"] = (
            lambda s=s: [(f.image, f.T_cam_cap, f.stamp_ns) for f in s.frames], s.camera, s.timing)
    n = 10 if args.quick else 60
    for i, res in enumerate(("540p", "1080p")):
        for j, light in enumerate(("neutral", "high", "low")):
            # One frame a second: tracking restarts every frame, as on the sampled blender sets.
            cfg = RenderConfig(lighting=light, **REALISTIC)
            camera, frames = drive_frames(res, n, step=30, seed=100 + 10 * i + j, config=cfg)

            def gen(frames=frames):  # noqa: ANN001, ANN202
                import cv2

                for f in frames:
                    yield cv2.imdecode(f.jpeg, cv2.IMREAD_GRAYSCALE), f.T_cam_cap, f.stamp_ns
            out[f"synth {res} {light}"] = (gen, camera, None)
    return out


def plot(points: dict[str, dict[str, list]]) -> str:
    plt = report.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    for ax, (err, bound, unit) in zip(axes, (("rot", "rot95", "deg"), ("trans", "trans95", "mm"))):
        for kind, color in (("blender", "tab:red"), ("synth", "tab:blue")):
            e = np.concatenate([v[err] for k, v in points.items() if k.startswith(kind)] or [[]])
            b = np.concatenate([v[bound] for k, v in points.items() if k.startswith(kind)] or [[]])
            ax.scatter(b, e, s=6, alpha=0.4, color=color, label=f"{kind} (ficap)")
        lim = ax.get_xlim()
        ax.plot(lim, lim, color="k", lw=0.8, label="error = bound")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"predicted 95 % bound ({unit})")
        ax.set_ylabel(f"true error ({unit})")
        ax.set_title("rotation" if err == "rot" else "translation")
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("Each frame's error against its 95 % bound (points below the line are covered)")
    fig.tight_layout()
    return report.save_figure(fig, "uncertainty")


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="8 frames a blender_dev set, 10 a synth drive (full: every frame, 60)")
    ap.add_argument("--photometric", action="store_true",
                    help="ours with the photometric corners and their profile (prints the section; "
                         "the docs keep the default corners')")
    args = ap.parse_args(argv)
    ours = OURS_PHOTOMETRIC if args.photometric else OURS
    methods = (ours, PEER)
    import cv2

    cv2.setNumThreads(1)
    run = report.Run()
    rows, points = [], {}
    for name, (frames, camera, timing) in sets(args).items():
        per = run_frames(frames(), camera, methods, timing)
        points[name] = per[ours.name]
        for m in methods:
            s = summary(per[m.name])
            if s is None:
                continue
            rows.append([name, m.name, s["n"], f"{s['rot_err']:.3f} / {s['rot_bound']:.3f}", f"{s['rot_cov']:.0f} %",
                         f"{s['rot_sharp']:.2f} ({s['rot_ideal']:.1f})", f"{s['spearman']:.2f}",
                         f"{s['trans_err']:.2f} / {s['trans_bound']:.2f}", f"{s['trans_cov']:.0f} %",
                         f"{s['trans_sharp']:.2f} ({s['trans_ideal']:.1f})"])
            print(" | ".join(str(c) for c in rows[-1]), file=sys.stderr, flush=True)
    table = report.md_table(["set", "method", "frames", "rotation: median error / bound (deg)", "coverage",
                             "sharpness (Gaussian)", "Spearman", "translation: median error / bound (mm)",
                             "coverage", "sharpness (Gaussian)"], rows)
    ours_rows = [r for r in rows if r[1] == ours.name]
    cov_ok = sum(90 <= float(r[4].rstrip(" %")) <= 100 and 90 <= float(r[8].rstrip(" %")) for r in ours_rows)
    figure = "" if args.photometric else plot(points)  # the docs' figure is the default corners'
    corners = "photometric" if args.photometric else "edge"
    body = (f"{table}\n\n{figure}\n\n{depth_section(points, corners)}\n\n{sign_section(points)}\n\n"
            f"{light_section(points, corners)}\n\n"
            f"{loso_section(points, corners)}\n\n"
            f"Ours: rotation and translation coverage both at least 90 % on {cov_ok} of {len(ours_rows)} sets. "
            "A calibrated 95 % bound covers every frame of a set of 12-25 frames with a probability of "
            "0.28-0.54, so the 90-99 % band cannot be asked of each small set. The bounds are of the cap pose; the head "
            "calibration's own uncertainty comes on top.")
    what = ("What it measures: per set, the share of frames whose true rotation / translation error "
            "is within the pose's predicted 95 % bound (`rot_err95_deg`, `trans_err95_mm`), the "
            "bound's size against the error (sharpness; in brackets what a Gaussian with each "
            "frame's covariance would give) and how well `reliability` ranks frames by error "
            "(Spearman), on every blender_dev set and on `ficap synth` drives (one frame a second; "
            "what the light gains of `UncertaintyConfig` were calibrated on), ours and the "
            "naive peer; which covariance terms state the depth error; then the leave-one-set-out fit "
            "of the shared corner offset's gain (the defaults' rule) on blender_dev and its check on the "
            "synth drives, the frames its held-out bounds miss, and the same fit over two gains beside it.")
    report.write_section("uncertainty", what, report.how("bench_uncertainty.py", "fewer frames per set"),
                         body, run, report.command(), args.quick, args.no_doc or args.photometric)
    return 0


if __name__ == "__main__":
    sys.exit(main())

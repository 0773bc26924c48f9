"""Fast glances: pose error against the head's angular speed, with and without the camera's timing.

A glance at a mirror turns the head at 150-250 deg/s: over a 1/60 s exposure the cap smears by
several pixels (motion blur), and a rolling shutter sees the cap's top and bottom rows milliseconds
apart. Recordings: blender_dev's two glance sets (30 fps through a right-mirror glance at up to
236 deg/s; ``glance_blur``: 1/60 s exposure, global shutter; ``glance_rs``: the same through a
rolling shutter read top to bottom over 22 ms; each with the exposure and readout its
ground_truth.json states) and, where ``ficap synth`` renders a rolling shutter, synth glance drives
of the same kind (``--motion glances``, motion blur over 16.7 ms, readouts of 22 ms and 0).

Methods, every recording's frames in order as ``ficap replay`` feeds them: ours (defaults, the
recording's ``CameraTiming``: the rolling-shutter pose with the cap's velocity, bounds with the
blur's terms; each frame solved again with the next frame's pose, ``vision.two_sided``, as replay
does), ours causal (the same from the frames before only, as the live node), ours without the
timing model (every corner seen at the stamp, no exposure), and the naive peer (OpenCV sub-pixel corners, one SQPnP + LM, no tracking). Per frame: the geodesic
rotation error and the translation error against the truth at the stamp, the 95 % bounds, and the
cap's angular speed at the stamp (from the truths of the neighbouring frames). Slow frames: under
30 deg/s; fast: 90 deg/s and over. Also the angular velocity ours reports against the truth's, and
the readout ours reads from the frames when not told it (``summary.json``'s ``timing_estimate``).
Writes docs/benchmarks/glance.md and glance.png.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, fields, replace
from pathlib import Path

import cv2
import numpy as np

from _lib import cli, devsets, report
from _lib.methods import OURS, PEER
from _lib.stats import q
from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.detector import as_gray
from ficap_ros.vision.pipeline import FrameProcessor, FrameResult
from ficap_ros.vision.shutter import combine_evidence
from ficap_ros.vision.two_sided import TwoSidedFrames
from ficap_ros.vision.uncertainty import UncertaintyConfig

DEV_SETS = ("dev_540p_glance_blur", "dev_540p_glance_rs")
#: Synth glance drives: (label, ``ficap synth`` options beyond resolution, frames and seed).
SYNTH = (
    ("synth 540p glances, rolling 22 ms + blur", ("--motion", "glances", "--motion-blur",
                                                  "--exposure-ms", "16.7", "--readout-ms", "22")),
    ("synth 540p glances, blur", ("--motion", "glances", "--motion-blur", "--exposure-ms", "16.7")),
)
OURS_TIMED, OURS_CAUSAL, OURS_UNTIMED, NAIVE = ("ficap", "ficap, causal (live)",
                                                "ficap, no timing model", PEER.name)
METHODS = (OURS_TIMED, OURS_CAUSAL, OURS_UNTIMED, NAIVE)
#: The grids the motion-blur gains are fitted on (``UncertaintyConfig.motion_blur_gain`` and
#: ``motion_blur_shift_gain``, each pair).
BLUR_GRID = (0.0, 0.025, 0.05, 0.1, 0.2)
SHIFT_GRID = (0.0, 0.05, 0.1)
GAIN_GRID_PAIRS = tuple((a, b) for a in BLUR_GRID for b in SHIFT_GRID)
#: The fast-frame coverage a gain pair must reach on every recording it is fitted on.
MIN_FAST_COVERAGE = 90.0
SLOW_DPS, FAST_DPS = 30.0, 90.0
#: A fast/slow ratio within this factor of the Cramer-Rao bound's own ratio passes where that ratio is
#: over 2 (issue 25: some loss in blurred frames is physical).
BOUND_SLACK = 1.3
#: The 95 % quantile of chi-square with 3 degrees of freedom: an angular velocity error within its
#: 95 % ellipsoid has a squared Mahalanobis length under it.
CHI2_3_95 = 7.8147


@dataclass(frozen=True)
class Recording:
    """Frames in order with their truth, and the camera's timing."""

    name: str
    camera: CameraModel
    timing: CameraTiming
    images: list[np.ndarray]
    stamps_ns: np.ndarray
    truths: list[Transform]


def dev_recording(data: Path, name: str, window: slice = slice(None)) -> Recording:
    """A glance set's frames ``window`` (consecutive frames) with the timing its truth states."""
    s = devsets.load_set(data, name)
    frames = s.frames[window]
    return Recording(name.replace("dev_", ""), s.camera, s.timing, [f.image for f in frames],
                     np.array([f.stamp_ns for f in frames]), [f.T_cam_cap for f in frames])


def synth_supports_rolling() -> bool:
    from ficap_ros.tools.synth import RenderConfig

    return "readout_ms" in {f.name for f in fields(RenderConfig)}


def synth_recording(cache: Path, label: str, extra: tuple[str, ...], frames: int, seed: int) -> Recording:
    from _lib.synthdata import cached_synth_bag
    from ficap_ros.cli.synth import TRUTH_CAP_TOPIC
    from ficap_ros.io.sources import decode_raw, open_bag_reader, open_frames
    from ficap_ros.stamps import stamp_to_ns

    bag = cached_synth_bag(cache, "540p", frames, seed=seed, extra=extra)
    reader = open_bag_reader(bag)
    truth: dict[int, Transform] = {}
    try:
        conns = [c for c in reader.connections if c.topic == TRUTH_CAP_TOPIC]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            p, o = msg.pose.position, msg.pose.orientation
            truth[stamp_to_ns(msg.header.stamp)] = Transform.from_xyz_q_xyzw([p.x, p.y, p.z, o.x, o.y, o.z, o.w])
    finally:
        reader.close()
    source = open_frames(bag)
    raws = [r for r in source.raw_frames() if r.stamp_ns in truth]
    timing = source.timing or CameraTiming()  # the bag's metadata, as ficap replay reads it
    return Recording(label, raws[0].camera, timing, [decode_raw(r) for r in raws],
                     np.array([r.stamp_ns for r in raws]), [truth[r.stamp_ns] for r in raws])


def angular_velocity(rec: Recording) -> tuple[np.ndarray, np.ndarray]:
    """(speed deg/s (n,), angular velocity rad/s (n, 3), camera axes) at each stamp from the
    truths of the neighbouring frames (central differences; one-sided at the ends)."""
    n = len(rec.truths)
    w = np.full((n, 3), np.nan)
    for i in range(n):
        a, b = max(i - 1, 0), min(i + 1, n - 1)
        dt = (rec.stamps_ns[b] - rec.stamps_ns[a]) * 1e-9
        if 0.0 < dt <= 0.1:
            w[i] = (rec.truths[b] * rec.truths[a].inv()).rvec / dt
    return np.degrees(np.linalg.norm(w, axis=1)), w


def processor(method: str, timing: CameraTiming) -> FrameProcessor:
    model = nominal_model()
    if method == NAIVE:
        return PEER.processor(model)
    return FrameProcessor(model, OURS.detector, OURS.pose, tracking=True,
                          timing=None if method == OURS_UNTIMED else timing, readout_evidence=True)


def results_in_order(proc: FrameProcessor, rec: Recording, two_sided: bool) -> list[FrameResult]:
    """Every frame's result, as replay makes them (``TwoSidedFrames``: with ``two_sided`` each
    frame solved again with the next frame's pose)."""
    frames: TwoSidedFrames[int] = TwoSidedFrames(proc, enabled=two_sided)
    out: list[FrameResult | None] = [None] * len(rec.images)
    for i, (image, stamp) in enumerate(zip(rec.images, rec.stamps_ns)):
        for k, r in frames.process(i, image, rec.camera, int(stamp)):
            out[k] = r
    for k, r in frames.finish():
        out[k] = r
    assert all(r is not None for r in out)
    return out  # type: ignore[return-value]


def run(rec: Recording) -> dict[str, dict[str, np.ndarray]]:
    """Per method and frame: rotation and translation error and bounds, angular velocity error
    and its 1-sigma (ours), and, without the timing model, the readout read from the frames."""
    speed, w_true = angular_velocity(rec)
    out: dict[str, dict] = {}
    for method in METHODS:
        proc = processor(method, rec.timing)
        keys = ("rot", "trans", "rot95", "trans95", "w_err", "w_maha")
        o = {k: np.full(len(rec.images), np.nan) for k in keys}
        evidence, used = [], []
        results = results_in_order(proc, rec, two_sided=method == OURS_TIMED)
        for i, (r, truth) in enumerate(zip(results, rec.truths)):
            evidence.append(r.timing_evidence)
            p = r.pose
            used.append(sorted(p.used_ids) if p is not None else [])
            if p is None:
                continue
            o["rot"][i] = angle_deg(p.T_cam_cap.rotation, truth.rotation)
            o["trans"][i] = 1e3 * np.linalg.norm(p.T_cam_cap.translation_m - truth.translation_m)
            o["rot95"][i], o["trans95"][i] = p.rot_err95_deg, p.trans_err95_mm
            if p.velocity is not None and np.all(np.isfinite(w_true[i])):
                e = p.velocity[3:] - w_true[i]
                o["w_err"][i] = np.degrees(np.linalg.norm(e))
                o["w_maha"][i] = float(e @ np.linalg.solve(p.velocity_covariance[3:, 3:], e))
        o["speed"] = speed
        o["timing_estimate"] = combine_evidence(evidence)
        o["used_ids"] = used
        out[method] = o
    return out


def blur_bound_row(rec: Recording, res: dict[str, dict[str, np.ndarray]]) -> list[str] | None:
    """The Cramer-Rao bound's slow and fast rotation medians of a recording with a stated exposure
    (``_lib.blur_bound``: a rolling shutter's corners at their row times, the motion over the
    readout known; every fast frame, every fourth slow one, on the tags ours used) beside ours:
    None without an exposure."""
    from _lib.blur_bound import frame_rotation_draws

    if rec.timing.exposure_ms <= 0.0:
        return None
    o = res[OURS_TIMED]
    model, rng = nominal_model(), np.random.default_rng(0)
    draws: dict[bool, list[np.ndarray]] = {True: [], False: []}
    for i in range(1, len(rec.images) - 1):
        fast, slow = o["speed"][i] >= FAST_DPS, o["speed"][i] < SLOW_DPS and i % 4 == 0
        if not (fast or slow) or not o["used_ids"][i]:
            continue
        dt = (rec.stamps_ns[i + 1] - rec.stamps_ns[i - 1]) * 0.5e-9
        gray = as_gray(rec.images[i])
        draws[bool(fast)].append(frame_rotation_draws(gray, rec.camera, model, o["used_ids"][i],
                                                      tuple(rec.truths[i - 1:i + 2]), dt,
                                                      rec.timing.exposure_ms * 1e-3, rng,
                                                      timing=rec.timing))
    if not draws[True] or not draws[False]:
        return None
    b_slow, b_fast = (float(np.median(np.concatenate(draws[k]))) for k in (False, True))
    slow, fast = o["speed"] < SLOW_DPS, o["speed"] >= FAST_DPS
    ratio = q(o["rot"][fast], 50) / q(o["rot"][slow], 50)
    return [rec.name, f"{b_slow:.4f}", f"{b_fast:.4f}", f"{b_fast / b_slow:.2f}", f"{ratio:.2f}",
            f"{ratio / (b_fast / b_slow):.2f}"]


def bounds_with_gains(rec: Recording, gains: tuple[float, float]) -> np.ndarray:
    """Ours with the timing model and the motion-blur ``gains`` (``UncertaintyConfig``'s
    ``motion_blur_gain``, ``motion_blur_shift_gain``): per frame (n, 4) the rotation error (deg),
    translation error (mm) and their 95 % bounds; NaN without a pose."""
    uncertainty = replace(OURS.pose.uncertainty or UncertaintyConfig(), motion_blur_gain=gains[0],
                          motion_blur_shift_gain=gains[1])
    proc = FrameProcessor(nominal_model(), OURS.detector, replace(OURS.pose, uncertainty=uncertainty),
                          tracking=True, timing=rec.timing)
    out = np.full((len(rec.images), 4), np.nan)
    for i, (r, truth) in enumerate(zip(results_in_order(proc, rec, two_sided=True), rec.truths)):
        p = r.pose
        if p is not None:
            out[i] = (angle_deg(p.T_cam_cap.rotation, truth.rotation),
                      1e3 * np.linalg.norm(p.T_cam_cap.translation_m - truth.translation_m),
                      p.rot_err95_deg, p.trans_err95_mm)
    return out


def bound_stats(table: np.ndarray, speed: np.ndarray) -> tuple[float, ...]:
    """(rotation coverage % all, fast; translation coverage % all, fast; sharpness rotation,
    translation; the same two sharpnesses in fast frames) of one recording's
    ``bounds_with_gains``."""
    fast = speed >= FAST_DPS
    cover = [100.0 * np.mean(table[m, k] <= table[m, k + 2]) for k in (0, 1) for m in (slice(None), fast)]
    sharp = [q(table[m, k + 2], 50) / q(table[m, k], 50) for m in (slice(None), fast) for k in (0, 1)]
    return (*cover, *sharp)


def fit_gains(stats: dict[str, dict[tuple[float, float], tuple[float, ...]]],
              names: list[str]) -> tuple[float, float]:
    """The gains fitted on the recordings ``names``: of the grid's pairs whose rotation and
    translation bounds hold in at least ``MIN_FAST_COVERAGE`` % of every recording's fast frames
    (the frames the blur's terms are for), the one with the smallest mean log sharpness of the
    fast frames' rotation and translation bounds over the recordings (ties: the first); where
    none holds, the pair with the highest worst fast-frame coverage."""
    def worst_fast(g: tuple[float, float]) -> float:  # a recording without fast frames: no bar
        return min(float(np.nan_to_num(min(stats[n][g][1], stats[n][g][3]), nan=100.0)) for n in names)

    holding = [g for g in GAIN_GRID_PAIRS if worst_fast(g) >= MIN_FAST_COVERAGE]
    if not holding:
        return max(GAIN_GRID_PAIRS, key=worst_fast)
    return min(holding, key=lambda g: float(np.nanmean([np.log(stats[n][g][6]) + np.log(stats[n][g][7])
                                                        for n in names])))


def leave_one_out(recs: list[Recording]) -> tuple[list[list[str]], tuple[float, float]]:
    """The motion-blur gains fitted leaving each recording out, that recording's bounds with
    them (table rows), and the gains fitted on all of them (the defaults' check)."""
    stats = {}
    for rec in recs:
        speed = angular_velocity(rec)[0]
        stats[rec.name] = {g: bound_stats(bounds_with_gains(rec, g), speed) for g in GAIN_GRID_PAIRS}
        print(f"gains grid: {rec.name}", file=sys.stderr, flush=True)
    names = [r.name for r in recs]
    rows = []
    for name in names:
        g = fit_gains(stats, [n for n in names if n != name])
        st = stats[name][g]
        rows.append([name, f"{g[0]:g} / {g[1]:g}", f"{st[0]:.0f} / {st[1]:.0f}",
                     f"{st[2]:.0f} / {st[3]:.0f}", f"{st[4]:.2f} / {st[5]:.2f}", f"{st[6]:.2f} / {st[7]:.2f}"])
    return rows, fit_gains(stats, names)


def _cov(err: np.ndarray, bound: np.ndarray, mask: np.ndarray) -> str:
    m = mask & np.isfinite(err)
    return f"{100 * np.mean(err[m] <= bound[m]):.0f}" if m.any() else "-"


def rows_of(name: str, res: dict[str, dict[str, np.ndarray]]) -> tuple[list[list[str]], dict]:
    """Table rows of one recording and its verdict against the targets."""
    rows, verdict = [], {}
    peer_p95 = q(res[NAIVE]["rot"], 95)
    for method in METHODS:
        o = res[method]
        slow, fast = o["speed"] < SLOW_DPS, o["speed"] >= FAST_DPS
        every = np.ones_like(slow)
        med_s, med_f = q(o["rot"][slow], 50), q(o["rot"][fast], 50)
        p95 = q(o["rot"], 95)
        posed = int(np.isfinite(o["rot"]).sum())
        vel = (f"{q(o['w_err'], 50):.1f} ({_cov(o['w_maha'], np.full(len(slow), CHI2_3_95), every)} %)"
               if np.isfinite(o["w_err"]).any() else "-")
        rows.append([name, method, f"{posed}/{len(o['rot'])}", f"{med_s:.3f}", f"{med_f:.3f}",
                     f"{med_f / med_s:.2f}", f"{p95:.3f}", f"{q(o['trans'], 50):.2f} / {q(o['trans'], 95):.2f}",
                     f"{_cov(o['rot'], o['rot95'], every)} / {_cov(o['rot'], o['rot95'], fast)}",
                     f"{_cov(o['trans'], o['trans95'], every)} / {_cov(o['trans'], o['trans95'], fast)}",
                     f"{q(o['rot95'], 50) / q(o['rot'], 50):.2f} / {q(o['trans95'], 50) / q(o['trans'], 50):.2f}",
                     vel])
        if method == OURS_TIMED:
            verdict = {"every frame": posed == len(o["rot"]),
                       "fast <= 2x slow": med_f <= 2.0 * med_s if fast.any() and slow.any() else None,
                       "p95 <= half the peer's": p95 <= 0.5 * peer_p95}
    return rows, verdict


def plot(results: dict[str, dict[str, dict[str, np.ndarray]]]) -> str:
    plt = report.pyplot()
    names = list(results)
    fig, axes = plt.subplots(1, len(names), figsize=(5.2 * len(names), 4.2), squeeze=False)
    style = {OURS_TIMED: ("o", "C0"), OURS_CAUSAL: ("v", "C3"), OURS_UNTIMED: ("^", "C1"),
             NAIVE: ("s", "C2")}
    for ax, name in zip(axes[0], names):
        for method in METHODS:
            o = results[name][method]
            marker, color = style[method]
            ax.scatter(o["speed"], o["rot"], s=14, marker=marker, color=color, alpha=0.75, label=method)
        ax.set_yscale("log")
        ax.set_xlabel("cap angular speed at the stamp (deg/s)")
        ax.set_ylabel("rotation error (deg, geodesic)")
        ax.set_title(name, fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[0][0].legend(fontsize=8, loc="upper left")
    fig.suptitle("Pose error against angular speed through fast glances")
    fig.tight_layout()
    return report.save_figure(fig, "glance")


def _recordings(args) -> list[Recording]:  # noqa: ANN001 - argparse namespace
    window = slice(8, 32) if args.quick else slice(None)  # quick: the frames around the glance
    recs = [dev_recording(args.data, n, window) for n in devsets.present(args.data, DEV_SETS)]
    if synth_supports_rolling():
        frames = 60 if args.quick else 240
        recs += [synth_recording(args.cache, label, extra, frames, seed=21) for label, extra in SYNTH]
    return recs


def _gains_section(recs: list[Recording]) -> str:
    """The leave-one-recording-out fit of the motion-blur gains, as a table and its note."""
    rows, fitted = leave_one_out(recs)
    defaults = UncertaintyConfig()
    table = report.md_table(["recording left out", "gains fitted without it (blur / shift)",
                             "its rotation bound holds %, all / fast",
                             "its translation bound holds %, all / fast",
                             "its sharpness rotation / translation", "the same in fast frames"], rows)
    return ("Motion-blur gains (`UncertaintyConfig.motion_blur_gain` / `motion_blur_shift_gain`), "
            "fitted on the grids " + ", ".join(f"{g:g}" for g in BLUR_GRID) + " / "
            + ", ".join(f"{g:g}" for g in SHIFT_GRID) + ": of the pairs whose rotation and "
            f"translation bounds hold in at least {MIN_FAST_COVERAGE:g} % of the fast frames of every "
            "recording but the one each row reports, the one with the smallest mean log sharpness of "
            "the fast frames' bounds over those recordings (the blur's terms are for the fast frames; "
            "leave-one-out: a row's numbers never come from gains that saw it):\n\n"
            f"{table}\n\nFitted on all of them: "
            f"{fitted[0]:g} / {fitted[1]:g}; the defaults: {defaults.motion_blur_gain:g} / "
            f"{defaults.motion_blur_shift_gain:g}. The gains act only when the camera's exposure "
            "is given (`CameraTiming.exposure_ms`).")


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="frames 8-31 of each glance set and 60-frame synth drives")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    run_info = report.Run()
    recs = _recordings(args)
    if not recs:
        print(f"no glance set under {args.data} and no rolling-shutter synth (--data)", file=sys.stderr)
        return 1
    results, rows, verdicts, readouts, crb_rows = {}, [], [], [], []
    for rec in recs:
        res = run(rec)
        results[rec.name] = res
        crb = blur_bound_row(rec, res)
        if crb is not None:
            crb_rows.append(crb)
        r, v = rows_of(rec.name, res)
        if crb is not None and float(crb[3]) > 2.0:  # the rule where the bound itself says > 2x
            v["fast <= 2x slow"] = float(crb[4]) <= BOUND_SLACK * float(crb[3])
        rows += r
        verdicts.append([rec.name] + ["-" if ok is None else "yes" if ok else "**no**" for ok in v.values()])
        est = res[OURS_UNTIMED]["timing_estimate"]
        readouts.append([rec.name, f"{rec.timing.readout_ms:.1f}",
                         "-" if est.readout_ms is None else f"{est.readout_ms:.1f} +- {est.readout_se_ms:.1f}",
                         str(est.readout_frames)])
        print(" | ".join(r[0]), file=sys.stderr, flush=True)
    table = report.md_table(["recording", "method", "frames with a pose", "rotation median, slow (deg)",
                             "median, fast", "fast / slow", "rotation p95", "translation median / p95 (mm)",
                             "rotation bound holds %, all / fast", "translation bound holds %, all / fast",
                             "sharpness rotation / translation", "angular velocity error median deg/s "
                             "(95 % bound holds)"], rows)
    targets = report.md_table(["recording", "a pose in every frame", "fast median <= 2x slow (where "
                               f"the Cramer-Rao bound's own ratio is over 2: within {BOUND_SLACK:g}x of it)",
                               "p95 <= half the peer's"], verdicts)
    readout = report.md_table(["recording", "readout given (ms)", "read from the frames (ms)",
                               "frames with evidence"], readouts)
    body = (f"{table}\n\n{plot(results)}\n\nTargets (ours with the timing model):\n\n{targets}\n\n"
            f"Readout read from the frames by ours without the timing model (summary.json's "
            f"`timing_estimate`; signed: negative is bottom to top):\n\n{readout}\n\n"
            f"Slow: under {SLOW_DPS:g} deg/s; fast: {FAST_DPS:g} deg/s and over (the truth's angular "
            "speed at the stamp). Sharpness: median bound / median error. The angular velocity is "
            "the pose's twist (a rolling shutter's solved with the pose over the readout; a global "
            "shutter's the finite difference of the poses before, tied to the frame's own pose; "
            "none without a stated timing); its bound holds when the error is inside the 95 % "
            "ellipsoid of its covariance.")
    if crb_rows:
        body += ("\n\nA Cramer-Rao bound for the blurred frames (`benchmarks/_lib/blur_bound.py`: "
                 "each tag's pixels through the photometric model moving along the truth's path over the "
                 "exposure, levels, lens blur and tone marginalised, the pixel noise the fit's residual sd, "
                 "on the tags ours used; a rolling shutter's corners at their row times with the cap's "
                 "motion over the readout known; every fast frame, every fourth slow one): the rotation median "
                 "an efficient estimator would have, slow and fast, and ours against it:\n\n"
                 + report.md_table(["recording", "bound median, slow (deg)", "bound median, fast",
                                    "bound fast / slow", "ours fast / slow", "ours / bound (ratios)"], crb_rows))
    body += "\n\n" + _gains_section(recs)
    what = ("What it measures: pose error through fast glances against the cap's angular speed, "
            "ours with and without the camera's timing (exposure, rolling-shutter readout) beside "
            "the naive peer, on blender_dev's glance sets and synth glance drives; the bounds' "
            "coverage in fast frames, the twist's accuracy and the readout read from the frames.")
    report.write_section("glance", what, report.how("bench_glance.py", "frames 8-31 of each glance "
                         "set and 60-frame synth drives"), body, run_info, report.command(),
                         args.quick, args.no_doc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

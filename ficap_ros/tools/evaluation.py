"""Benchmark a head-pose estimator against Fi-Cap labels.

Truth and estimate are head orientations in the same frame (the labels' frontal frame F: x forward,
y left, z up; ``head_q*`` of labels.csv, ``head_pose`` of labels.mcap). They are paired by stamp
(nearest estimate within ``max_dt_ms``, each estimate used once) and compared with:
    geodesic angle (deg) = angle of R_truth^-1 R_est;
    Phi3 (deg) = arccos(|q_truth . q_est|), the paper's metric, half the geodesic angle;
    per-axis errors (deg) = estimate - truth of yaw, pitch, roll (``ficap_ros.geometry.metrics`` convention),
    wrapped to [-180, 180).
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.errors import BagError
from ficap_ros.geometry.metrics import (
    angle_deg,
    phi3_deg,
    rotation_from_ypr_deg,
    summarize_errors,
    yaw_pitch_roll_deg,
)
from ficap_ros.io.labels import read_labels_text
from ficap_ros.stamps import pair_by_stamp

__all__ = [
    "PoseSeries",
    "EvaluationResult",
    "load_series",
    "read_series_csv",
    "read_series_bag",
    "evaluate",
    "write_report",
    "POSE_TYPES",
    "DetectionStats",
    "detection_stats",
    "plot_stats",
]

#: Message types ``read_series_bag`` accepts (orientation taken from each).
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/QuaternionStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
)


@dataclass(frozen=True)
class PoseSeries:
    """Head orientations over time.

    Attributes:
        stamp_ns: (N,) int64, increasing.
        rotations: N stacked rotations (R_frontal_head).
        source: where they came from.
    """

    stamp_ns: np.ndarray
    rotations: Rotation
    source: str = ""

    def __len__(self) -> int:
        return int(self.stamp_ns.size)


def _series(stamps: list[int], quats_xyzw: list[Any], source: str) -> PoseSeries:
    if not stamps:
        raise BagError(f"{source} holds no head orientation")
    s = np.asarray(stamps, dtype=np.int64)
    q = np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4)
    good = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 1e-6)
    if not np.any(good):
        raise BagError(f"{source} holds no valid orientation")
    s, q = s[good], q[good]
    order = np.argsort(s, kind="stable")
    return PoseSeries(s[order], Rotation.from_quat(q[order]), source)


_Q_COLUMNS = (("head_qw", "head_qx", "head_qy", "head_qz"), ("qw", "qx", "qy", "qz"))
_YPR_COLUMNS = (("head_yaw_deg", "head_pitch_deg", "head_roll_deg"),
                ("yaw_deg", "pitch_deg", "roll_deg"))


def read_series_csv(path: str | Path) -> PoseSeries:
    """Head orientations from a CSV: labels.csv, or any CSV with a ``stamp_ns`` column and either
    ``qw,qx,qy,qz`` (or ``head_q*``) or ``yaw_deg,pitch_deg,roll_deg`` (or ``head_*_deg``).

    Rows with empty orientation fields are skipped.

    Raises:
        BagError: unreadable file or missing columns.
    """
    path, text = read_labels_text(path)
    reader = csv.DictReader(io.StringIO(text))
    cols = set(reader.fieldnames or [])
    if "stamp_ns" not in cols:
        raise BagError(f"{path} has no stamp_ns column")
    qcols = next((c for c in _Q_COLUMNS if set(c) <= cols), None)
    ycols = next((c for c in _YPR_COLUMNS if set(c) <= cols), None)
    if qcols is None and ycols is None:
        raise BagError(f"{path} has neither qw,qx,qy,qz nor yaw_deg,pitch_deg,roll_deg columns")
    stamps: list[int] = []
    quats: list[Any] = []
    try:
        for row in reader:
            if qcols is not None:
                vals = [row.get(c) or "" for c in qcols]
                if not all(v.strip() for v in vals):
                    continue
                w, x, y, z = (float(v) for v in vals)
                quats.append((x, y, z, w))
            else:
                vals = [row.get(c) or "" for c in ycols]  # type: ignore[union-attr]
                if not all(v.strip() for v in vals):
                    continue
                quats.append(rotation_from_ypr_deg(*(float(v) for v in vals)).as_quat())
            stamp = row.get("stamp_ns") or ""  # None: the row is cut short before it
            if not stamp.strip():
                raise ValueError("no stamp_ns")
            stamps.append(int(stamp))
    except ValueError as err:
        # reader.line_num: the file's line the bad row ends on (header = line 1).
        detail = str(err).replace("could not convert string to float: ", "not a number: ")
        raise BagError(f"{path} line {reader.line_num}: malformed row ({detail})") from err
    return _series(stamps, quats, str(path))


def read_series_bag(path: str | Path, topic: str) -> PoseSeries:
    """Head orientations from one topic of a bag (stamps from the message headers).

    Raises:
        BagError: unreadable bag, missing topic or an unsupported message type.
    """
    from ficap_ros.io.messages import orientation
    from ficap_ros.io.sources import open_bag_reader
    from ficap_ros.stamps import stamp_to_ns

    reader = open_bag_reader(Path(path))
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            topics = sorted({c.topic for c in reader.connections if c.msgtype in POSE_TYPES})
            raise BagError(f"bag {path} has no topic {topic} (pose topics: "
                           f"{', '.join(topics) or 'none'})")
        if conns[0].msgtype not in POSE_TYPES:
            raise BagError(f"topic {topic} is {conns[0].msgtype}, not one of "
                           f"{', '.join(t.split('/')[-1] for t in POSE_TYPES)}")
        stamps: list[int] = []
        quats: list[Any] = []
        for conn, log_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            o = orientation(msg)
            stamps.append(stamp_to_ns(msg.header.stamp) or int(log_ns))
            quats.append((o.x, o.y, o.z, o.w))
    except BagError:
        raise
    except Exception as err:  # noqa: BLE001 - rosbags raises many types for a corrupt bag
        raise BagError(f"cannot read {topic} from {path}: {err}") from err
    finally:
        reader.close()
    return _series(stamps, quats, f"{path}:{topic}")


def load_series(spec: str) -> PoseSeries:
    """``BAG:TOPIC`` (rosbag2 folder or .mcap/.db3 file and a topic), or a CSV / labels folder."""
    path, sep, topic = spec.rpartition(":")  # topics hold no ':', paths might
    if sep and topic.startswith("/") and Path(path).exists():
        return read_series_bag(path, topic)
    if not Path(spec).exists():
        raise BagError(f"{spec} does not exist (expected BAG:TOPIC or a CSV file)")
    p = Path(spec)
    if p.is_dir() and not (p / "labels.csv").exists():
        # A folder here is most likely a replay output whose labels.csv is gone or not written yet.
        raise BagError(f"{spec} is a folder without labels.csv; give a replay output folder "
                       f"(holding labels.csv), a CSV file, or BAG:TOPIC")
    return read_series_csv(spec)


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


@dataclass(frozen=True)
class EvaluationResult:
    """Paired errors and their statistics.

    Attributes:
        stamp_ns: (M,) truth stamps of the pairs.
        truth_ypr_deg, estimate_ypr_deg: (M, 3) yaw, pitch, roll.
        geodesic_deg, phi3_deg: (M,) errors.
        axis_error_deg: (M, 3) estimate - truth yaw, pitch, roll, wrapped.
        n_truth, n_estimate: series lengths.
        max_dt_ms: pairing tolerance.
        truth_source, estimate_source: where they came from.
    """

    stamp_ns: np.ndarray
    truth_ypr_deg: np.ndarray
    estimate_ypr_deg: np.ndarray
    geodesic_deg: np.ndarray
    phi3_deg: np.ndarray
    axis_error_deg: np.ndarray
    n_truth: int
    n_estimate: int
    max_dt_ms: float
    truth_source: str = ""
    estimate_source: str = ""

    @property
    def n_paired(self) -> int:
        return int(self.stamp_ns.size)

    def summary(self) -> dict[str, Any]:
        """Statistics as a JSON-ready dict (degrees)."""
        axes: dict[str, Any] = {}
        for k, name in enumerate(("yaw", "pitch", "roll")):
            e = self.axis_error_deg[:, k] if self.n_paired else np.zeros(0)
            a = np.abs(e)
            axes[name] = {
                "mean": float(np.mean(e)) if e.size else math.nan,
                "std": float(np.std(e)) if e.size else math.nan,
                "mean_abs": float(np.mean(a)) if e.size else math.nan,
                "median_abs": float(np.median(a)) if e.size else math.nan,
                "p95_abs": float(np.percentile(a, 95)) if e.size else math.nan,
                "rmse": float(np.sqrt(np.mean(e**2))) if e.size else math.nan,
            }
        return {
            "truth": self.truth_source,
            "estimate": self.estimate_source,
            "n_truth": self.n_truth,
            "n_estimate": self.n_estimate,
            "n_paired": self.n_paired,
            "pct_truth_paired": round(100.0 * self.n_paired / self.n_truth, 3) if self.n_truth else 0.0,
            "max_dt_ms": self.max_dt_ms,
            "geodesic_deg": summarize_errors(self.geodesic_deg),
            "phi3_deg": summarize_errors(self.phi3_deg),
            "axis_error_deg": axes,
        }


def evaluate(truth: PoseSeries, estimate: PoseSeries, max_dt_ms: float = 20.0) -> EvaluationResult:
    """Pair ``estimate`` with ``truth`` by stamp and compute the errors.

    Raises:
        BagError: no pair within ``max_dt_ms``.
    """
    i_t, i_e = pair_by_stamp(truth.stamp_ns, estimate.stamp_ns, int(round(max_dt_ms * 1e6)))
    if i_t.size == 0:
        raise BagError(
            f"no estimate within {max_dt_ms:g} ms of a truth stamp ({len(truth)} truth, "
            f"{len(estimate)} estimates); check the stamps or raise --max-dt-ms"
        )
    rt = truth.rotations[i_t]
    re = estimate.rotations[i_e]
    ypr_t = np.atleast_2d(yaw_pitch_roll_deg(rt))
    ypr_e = np.atleast_2d(yaw_pitch_roll_deg(re))
    return EvaluationResult(
        stamp_ns=truth.stamp_ns[i_t],
        truth_ypr_deg=ypr_t,
        estimate_ypr_deg=ypr_e,
        geodesic_deg=np.atleast_1d(angle_deg(rt, re)),
        phi3_deg=np.atleast_1d(phi3_deg(rt, re)),
        axis_error_deg=_wrap_deg(ypr_e - ypr_t),
        n_truth=len(truth),
        n_estimate=len(estimate),
        max_dt_ms=float(max_dt_ms),
        truth_source=truth.source,
        estimate_source=estimate.source,
    )


# -- report --------------------------------------------------------------------------------------
def _write(path: Path, data: str | bytes) -> Path:
    """One file of a checked output folder (an ``OutputFolder``'s temporary), atomically."""
    from ficap_ros.errors import OutputError
    from ficap_ros.files import write_atomic

    try:
        write_atomic(path, data)
    except OSError as err:
        raise OutputError(f"cannot write {path.name}: {err.strerror or err}") from err
    return path


def _png(fig: Any, path: Path) -> Path:
    """Lay out, write atomically as PNG, close; returns ``path``."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return _write(path, buf.getvalue())


def plot_report(result: EvaluationResult, out_dir: Path) -> list[Path]:
    """error_histogram.png (the paper's Fig. 3), timeseries.png, error_vs_yaw.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    top = max(float(np.percentile(result.geodesic_deg, 99.5)) * 1.1, 1.0)
    bins = np.linspace(0.0, top, 41)
    ax.hist(np.clip(result.geodesic_deg, 0, top), bins=bins, color="tab:blue", alpha=0.75,
            label="geodesic angle")
    ax.hist(np.clip(result.phi3_deg, 0, top), bins=bins, color="tab:orange", alpha=0.6,
            label="Φ3 = arccos|q1·q2|")
    ax.set_xlabel("Error degrees (°)")
    ax.set_ylabel("Frequency")
    ax.set_title(f"Head pose error ({result.geodesic_deg.size} paired frames)")
    ax.legend()
    paths.append(_png(fig, out_dir / "error_histogram.png"))

    t_s = (result.stamp_ns - result.stamp_ns[0]) / 1e9
    fig, axes = plt.subplots(3, 1, figsize=(8.0, 6.4), sharex=True)
    sign = ("+ left", "+ nose down", "+ right ear down")  # REP-103 right-hand signs
    for k, name in enumerate(("yaw", "pitch", "roll")):
        axes[k].plot(t_s, result.truth_ypr_deg[:, k], "-", color="k", lw=1.0, label="truth")
        axes[k].plot(t_s, result.estimate_ypr_deg[:, k], "-", color="tab:red", lw=0.8,
                     label="estimate")
        axes[k].set_ylabel(f"{name} (°, {sign[k]})")
    axes[0].legend(loc="upper right")
    axes[0].set_title(f"Head yaw, pitch, roll in the frontal frame, REP-103 "
                      f"({t_s.size} paired frames)")
    axes[-1].set_xlabel("time (s)")
    paths.append(_png(fig, out_dir / "timeseries.png"))

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    yaw = result.truth_ypr_deg[:, 0]
    ax.plot(yaw, result.geodesic_deg, ".", ms=2, alpha=0.5, color="tab:blue")
    edges = np.linspace(yaw.min(), yaw.max() + 1e-9, 16)
    idx = np.digitize(yaw, edges) - 1
    centres, medians = [], []
    for b in range(edges.size - 1):
        sel = result.geodesic_deg[idx == b]
        if sel.size:
            centres.append(0.5 * (edges[b] + edges[b + 1]))
            medians.append(float(np.median(sel)))
    ax.plot(centres, medians, "-o", color="k", ms=3, label="median per bin")
    ax.set_xlabel("truth yaw (°, + left)")
    ax.set_ylabel("geodesic error (°)")
    ax.set_title(f"Head pose error against yaw ({yaw.size} paired frames)")
    ax.legend()
    paths.append(_png(fig, out_dir / "error_vs_yaw.png"))
    return paths


def report_markdown(result: EvaluationResult) -> str:
    """report.md: the tables."""
    s = result.summary()

    def row(name: str, d: dict[str, float]) -> str:
        return f"| {name} | {d['mean']:.3f} | {d['median']:.3f} | {d['p95']:.3f} | {d['max']:.3f} |"

    lines = [
        "# Head-pose evaluation",
        "",
        f"- truth: `{s['truth']}` ({s['n_truth']} poses)",
        f"- estimate: `{s['estimate']}` ({s['n_estimate']} poses)",
        f"- paired within {s['max_dt_ms']:g} ms: {s['n_paired']} "
        f"({s['pct_truth_paired']:.1f} % of the truth)",
        "",
        "| error (°) | mean | median | p95 | max |",
        "|---|---|---|---|---|",
        row("geodesic angle", s["geodesic_deg"]),
        row("Φ3 = arccos(abs(q1·q2)) (paper)", s["phi3_deg"]),
        "",
        "Per axis, estimate − truth (°):",
        "",
        "| axis | mean (bias) | std | mean abs | median abs | p95 abs | RMSE |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, d in s["axis_error_deg"].items():
        lines.append(f"| {name} | {d['mean']:+.3f} | {d['std']:.3f} | {d['mean_abs']:.3f} | "
                     f"{d['median_abs']:.3f} | {d['p95_abs']:.3f} | {d['rmse']:.3f} |")
    lines += [
        "",
        "Plots: `error_histogram.png` (the paper's Fig. 3), `timeseries.png` (yaw, pitch, roll of "
        "both), `error_vs_yaw.png`.",
        "",
    ]
    return "\n".join(lines)


def write_report(result: EvaluationResult, out_dir: str | Path, plots: bool = True) -> list[Path]:
    """Write report.md, report.json and the PNG plots into ``out_dir``, each atomically.

    Args:
        out_dir: a folder checked under the output rule: an ``OutputFolder``'s temporary
            (``ficap evaluate`` swaps it in when the report is complete); created if missing.

    Raises:
        OutputError: a file cannot be written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = plot_report(result, out) if plots else []
    _write(out / "report.json", json.dumps(_finite(result.summary()), indent=2) + "\n")
    _write(out / "report.md", report_markdown(result))
    return [out / "report.md", out / "report.json", *paths]


def _finite(obj: Any) -> Any:
    """NaN -> None, so report.json is strict JSON."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


# -- detection statistics (the paper's section 6) -----------------------------------------------
@dataclass(frozen=True)
class DetectionStats:
    """How often the cap was seen.

    Attributes:
        frames: images counted (undecodable ones excluded).
        frames_skipped: undecodable images.
        frames_no_tag, frames_ge1_tag, frames_ge4_tags: by number of model tags detected.
        frames_with_pose: images with a cap pose.
        tag_rate: tag id -> share of the frames in which it was detected.
        reliability_edges: histogram bin edges (0..1); reliability_counts: frames per bin.
    """

    frames: int
    frames_skipped: int
    frames_no_tag: int
    frames_ge1_tag: int
    frames_ge4_tags: int
    frames_with_pose: int
    tag_rate: dict[int, float]
    reliability_edges: np.ndarray
    reliability_counts: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        n = max(self.frames, 1)
        return {
            "frames": self.frames,
            "frames_skipped": self.frames_skipped,
            "frames_no_tag": self.frames_no_tag,
            "frames_ge1_tag": self.frames_ge1_tag,
            "frames_ge4_tags": self.frames_ge4_tags,
            "frames_with_pose": self.frames_with_pose,
            "pct_no_tag": round(100.0 * self.frames_no_tag / n, 3),
            "pct_ge1_tag": round(100.0 * self.frames_ge1_tag / n, 3),
            "pct_ge4_tags": round(100.0 * self.frames_ge4_tags / n, 3),
            "pct_with_pose": round(100.0 * self.frames_with_pose / n, 3),
            "tag_detection_rate": {str(k): round(v, 5) for k, v in self.tag_rate.items()},
            "reliability_histogram": {
                "edges": [round(float(e), 3) for e in self.reliability_edges],
                "counts": [int(c) for c in self.reliability_counts],
            },
        }


#: Reliability histogram edges: 0.1 wide up to 0.8, 0.02 wide above, where good frames differ.
RELIABILITY_EDGES = np.concatenate([np.linspace(0.0, 0.8, 9), np.linspace(0.82, 1.0, 10)])


def detection_stats(
    tags_detected: np.ndarray, detected_ids: tuple[tuple[int, ...], ...], reliability: np.ndarray,
    has_pose: np.ndarray, skipped: np.ndarray, model_ids: tuple[int, ...],
    edges: np.ndarray | None = None,
) -> DetectionStats:
    """Counts of frames by tags detected, per-tag detection rate and the reliability histogram.

    Args:
        tags_detected: (N,) model tags detected per frame.
        detected_ids: per frame, the detected ids.
        reliability: (N,) pose reliability (NaN without a pose).
        has_pose: (N,) bool.
        skipped: (N,) bool, undecodable frames (left out of every count but their own).
        model_ids: the cap's tag ids (rows of the per-tag table).
        edges: reliability histogram bin edges over [0, 1] (default ``RELIABILITY_EDGES``; the
            last bin includes 1.0).
    """
    keep = ~np.asarray(skipped, dtype=bool)
    td = np.asarray(tags_detected)[keep]
    n = int(td.size)
    counts = {int(t): 0 for t in model_ids}
    for ids, k in zip(detected_ids, keep):
        if k:
            for t in set(ids):
                if t in counts:
                    counts[t] += 1
    rel = np.asarray(reliability, dtype=np.float64)[keep & np.asarray(has_pose, dtype=bool)]
    rel = rel[np.isfinite(rel)]
    edges = RELIABILITY_EDGES if edges is None else np.asarray(edges, dtype=np.float64)
    hist, _ = np.histogram(np.clip(rel, 0.0, 1.0), bins=edges)
    return DetectionStats(
        frames=n,
        frames_skipped=int(np.count_nonzero(~keep)),
        frames_no_tag=int(np.count_nonzero(td == 0)),
        frames_ge1_tag=int(np.count_nonzero(td >= 1)),
        frames_ge4_tags=int(np.count_nonzero(td >= 4)),
        frames_with_pose=int(np.count_nonzero(np.asarray(has_pose, dtype=bool)[keep])),
        tag_rate={t: (c / n if n else 0.0) for t, c in counts.items()},
        reliability_edges=edges,
        reliability_counts=hist,
    )


def plot_stats(stats: DetectionStats, out_dir: Path) -> list[Path]:
    """reliability_histogram.png and tag_detection_rate.png, into a checked output folder (an
    ``OutputFolder``'s temporary)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    e = stats.reliability_edges
    # Counts per unit of reliability (frames / bin width): bins of different widths compare.
    density = stats.reliability_counts / np.diff(e)
    ax.bar(e[:-1], density, width=np.diff(e), align="edge",
           color="tab:green", edgecolor="white", linewidth=0.5)
    # A density's axis reads 1500 for 30 frames in one 0.02 bin: each bar says its frame count.
    for left, width, height, count in zip(e[:-1], np.diff(e), density, stats.reliability_counts):
        if count:
            ax.annotate(f"{int(count)}", (left + width / 2, height), xytext=(0, 2),
                        textcoords="offset points", ha="center", va="bottom", fontsize=7)
    ax.set_xlabel("pose reliability (bins 0.1 wide below 0.8, 0.02 above)")
    ax.set_ylabel("frames per 1.0 of reliability (bar labels: frames)")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.12 * max(float(density.max(initial=0.0)), 1.0))
    ax.set_title(f"Reliability ({stats.frames_with_pose} frames with a pose of {stats.frames})")
    paths.append(_png(fig, out_dir / "reliability_histogram.png"))

    fig, ax = plt.subplots(figsize=(8.0, 4.0))
    ids = list(stats.tag_rate)
    ax.bar([str(i) for i in ids], [100.0 * stats.tag_rate[i] for i in ids], color="tab:blue")
    ax.set_xlabel("tag id")
    ax.set_ylabel("detected in % of frames")
    ax.set_ylim(0, 100)
    ax.set_title(f"Tag detection rate ({stats.frames} frames)")
    paths.append(_png(fig, out_dir / "tag_detection_rate.png"))
    return paths

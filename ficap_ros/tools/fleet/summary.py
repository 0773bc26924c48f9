"""A fleet's results: one line per recording (``RecordingResult``, made from the recording's
summary.json) and the fleet summary at the top of ``--out`` (CSV, JSON, PNG).
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

from ficap_ros import __version__
from ficap_ros.files import write_output_file
from ficap_ros.tools.fleet.manifest import Recording

__all__ = ["FLEET_FILES", "RecordingResult", "FleetResult", "recording_result",
           "write_fleet_summary"]

#: The fleet summary, at the top of --out.
FLEET_FILES = ("fleet_summary.csv", "fleet_summary.json", "fleet_summary.png")


@dataclass(frozen=True)
class RecordingResult:
    """One recording's line in the fleet summary.

    Attributes:
        recording, rel: input and output folder (relative to --out).
        status: ``done``, ``skipped`` (outputs current), ``damaged`` (labelled what could be
            read; frames were lost) or ``failed`` (no labels; ``error`` says why).
        frames: images labelled; frames_with_pose, pct_with_pose: coverage; pct_ge4_tags: share
            of decoded frames with at least 4 tags; reliability_mean/median: over frames with a
            pose; frames_lost: frames that gave no label input (undecodable images plus what a
            damaged container lost), None when the container cannot say how many it lost;
            wall_s: this run's time on it (0 when skipped).
    """

    recording: str
    rel: str
    status: str
    frames: int = 0
    frames_with_pose: int = 0
    pct_with_pose: float = 0.0
    pct_ge4_tags: float = 0.0
    reliability_mean: float = math.nan
    reliability_median: float = math.nan
    frames_lost: int | None = 0
    wall_s: float = 0.0
    error: str = ""


@dataclass
class FleetResult:
    """What a fleet run did: a result per recording (in the order given), its wall time, and the
    engine (``processes`` or ``ray ...``) with its workers."""

    results: list[RecordingResult] = field(default_factory=list)
    wall_s: float = 0.0
    engine: str = "processes"
    workers: int = 1

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)


def _lost(summary: dict[str, Any]) -> int | None:
    """Frames a recording lost: undecodable images, plus what a damaged container cut off (None
    when it is damaged and cannot say how many)."""
    lost = int(summary.get("frames_skipped", 0) or 0)
    if summary.get("damaged") and "frames_lost" in summary and summary["frames_lost"] is None:
        return None
    for key in ("frames_lost", "messages_lost"):
        value = summary.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return lost + int(value)
        if isinstance(value, dict) and isinstance(value.get("count"), (int, float)):
            return lost + int(value["count"])
    recovery = summary.get("recovery") or summary.get("damage")
    if isinstance(recovery, dict):
        for key in ("frames_lost", "messages_lost", "lost", "count"):
            if isinstance(recovery.get(key), (int, float)):
                return lost + int(recovery[key])
    return lost


def _damaged(summary: dict[str, Any]) -> bool:
    lost = _lost(summary)
    return lost is None or lost > int(summary.get("frames_skipped", 0) or 0) or bool(
        summary.get("truncated") or summary.get("damaged"))


def recording_result(rec: Recording, status: str, summary: dict[str, Any],
                     reliability: Sequence[float], wall_s: float) -> RecordingResult:
    """A recording's line from its summary.json and the reliabilities of its frames with a pose
    (``done`` becomes ``damaged`` when frames were lost)."""
    import numpy as np

    rel = np.asarray([r for r in reliability if math.isfinite(r)], dtype=float)
    if status == "done" and _damaged(summary):
        status = "damaged"
    return RecordingResult(
        str(rec.path), str(rec.rel), status, int(summary.get("frames", 0)),
        int(summary.get("frames_with_pose", 0)), float(summary.get("pct_with_pose", 0.0)),
        float(summary.get("pct_ge4_tags", 0.0)),
        round(float(rel.mean()), 4) if rel.size else math.nan,
        round(float(np.median(rel)), 4) if rel.size else math.nan,
        _lost(summary), round(wall_s, 3))


_COLUMNS = ("recording", "rel", "status", "frames", "frames_with_pose", "pct_with_pose",
            "pct_ge4_tags", "reliability_mean", "reliability_median", "frames_lost", "wall_s",
            "error")


def write_fleet_summary(out: Path, fleet: FleetResult) -> list[Path]:
    """fleet_summary.csv (a row per recording), .json (the rows and totals) and .png."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(_COLUMNS)
    for r in fleet.results:
        row = asdict(r)
        writer.writerow(["" if row[c] is None or (isinstance(row[c], float) and math.isnan(row[c]))
                         else row[c] for c in _COLUMNS])
    totals = {
        "recordings": len(fleet.results),
        **{s: fleet.count(s) for s in ("done", "skipped", "damaged", "failed")},
        "frames": sum(r.frames for r in fleet.results),
        "frames_processed": sum(r.frames for r in fleet.results if r.status in ("done", "damaged")),
        "frames_with_pose": sum(r.frames_with_pose for r in fleet.results),
        "frames_lost": sum(r.frames_lost or 0 for r in fleet.results),
        "recordings_lost_unknown": sum(r.frames_lost is None for r in fleet.results),
        "wall_s": round(fleet.wall_s, 3),
        "engine": fleet.engine,
        "workers": fleet.workers,
        "ficap_version": __version__,
    }
    processed = totals["frames_processed"]
    totals["throughput_fps"] = round(processed / fleet.wall_s, 2) if fleet.wall_s > 0 else None
    doc = {"fleet": totals,
           "recordings": [{k: (None if isinstance(v, float) and math.isnan(v) else v)
                           for k, v in asdict(r).items()} for r in fleet.results]}
    paths = [out / name for name in FLEET_FILES]
    write_output_file(paths[0], buf.getvalue())
    write_output_file(paths[1], json.dumps(doc, indent=2) + "\n")
    write_output_file(paths[2], _plot(fleet))
    return paths


_STATUS_COLOURS = {"done": "#2b7bba", "skipped": "#8fb9dc", "damaged": "#e39b2d", "failed": "#c8312b"}


def _plot(fleet: FleetResult) -> bytes:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rs = fleet.results
    names = [r.rel if r.rel != "." else Path(r.recording).name for r in rs]
    colours = [_STATUS_COLOURS.get(r.status, "grey") for r in rs]
    panels = (("frames", "frames labelled", lambda r: r.frames),
              ("coverage %", "frames with a pose, %", lambda r: r.pct_with_pose),
              (">= 4 tags %", "decoded frames with >= 4 tags, %", lambda r: r.pct_ge4_tags),
              ("reliability", "mean reliability (frames with a pose)",
               lambda r: 0.0 if math.isnan(r.reliability_mean) else r.reliability_mean),
              ("frames lost", "undecodable or cut off (unknown: 0)", lambda r: r.frames_lost or 0),
              ("wall s", "this run's time, s (0: skipped)", lambda r: r.wall_s))
    height = max(3.0, 0.28 * len(rs) + 1.6)
    fig, axes = plt.subplots(1, len(panels), figsize=(3.0 * len(panels), height), sharey=True)
    ys = range(len(rs))
    for ax, (label, title, value) in zip(axes, panels):
        values = [value(r) for r in rs]
        ax.barh(list(ys), values, color=colours)
        ax.set_xlim(0, max(max(values, default=0) * 1.05, 1e-9) if any(values) else 1)
        ax.set_title(title, fontsize=8)
        ax.set_xlabel(label, fontsize=8)
        ax.tick_params(labelsize=7)
    for y, r in zip(ys, rs):  # a failed recording has no bars: say so where they would be
        if r.status == "failed":
            axes[0].text(0, y, " failed", va="center", fontsize=7, color=_STATUS_COLOURS["failed"])
    axes[0].invert_yaxis()
    axes[0].set_yticks(list(ys), names)
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in _STATUS_COLOURS.values()]
    fig.legend(handles, list(_STATUS_COLOURS), loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(f"ficap fleet: {len(rs)} recordings, {fleet.count('done')} done, "
                 f"{fleet.count('skipped')} skipped, {fleet.count('damaged')} damaged, "
                 f"{fleet.count('failed')} failed", fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 0.95))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()

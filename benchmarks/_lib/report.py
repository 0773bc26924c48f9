"""Each benchmark's section of docs/benchmarks.md, written from its results.

A script writes ``docs/benchmarks/<name>.md`` (and its PNGs beside it) whole, then
``regenerate_index`` rebuilds ``docs/benchmarks.md``: a short head, a table of contents and every
section that exists, in ``SECTIONS``' order. Nothing written by hand is patched: to change a
section's prose, change its script.
"""

from __future__ import annotations

import datetime as dt
import os
import platform
import re
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from _lib.cli import ROOT

DOCS = ROOT / "docs"
SECTION_DIR = DOCS / "benchmarks"
INDEX = DOCS / "benchmarks.md"

#: Section files in the index's order: name -> the heading's title.
SECTIONS: dict[str, str] = {
    "accuracy": "Accuracy on synth drives (the paper's Table 1)",
    "blender_pose": "Accuracy on blender_dev (independent path-traced renders)",
    "glance": "Fast glances: motion blur and rolling shutter",
    "corners": "Corners on blender_dev and synth",
    "uncertainty": "Calibrated uncertainty: coverage and sharpness of the 95 % bounds",
    "calibration": "Head calibration against a reference (the paper's Table 2)",
    "model_build": "As-built cap model",
    "visibility": "Visibility and camera placement (the paper's section 6)",
    "speed": "Speed: the whole `ficap replay` command against AprilTag 3",
    "search": "Searched frames and real photos",
    "fleet": "Fleet replay: processes and Ray",
    "node": "Node latency and rate",
    "soak": "Soak: the node for minutes with corrupt frames",
    "demo": "The demo (`make demo`)",
}

INDEX_HEAD = """# Benchmarks

Every section below is written by a script in `benchmarks/` from its own run (`make bench` runs them
all in turn; `make bench BENCH_ARGS=--quick` is the fast mode; each script's `--help` says what it
measures). A section states the machine, the commit and the load average during its run: the machine
has 2 cores shared with other jobs, so timings are CPU time (user + sys), medians of interleaved runs;
accuracy figures are exact functions of the seeds. Studies that answered one question and were then
retired keep their conclusions in `docs/studies.md`.
"""


def load_now() -> tuple[float, float]:
    try:
        one, five, _ = os.getloadavg()
        return one, five
    except OSError:
        return float("nan"), float("nan")


@dataclass
class Run:
    """The provenance of one benchmark run: machine, commit, start, load at start and end."""

    started: float = field(default_factory=time.time)
    load_start: tuple[float, float] = field(default_factory=load_now)

    def machine(self) -> str:
        import cv2
        import numpy as np

        cpu = platform.processor() or platform.machine()
        try:
            for line in Path("/proc/cpuinfo").read_text().splitlines():
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
        except OSError:
            pass
        commit = _git("rev-parse", "--short", "HEAD") or "unknown"
        if _git("status", "--porcelain", "--", "ficap_ros", "benchmarks"):
            commit += "+uncommitted"
        when = dt.datetime.fromtimestamp(self.started).strftime("%Y-%m-%d %H:%M")
        return (f"{when}, {cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
                f"numpy {np.__version__}, OpenCV {cv2.__version__}, commit {commit}")

    def load(self) -> str:
        end = load_now()
        return (f"load average {self.load_start[0]:.1f} at the start, {end[0]:.1f} at the end "
                f"(1 min; 5 min {self.load_start[1]:.1f} / {end[1]:.1f}) on {os.cpu_count()} cores")

    def provenance(self, command: str, quick: bool) -> str:
        minutes = (time.time() - self.started) / 60.0
        mode = " (`--quick`: a fast run, smaller than the full one)" if quick else ""
        return (f"Run: `{command}`{mode}, {minutes:.1f} min. Machine: {self.machine()}; "
                f"{self.load()}.")


def _git(*args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                              check=False).stdout.strip()
    except OSError:
        return ""


def md_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def png_path(name: str) -> Path:
    SECTION_DIR.mkdir(parents=True, exist_ok=True)
    return SECTION_DIR / f"{name}.png"


def save_figure(fig, name: str) -> str:  # noqa: ANN001 - a matplotlib Figure
    """Save ``fig`` as docs/benchmarks/<name>.png; the Markdown image line for a section file."""
    import matplotlib.pyplot as plt

    fig.savefig(png_path(name), dpi=80)
    plt.close(fig)
    return f"![{name}](./{name}.png)"


def pyplot():  # noqa: ANN201 - matplotlib.pyplot without a display
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_section(name: str, what: str, how: str, body: str, run: Run, command: str,
                  quick: bool, no_doc: bool = False) -> None:
    """Print the section and, unless ``no_doc``, write docs/benchmarks/<name>.md and the index.

    ``what``: what it measures; ``how``: how to run it; ``body``: tables, plots and the reading."""
    text = (f"## {SECTIONS[name]}\n\n{what.strip()}\n\n{how.strip()}\n\n"
            f"{run.provenance(command, quick)}\n\n{body.strip()}\n")
    print(text)
    if no_doc:
        return
    SECTION_DIR.mkdir(parents=True, exist_ok=True)
    tmp = SECTION_DIR / f"{name}.md.tmp"
    tmp.write_text(text)
    tmp.replace(SECTION_DIR / f"{name}.md")
    regenerate_index()


def regenerate_index() -> None:
    """docs/benchmarks.md: the head, a contents list and the sections, in ``SECTIONS``' order."""
    parts, contents = [], []
    for name, title in SECTIONS.items():
        path = SECTION_DIR / f"{name}.md"
        if not path.is_file():
            continue
        text = path.read_text()
        # Images sit beside the section files: from docs/ they are under benchmarks/.
        parts.append(re.sub(r"\]\(\./", "](benchmarks/", text).strip())
        anchor = re.sub(r"[^a-z0-9 _-]", "", title.lower()).replace(" ", "-")
        contents.append(f"- [{title}](#{anchor}) (`benchmarks/bench_{name}.py`)")
    text = INDEX_HEAD + "\n" + "\n".join(contents) + "\n\n" + "\n\n".join(parts) + "\n"
    tmp = INDEX.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(INDEX)


def command(extra_hidden: Sequence[str] = ("--no-doc",)) -> str:
    """This script's command line as a user types it from the repository."""
    import sys

    args = [a for a in sys.argv[1:] if a not in extra_hidden]
    return " ".join([f"benchmarks/{Path(sys.argv[0]).name}", *args])


def how(script: str, quick: str, extra: str = "") -> str:
    """The 'how to run it' paragraph of a section."""
    return (f"How to run: `.venv/bin/python benchmarks/{script}` (`make bench` runs it with the "
            f"others; `--quick`: {quick}; `--help` lists the options).{' ' + extra if extra else ''}")

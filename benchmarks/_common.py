"""Shared helpers of the benchmark scripts: machine line, timing, recording into docs/benchmarks.md."""

from __future__ import annotations

import datetime as dt
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
DOC_HEAD = (
    "# Benchmarks\n\n"
    "Every table below comes from a run of a script in `benchmarks/` (`make bench` runs them all with\n"
    "modest sizes; each script takes `--frames` etc. for full-size runs). Each section says the machine,\n"
    "date, commit and the load average while it ran: the benchmark machine has 2 cores shared with other\n"
    "jobs, so timings are noisy; accuracy numbers are exact functions of the seeds.\n"
)


def load_avg() -> str:
    try:
        one, five, _ = os.getloadavg()
        return f"load average {one:.1f} (1 min) / {five:.1f} (5 min) on {os.cpu_count()} cores"
    except OSError:
        return "load average unknown"


def machine_line() -> str:
    """Date, CPU, cores, Python, OpenCV, commit (with a ``+dirty`` mark)."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip() or "unknown"
    # The package is installed editable: uncommitted changes to it are what the benchmark measured.
    dirty = subprocess.run(["git", "status", "--porcelain", "--", "ficap_ros", "benchmarks"], cwd=ROOT,
                           capture_output=True, text=True).stdout.strip()
    if dirty:
        commit += "+dirty"
    return (f"{dt.datetime.now().strftime('%Y-%m-%d %H:%M')}, {cpu}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}, OpenCV {cv2.__version__}, commit {commit}")


def _subsections(section: str) -> list[tuple[str, str]]:
    """(heading line, whole text) of each ``### `` subsection of a ``## `` section, in order."""
    parts = re.split(r"(?m)^(?=### )", section)
    return [(p.split("\n", 1)[0], p) for p in parts[1:]]


def record_section(name: str, body: str, path: Path = DOC) -> None:
    """Write ``## name`` + body into docs/benchmarks.md, replacing a section of the same name.

    ``### `` subsections of the old section that the new body does not write itself (by heading)
    are kept, after it, in their order: notes written by hand under a recorded table (where the
    time goes, what was tried) survive re-recording. Text by hand outside a ``###`` subsection is
    replaced with the rest of the section."""
    text = path.read_text() if path.exists() else DOC_HEAD
    section = f"## {name}\n\n{body.rstrip()}\n\n"
    pattern = re.compile(rf"^## {re.escape(name)}\n.*?(?=^## |\Z)", re.S | re.M)
    match = pattern.search(text)
    if match:
        written = {h for h, _ in _subsections(section)}
        kept = [t.rstrip() + "\n\n" for h, t in _subsections(match.group(0)) if h not in written]
        section += "".join(kept)
        text = text[:match.start()] + section + text[match.end():]
    else:
        text = text.rstrip() + "\n\n" + section
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text.rstrip() + "\n")
    tmp.replace(path)


def md_table(header: list[str], rows: list[list[object]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def Progress(total: int, label: str):  # noqa: ANN201, N802 - a tqdm bar
    """Progress on stderr (tqdm: rate and ETA; silent when stderr is not a terminal)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=f"  {label}", unit="frame", file=sys.stderr, disable=None,
                smoothing=0.1)


def patch_own_time(stages, own: dict[str, float]):  # noqa: ANN001, ANN202
    """Wrap each stage's function (``stages``: (module, "attr" or "Class.attr", label) rows) so
    ``own[label]`` collects its CPU time (``time.process_time``) without the time of the wrapped
    stages it calls; generator functions are timed per item. Returns the undo list: (owner, name,
    original) to ``setattr`` back in reverse order. The wrappers cost ~1 us a call."""
    import functools
    import importlib
    import inspect

    stack: list[list[float]] = []

    def enter() -> float:
        stack.append([0.0])
        return time.process_time()

    def leave(t0: float, label: str) -> None:
        dt = time.process_time() - t0
        inner = stack.pop()[0]
        own[label] = own.get(label, 0.0) + dt - inner
        if stack:
            stack[-1][0] += dt

    def wrap(fn, label):  # noqa: ANN001, ANN202
        if inspect.isgeneratorfunction(fn):
            @functools.wraps(fn)
            def timed_gen(*a, **k):  # noqa: ANN002, ANN003, ANN202
                gen = fn(*a, **k)
                while True:
                    t0 = enter()
                    try:
                        item = next(gen)
                    except StopIteration:
                        return
                    finally:
                        leave(t0, label)
                    yield item
            return timed_gen

        @functools.wraps(fn)
        def timed(*a, **k):  # noqa: ANN002, ANN003, ANN202
            t0 = enter()
            try:
                return fn(*a, **k)
            finally:
                leave(t0, label)
        return timed

    patched = []
    for mod_name, attr, label in stages:
        owner = importlib.import_module(mod_name)
        *path, name = attr.split(".")
        for part in path:
            owner = getattr(owner, part, None)
        fn = owner.__dict__.get(name) if owner is not None else None
        if fn is None or not callable(fn):
            continue
        patched.append((owner, name, fn))
        setattr(owner, name, wrap(fn, label))
    return patched

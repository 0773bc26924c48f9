"""Which recordings a fleet holds and where each one's outputs go: inputs given on the command
line (recordings, or folder trees searched for them) and manifests.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

from ficap_ros.errors import BagError
from ficap_ros.files import BAG_SUFFIXES, VIDEO_SUFFIXES, read_text

__all__ = ["BAG_SUFFIXES", "Recording", "is_recording", "read_manifest", "find_recordings",
           "MAX_MANIFEST_BYTES"]

#: Largest manifest read: some hundred thousand recordings.
MAX_MANIFEST_BYTES = 16 << 20


@dataclass(frozen=True)
class Recording:
    """One recording of the fleet.

    Attributes:
        path: the input (rosbag2 folder, .mcap/.db3 file, or video).
        rel: its output folder under ``--out`` (``.``: ``--out`` itself, for a single input).
    """

    path: Path
    rel: Path


def _is_bag_folder(path: Path) -> bool:
    return path.is_dir() and (path / "metadata.yaml").is_file()


def _is_replay_output(path: Path) -> bool:
    """A folder ficap replay wrote (it is a rosbag2 too, of labels only)."""
    return (path / "labels.csv").is_file() and (path / "summary.json").is_file()


def is_recording(path: Path, videos: bool = False) -> bool:
    """A rosbag2 folder, a bag file, or (with ``videos``) a video file."""
    if path.is_dir():
        return _is_bag_folder(path) and not _is_replay_output(path)
    suffix = path.suffix.lower()
    return path.is_file() and (suffix in BAG_SUFFIXES or (videos and suffix in VIDEO_SUFFIXES))


def _stem(path: Path) -> str:
    return path.name if path.is_dir() else path.stem


def _search_tree(root: Path, videos: bool, exclude: Path | None) -> Iterator[Path]:
    """Recordings under ``root``, in sorted order; a bag folder is not searched inside."""
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        if exclude is not None and _inside(here, exclude):
            dirnames[:] = []
            continue
        if here != root and _is_bag_folder(here):
            dirnames[:] = []
            if not _is_replay_output(here):
                yield here
            continue
        dirnames.sort()
        for name in sorted(filenames):
            p = here / name
            if is_recording(p, videos):
                yield p


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def read_manifest(path: str | Path) -> list[tuple[Path, Path | None]]:
    """A manifest: one input per line (``#`` starts a comment), relative to the manifest's folder.

    Returns (input path, output folder or None) per entry: a relative entry's output mirrors its
    path (``drivers/d01/drive.mcap`` -> ``drivers/d01/drive``); an absolute one, or one that
    leaves the manifest's folder (``../other/drive.mcap``), uses its name, so no output lands
    outside ``--out``.

    Raises:
        BagError: the manifest is not a readable text file (``files.read_text``).
    """
    p = Path(path)
    text = read_text(p, "manifest", BagError, MAX_MANIFEST_BYTES)
    entries: list[tuple[Path, Path | None]] = []
    for line in text.splitlines():
        entry = line.split("#", 1)[0].strip()
        if not entry:
            continue
        e = Path(entry)
        if e.is_absolute():
            entries.append((e, None))
        elif ".." in e.parts:
            entries.append((p.parent / e, None))
        else:
            entries.append((p.parent / e, e.parent / _stem(p.parent / e)))
    return entries


def find_recordings(
    inputs: Sequence[str | Path], manifest: str | Path | None = None, out: str | Path | None = None,
    videos: bool = False,
) -> list[Recording]:
    """Every recording named by ``inputs`` and ``manifest``, with its output folder.

    A recording given alone (one input, no manifest) writes into ``--out`` itself, as a single
    replay does. Otherwise: a folder tree given as the only input mirrors into ``--out``
    (``ROOT/a/b/drive`` -> ``OUT/a/b/drive``); with several inputs each goes under its own name
    (``OUT/NAME/...``); a manifest's relative entries mirror their paths. ``out`` is never
    searched, so outputs inside the input tree are not taken for recordings.

    Raises:
        BagError: a missing input, an input that is no recording and holds none, no recording at
            all, or two recordings that would write to one folder.
    """
    out_path = Path(out) if out is not None else None
    entries: list[tuple[Path, Path | None]] = [(Path(i), None) for i in inputs]
    if manifest is not None:
        entries += read_manifest(manifest)
    single = len(entries) == 1
    found: list[Recording] = []
    for path, rel in entries:
        if not path.exists():
            raise BagError(f"{path} does not exist")
        if is_recording(path, videos=True):
            if out_path is not None and _inside(out_path, path):
                raise BagError(f"output folder {out_path} is inside the input {path}")
            found.append(Recording(path, Path(".") if single and rel is None else
                                   rel if rel is not None else Path(_stem(path))))
            continue
        if not path.is_dir():
            raise BagError(f"{path} is neither a recording (rosbag2 folder, .mcap, .db3, video) "
                           "nor a folder")
        base = rel if rel is not None else (Path(".") if single else Path(path.name))
        before = len(found)
        for rec in _search_tree(path, videos, out_path):
            sub = rec.relative_to(path)
            found.append(Recording(rec, base / sub.parent / _stem(rec)))
        if len(found) == before:
            raise BagError(f"no recording (rosbag2 folder, .mcap, .db3"
                           f"{', video' if videos else ''}) found under {path}")
    seen: dict[Path, Path] = {}
    for r in found:
        if r.rel.is_absolute() or ".." in r.rel.parts:  # never outside --out
            raise BagError(f"{r.path} would write outside the output folder ({r.rel})")
        if r.rel in seen:
            raise BagError(f"{seen[r.rel]} and {r.path} would both write to {r.rel}; "
                           "rename one or list them in a manifest with distinct paths")
        seen[r.rel] = r.path
    return found

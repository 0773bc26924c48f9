"""Files in and out: the one rule every reader and writer of ficap_ros follows.

Reading: user files (YAML, CSV) are opened read-only and decoded as UTF-8; anything that is not
text (a binary file, UTF-16, a bag given where a CSV was expected) is the caller's ``FicapError``
with one line, never a ``UnicodeDecodeError``.

Writing:
    * a single file goes through a temporary file in the same folder, then ``os.replace``: a crash,
      Ctrl-C or full disk never leaves half a file (``write_atomic``);
    * an output folder (``OutputFolder``) is built in a temporary folder beside the target and
      replaces it as a unit when complete: its files are all new or all old;
    * an output never is, contains or lies inside an input (``check_not_input``), and an existing
      folder is only replaced when ficap wrote it (``check_replaceable``): a rosbag2 recording is
      never overwritten.
Every failure is an ``OutputError`` whose message is one line.
"""

from __future__ import annotations

import fcntl
import glob
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Iterable

from ficap_ros.errors import FicapError, OutputError

__all__ = ["read_text", "write_atomic", "write_output_file", "check_file_target",
           "check_not_input", "check_replaceable", "check_output_folder", "OutputFolder",
           "FICAP_OUTPUT_FILES", "is_ficap_output", "prepare_output_folder",
           "remove_stale_temporaries"]

#: Files ficap writes into an output folder (replay, stats, evaluate, a fleet's summary): an
#: existing folder holding only these (and ficap's own hidden temporaries) may be replaced.
FICAP_OUTPUT_FILES = frozenset({
    "labels.mcap", "metadata.yaml", "labels.csv", "detections.csv", "summary.json", "stats.json",
    "reliability_histogram.png", "tag_detection_rate.png", "report.md", "report.json",
    "error_histogram.png", "timeseries.png", "error_vs_yaw.png",
    "fleet_summary.csv", "fleet_summary.json", "fleet_summary.png",
})
#: The kit's files, whose names carry the paper size and the sheet's page (``ficap_ros.tools.kit``).
_KIT_FILE = re.compile(r"ficap_tags_(a4|letter)(_p\d+\.svg|\.pdf)|ficap_assembly\.(png|pdf)"
                       r"|ficap_shell\.stl")


def is_ficap_output(name: str) -> bool:
    """``name`` is a file ficap writes into an output folder (or one of its hidden temporaries)."""
    return name in FICAP_OUTPUT_FILES or name.startswith(".ficap") or bool(_KIT_FILE.fullmatch(name))


def _reason(err: OSError) -> str:
    return err.strerror or str(err) or type(err).__name__


def read_text(path: str | os.PathLike[str], what: str, error: type[FicapError]) -> str:
    """The text of a user file, or ``error`` with one line (missing, unreadable, not UTF-8 text).

    Args:
        path: the file.
        what: what it should be, for the message ("calibration", "intrinsics" ...).
        error: the ``FicapError`` subclass to raise.
    """
    p = Path(path)
    try:
        if p.is_dir():
            raise error(f"{what} {p} is a folder, not a file")
        data = p.read_bytes()
    except OSError as err:
        raise error(f"cannot read {what} {p}: {_reason(err)}") from err
    if b"\x00" in data:
        raise error(f"{what} {p} is a binary file, not text")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise error(f"{what} {p} is not UTF-8 text (byte {err.start})") from err


def write_atomic(path: str | os.PathLike[str], text: str | bytes) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder, then rename.

    A crash or Ctrl-C never leaves a half-written file at ``path``.

    Raises:
        OSError: the folder is not writable, the disk is full (``write_output_file`` turns
            these into one-line ``OutputError``).
    """
    path = Path(path)
    data = text.encode() if isinstance(text, str) else text
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    try:
        # mkstemp creates the file 0600; give the result the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def check_file_target(path: str | os.PathLike[str], what: str = "output") -> Path:
    """Fail early (before any processing) when ``path`` cannot be written as a file."""
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{what} {p} is a folder; give a file name")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"cannot write {what} {p}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {what} {p}: folder {parent} is not writable")
    return p


def write_output_file(path: str | os.PathLike[str], data: str | bytes,
                      inputs: Iterable[str | os.PathLike[str]] = (), what: str = "output") -> None:
    """``write_atomic`` under the output rule: not a folder, not an input, one-line errors."""
    p = check_file_target(path, what)
    check_not_input(p, inputs)
    try:
        write_atomic(p, data)
    except OSError as err:
        raise OutputError(f"cannot write {what} {p}: {_reason(err)}") from err


def _resolved(path: str | os.PathLike[str]) -> Path:
    return Path(os.path.abspath(os.path.realpath(path)))


def check_not_input(out: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str]]) -> None:
    """Refuse an output that is an input, holds one, or lies inside one (a bag folder).

    Raises:
        OutputError: naming the input.
    """
    o = _resolved(out)
    for item in inputs:
        i = _resolved(item)
        if o == i or i.is_relative_to(o) or (i.is_dir() and o.is_relative_to(i)):
            raise OutputError(f"output {out} is, holds or lies inside the input {item}; "
                              "choose another output")


def check_replaceable(out: str | os.PathLike[str], subfolders: bool = False) -> None:
    """Refuse to replace (or add files to) an existing folder that ficap did not write.

    An existing ``out`` may be replaced when it is an empty folder or holds only files ficap
    writes (``is_ficap_output``), and when its ``metadata.yaml``, if any, describes a rosbag2
    whose only file is ficap's ``labels.mcap``. Anything else (a recording, a folder of the
    user's files) is refused.

    Args:
        out: the folder.
        subfolders: the folder may hold folders (a fleet's ``--out``: one per recording); then
            every file under it is checked the same way, at any depth.

    Raises:
        OutputError: ``out`` is a file, or a folder ficap did not write.
    """
    p = Path(out)
    if not p.exists():
        return
    if not p.is_dir():
        raise OutputError(f"output {p} exists and is not a folder")
    folders = [p]
    for folder in folders:
        if subfolders:  # breadth first; ficap's hidden temporaries are not looked into
            folders += sorted(c for c in folder.iterdir()
                              if c.is_dir() and not c.is_symlink() and not c.name.startswith(".ficap"))
        # ficap never writes a symlink: one (to a folder or a file) is the user's, and a fleet
        # writing through it would land outside --out.
        foreign = sorted(str(c.relative_to(p)) + ("/" if c.is_dir() else "") for c in folder.iterdir()
                         if c.is_symlink() or not (is_ficap_output(c.name) or (subfolders and c.is_dir())))
        if foreign:
            listed = ", ".join(foreign[:3]) + (" ..." if len(foreign) > 3 else "")
            raise OutputError(f"output folder {p} holds files ficap did not write ({listed}); "
                              "choose a new or empty folder")
        meta = folder / "metadata.yaml"
        if meta.exists():
            import yaml

            try:
                info = yaml.safe_load(read_text(meta, "metadata", OutputError))
                files = info["rosbag2_bagfile_information"]["relative_file_paths"]
            except (FicapError, yaml.YAMLError, KeyError, TypeError) as err:
                raise OutputError(f"output folder {folder} holds a metadata.yaml ficap did not "
                                  "write; choose a new or empty folder") from err
            if list(files) != ["labels.mcap"]:
                raise OutputError(f"output folder {folder} is a rosbag2 recording ficap did not "
                                  "write; choose a new or empty folder")


def prepare_output_folder(out: str | os.PathLike[str]) -> Path:
    """The folder ``stats --out``, ``evaluate --out`` and ``kit --out`` add their files to.

    It must be new, empty or one ficap wrote (``check_replaceable``: never a recording or a
    folder of the user's files); it is created, and each file is then written atomically into it.

    Raises:
        OutputError: with one line.
    """
    p = Path(out)
    check_replaceable(p)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot write output folder {p}: {_reason(err)}") from err
    if not os.access(p, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write output folder {p}: not writable")
    return p


def check_output_folder(out: str | os.PathLike[str],
                        inputs: Iterable[str | os.PathLike[str]] = ()) -> None:
    """``OutputFolder``'s checks without creating anything (fail before any processing)."""
    p = Path(out)
    check_not_input(p, inputs)
    check_replaceable(p)
    parent = p.parent if str(p.parent) else Path(".")
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent  # the first folder that exists is where it will be created
    if not parent.is_dir():
        raise OutputError(f"cannot write output folder {p}: {parent} is not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write output folder {p}: {parent} is not writable")


_LOCK = ".lock"


def remove_stale_temporaries(out: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporary folders of ``out`` left by runs that were killed outright (SIGKILL).

    Each run's ``.ficap-NAME.XXXX`` folder has a ``.ficap-NAME.XXXX.lock`` file beside it that the
    run holds an exclusive ``flock`` on while it lives; the kernel lets go of it when the process
    (and any worker forked with it) is gone, however it died. A lock this function can take, on a
    file still linked under its name, is therefore a dead run's: its folder goes, then the lock
    file. A live run's lock cannot be taken, and a folder without a lock file (an older ficap's, or
    one whose lock file is being created) is left alone, so another live run's temporary is never
    deleted. The previous outputs renamed aside during a commit (``.old-PID``) are not touched.

    Returns:
        The folders removed.
    """
    out = Path(out)
    parent = out.parent if str(out.parent) else Path(".")
    removed = []
    for lock in parent.glob(f"{glob.escape(f'.ficap-{out.name}.')}*{_LOCK}"):
        try:
            fd = os.open(lock, os.O_RDWR)
        except OSError:
            continue  # gone meanwhile (its run finished) or not ours to open
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                continue  # a live run holds it
            # The same file still under that name: not one unlinked by a run that finished and a
            # new file that happens to reuse the name.
            here, held = os.stat(lock), os.fstat(fd)
            if (here.st_dev, here.st_ino) != (held.st_dev, held.st_ino):
                continue
            folder = lock.with_name(lock.name[: -len(_LOCK)])
            shutil.rmtree(folder, ignore_errors=True)
            lock.unlink()
            removed.append(folder)
        except OSError:
            continue
        finally:
            os.close(fd)
    return removed


class OutputFolder:
    """An output folder built beside its target and swapped in as a unit.

    ``with OutputFolder(out, inputs) as tmp:`` write every file into ``tmp``; on a clean exit
    ``out`` is replaced by it (the old folder, if any, is renamed away first and removed after),
    on an exception (Ctrl-C included) ``tmp`` is removed and ``out`` is left as it was.

    The checks run in ``__init__`` so a command fails before hours of processing: ``out`` is not
    an input (``check_not_input``), is replaceable (``check_replaceable``), and its parent is
    writable (the temporary folder is created there at once).

    Raises:
        OutputError: any of the above, with one line.
    """

    def __init__(self, out: str | os.PathLike[str],
                 inputs: Iterable[str | os.PathLike[str]] = ()) -> None:
        self.out = Path(out)
        check_output_folder(self.out, inputs)
        parent = self.out.parent if str(self.out.parent) else Path(".")
        self._lock_fd: int | None = None
        try:
            parent.mkdir(parents=True, exist_ok=True)
            remove_stale_temporaries(self.out)
            # The lock file comes first and names the folder: a folder without a locked lock file
            # beside it is never taken for stale (it may be one being created right now).
            fd, lock = tempfile.mkstemp(prefix=f".ficap-{self.out.name}.", suffix=_LOCK,
                                        dir=parent)
            self._lock_fd, self._lock = fd, Path(lock)
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            self.tmp = Path(lock[: -len(_LOCK)])
            self.tmp.mkdir()
        except OSError as err:
            self._release()
            raise OutputError(f"cannot write output folder {self.out}: {_reason(err)}") from err

    def __enter__(self) -> Path:
        return self.tmp

    def _release(self) -> None:
        """Unlink the lock file, then let go of it (in that order: see remove_stale_temporaries)."""
        if self._lock_fd is None:
            return
        try:
            self._lock.unlink()
        except OSError:
            pass
        os.close(self._lock_fd)
        self._lock_fd = None

    def discard(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)
        self._release()

    def commit(self) -> None:
        """Swap the finished temporary folder in for ``out``."""
        old: Path | None = None
        try:
            os.chmod(self.tmp, 0o777 & ~_umask())
            if self.out.exists():
                old = self.out.with_name(f".ficap-{self.out.name}.old-{os.getpid()}")
                shutil.rmtree(old, ignore_errors=True)
                os.replace(self.out, old)
            os.replace(self.tmp, self.out)
        except OSError as err:
            if old is not None and not self.out.exists():
                os.replace(old, self.out)  # put the previous outputs back
                old = None
            self.discard()
            raise OutputError(f"cannot write output folder {self.out}: {_reason(err)}") from err
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        self._release()

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.discard()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask

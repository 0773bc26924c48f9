"""Files in and out: the one rule every reader and writer of ficap_ros follows.

Reading (``read_bytes``, ``read_text``, ``load_yaml``): a user's file is read only when it is a
regular file no larger than its kind's limit (a FIFO, /dev/zero or a folder is refused before a
byte is read), as UTF-8 text; YAML through a loader without aliases (no "billion laughs") and
with a depth limit. Every failure is the caller's ``FicapError`` with one line naming the file.

Writing: every file and folder any verb writes is an ``OutputFile`` or an ``OutputFolder``, whose
construction checks everything before any processing (``check_output_file``,
``check_output_folder``):

    * never a path that is, holds or lies inside an input (``check_not_input``), nor one inside a
      recording (a rosbag2 folder ficap did not write), nor a recording file;
    * an existing folder is only replaced when ficap wrote it (``check_replaceable``); a symbolic
      link given as the output stands for its target (one that leads nowhere is refused);
    * the place must really be writable (a probe file, and the immutable and append-only flags);
    * one writer at a time: an ``OutputLock`` on the target refuses a second ficap process;
    * the content is written beside its target and renamed into place (``write_atomic``;
      an output folder is built in a temporary folder and swapped in whole), so a failing verb
      leaves nothing under the final name and a crash never half a file.
"""

from __future__ import annotations

import fcntl
import glob
import os
import re
import shutil
import stat
import struct
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable

from ficap_ros.errors import FicapError, OutputError

__all__ = ["read_bytes", "read_text", "load_yaml", "parse_yaml", "MAX_CONFIG_BYTES", "MAX_TABLE_BYTES",
           "write_atomic", "write_output_file", "check_output_file", "check_not_input",
           "check_not_in_recording", "check_replaceable", "check_output_folder", "OutputLock",
           "OutputFile", "OutputFolder", "FICAP_OUTPUT_FILES", "is_ficap_output",
           "is_recording_folder", "remove_stale_temporaries", "BAG_SUFFIXES", "VIDEO_SUFFIXES"]

#: Largest configuration file read (calibration, intrinsics, cap model, params): a hundred times
#: the largest such file ficap writes; a larger one is refused before it is read.
MAX_CONFIG_BYTES = 1 << 20
#: Largest table read (a labels CSV: a row per frame, days of frames).
MAX_TABLE_BYTES = 1 << 30
#: Deepest nesting of mappings and lists a YAML configuration may have (ficap's have 3).
MAX_YAML_DEPTH = 32
#: Most digits of an integer in a YAML configuration (an int64 has 19).
MAX_YAML_INT_DIGITS = 40
#: Files of a bag container and of videos: recordings, which no output ever replaces.
BAG_SUFFIXES = (".mcap", ".db3", ".bag")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv", ".h264")
_RECORDING_MAGIC = (b"\x89MCAP", b"SQLite format 3\x00", b"#ROSBAG")

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


# -- reading -------------------------------------------------------------------------------------
def read_bytes(path: str | os.PathLike[str], what: str, error: type[FicapError],
               limit: int = MAX_CONFIG_BYTES) -> bytes:
    """The bytes of a user's file, or ``error`` with one line naming it.

    Only a regular file is read (opened without blocking, so a FIFO never hangs the caller; a
    device such as /dev/zero is refused), and only when it holds at most ``limit`` bytes.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except IsADirectoryError:
        raise error(f"{what} {p} is a folder, not a file") from None
    except OSError as err:
        raise error(f"cannot read {what} {p}: {_reason(err)}") from err
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise error(f"{what} {p} is a folder, not a file")
        if not stat.S_ISREG(info.st_mode):
            raise error(f"{what} {p} is not a regular file (a device, FIFO or socket)")
        if info.st_size > limit:
            raise error(f"{what} {p} is {info.st_size} bytes, more than any {what} "
                        f"({limit} at most)")
        os.set_blocking(fd, True)
        with os.fdopen(fd, "rb", closefd=False) as handle:
            data = handle.read(limit + 1)
    except OSError as err:
        raise error(f"cannot read {what} {p}: {_reason(err)}") from err
    finally:
        os.close(fd)
    if len(data) > limit:  # grew while being read
        raise error(f"{what} {p} is more than {limit} bytes, more than any {what}")
    return data


def read_text(path: str | os.PathLike[str], what: str, error: type[FicapError],
              limit: int = MAX_CONFIG_BYTES) -> str:
    """The text of a user's file (``read_bytes``, decoded as UTF-8), or ``error`` with one line
    (missing, not a regular file, more than ``limit`` bytes, binary, not UTF-8); ``what`` names
    its kind in the message ("calibration", "intrinsics" ...)."""
    p = Path(path)
    data = read_bytes(p, what, error, limit)
    if b"\x00" in data:
        raise error(f"{what} {p} is a binary file, not text")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise error(f"{what} {p} is not UTF-8 text (byte {err.start})") from err


def _guarded_loader() -> type:
    """PyYAML's safe loader without aliases, with a nesting limit and short integers only."""
    import yaml

    class Loader(yaml.SafeLoader):
        depth = 0

        def compose_node(self, parent: Any, index: Any) -> Any:
            if self.check_event(yaml.AliasEvent):
                raise yaml.YAMLError(f"line {self.peek_event().start_mark.line + 1}: aliases "
                                     "(*name) are not allowed")
            self.depth += 1
            try:
                if self.depth > MAX_YAML_DEPTH:
                    raise yaml.YAMLError(f"line {self.peek_event().start_mark.line + 1}: nested "
                                         f"deeper than {MAX_YAML_DEPTH} levels")
                return super().compose_node(parent, index)
            finally:
                self.depth -= 1

        def construct_yaml_int(self, node: Any) -> int:
            digits = sum(c.isdigit() for c in str(node.value))
            if digits > MAX_YAML_INT_DIGITS:
                raise yaml.YAMLError(f"line {node.start_mark.line + 1}: an integer of {digits} "
                                     "digits")
            return super().construct_yaml_int(node)

    Loader.add_constructor("tag:yaml.org,2002:int", Loader.construct_yaml_int)
    return Loader


_LOADER: type | None = None  # built on first use (PyYAML is imported then)


def parse_yaml(text: str, source: str, error: type[FicapError]) -> Any:
    """YAML text through the guarded loader (no aliases, ``MAX_YAML_DEPTH`` levels, integers of
    at most ``MAX_YAML_INT_DIGITS`` digits), or ``error`` with one line naming ``source``."""
    import yaml

    global _LOADER
    if _LOADER is None:
        _LOADER = _guarded_loader()
    loader = None
    try:
        loader = _LOADER(text)
        return loader.get_single_data()
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise error(f"{source} is not valid YAML: {where}{problem}") from None
    except (ValueError, OverflowError, RecursionError, MemoryError) as err:
        raise error(f"{source} is not valid YAML: {type(err).__name__}") from None
    finally:
        if loader is not None:
            loader.dispose()


def load_yaml(path: str | os.PathLike[str], what: str, error: type[FicapError],
              limit: int = MAX_CONFIG_BYTES) -> Any:
    """A user's YAML file (``read_text``, then ``parse_yaml``), or ``error`` with one line."""
    return parse_yaml(read_text(path, what, error, limit), f"{what} {path}", error)


# -- the output rule -----------------------------------------------------------------------------
def _resolved(path: str | os.PathLike[str]) -> Path:
    return Path(os.path.abspath(os.path.realpath(path)))


def _target(path: str | os.PathLike[str], what: str) -> Path:
    """The path an output is written at: a symbolic link stands for its target (refused when it
    leads nowhere: a loop or a missing target)."""
    p = Path(path)
    if os.path.islink(p):
        try:
            os.stat(p)
        except OSError as err:
            raise OutputError(f"{what} {p} is a symbolic link that leads nowhere "
                              f"({_reason(err)})") from None
        return _resolved(p)
    return p


def _mutable(path: Path, what: str) -> None:
    """Refuse a path whose immutable or append-only flag (chattr +i/+a) forbids replacing it."""
    fs_ioc_getflags, immutable, append_only = 0x80086601, 0x10, 0x20
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return
    try:
        flags = struct.unpack("i", fcntl.ioctl(fd, fs_ioc_getflags, b"\0" * 4))[0]
    except OSError:
        return  # a file system without these flags
    finally:
        os.close(fd)
    if flags & (immutable | append_only):
        raise OutputError(f"cannot write {what} {path}: it is "
                          f"{'immutable' if flags & immutable else 'append-only'} (chattr)")


def _probe_writable(folder: Path, what: str, target: Path) -> None:
    """Create and remove a file in ``folder``: the only test that holds for root, read-only file
    systems and immutable folders alike."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".ficap-probe.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise OutputError(f"cannot write {what} {target}: folder {folder}: {_reason(err)}") from err


def check_not_input(out: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str] | None]
                    ) -> None:
    """Refuse an output that is an input, holds one, or lies inside one (a bag folder).

    Raises:
        OutputError: naming the input.
    """
    o = _resolved(out)
    for item in inputs:
        if item is None or str(item) == "":
            continue
        i = _resolved(item)
        if o == i or i.is_relative_to(o) or (i.is_dir() and o.is_relative_to(i)):
            raise OutputError(f"output {out} is, holds or lies inside the input {item}; "
                              "choose another output")


def _rosbag_files(meta: Path) -> list[str] | None:
    """The files a rosbag2 metadata.yaml lists; None when it is no rosbag2 metadata."""
    try:
        info = load_yaml(meta, "metadata", OutputError)
        return [str(f) for f in info["rosbag2_bagfile_information"]["relative_file_paths"]]
    except (FicapError, KeyError, TypeError):
        return None


def is_recording_folder(folder: str | os.PathLike[str]) -> bool:
    """A rosbag2 folder ficap did not write (its metadata.yaml lists more than labels.mcap)."""
    meta = Path(folder) / "metadata.yaml"
    if not meta.is_file():
        return False
    files = _rosbag_files(meta)
    return files is not None and files != ["labels.mcap"]


def _is_recording_file(path: Path) -> bool:
    if path.suffix.lower() in BAG_SUFFIXES + VIDEO_SUFFIXES:
        return True
    try:
        with open(path, "rb") as handle:
            head = handle.read(16)
    except OSError:
        return False
    return head.startswith(_RECORDING_MAGIC)


def check_not_in_recording(out: str | os.PathLike[str], what: str = "output") -> None:
    """Refuse an output inside a recording (a rosbag2 folder, at any depth above it) or over a
    recording file (a bag or a video, by name or content).

    Raises:
        OutputError: naming the recording.
    """
    p = _resolved(out)
    for folder in p.parents:
        if is_recording_folder(folder):
            raise OutputError(f"{what} {out} lies inside the recording {folder}; choose another "
                              "output")
    if p.is_file() and _is_recording_file(p):
        raise OutputError(f"{what} {out} is a recording; ficap never overwrites one")


def check_output_file(path: str | os.PathLike[str], inputs: Iterable[Any] = (),
                      what: str = "output") -> Path:
    """Every check a single output file needs, before any processing (the output rule).

    Returns:
        The path to write (a symbolic link's target).

    Raises:
        OutputError: a folder or special file, an input, a recording or inside one, an immutable
            file, or a folder that is missing or not writable (one line).
    """
    p = _target(path, what)
    if p.is_dir():
        raise OutputError(f"{what} {p} is a folder; give a file name")
    if p.exists() and not p.is_file():
        raise OutputError(f"{what} {p} is not a regular file")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"cannot write {what} {p}: folder {parent} does not exist")
    check_not_input(p, inputs)
    check_not_in_recording(p, what)
    if p.exists():
        _mutable(p, what)
    _probe_writable(parent, what, p)
    return p


def check_replaceable(out: str | os.PathLike[str], subfolders: bool = False) -> None:
    """Refuse to replace (or add files to) an existing folder that ficap did not write.

    An existing ``out`` may be replaced when it is empty or holds only files ficap writes
    (``is_ficap_output``), its ``metadata.yaml`` (if any) a rosbag2 of ficap's ``labels.mcap``
    only; a recording or a folder of the user's files is refused (``OutputError``, as a file).
    ``subfolders``: it may hold folders (a fleet's ``--out``), checked alike at any depth.
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
            files = _rosbag_files(meta)
            if files is None:
                raise OutputError(f"output folder {folder} holds a metadata.yaml ficap did not "
                                  "write; choose a new or empty folder")
            if files != ["labels.mcap"]:
                raise OutputError(f"output folder {folder} is a rosbag2 recording ficap did not "
                                  "write; choose a new or empty folder")


def check_output_folder(out: str | os.PathLike[str], inputs: Iterable[Any] = (),
                        subfolders: bool = False) -> Path:
    """``OutputFolder``'s checks without creating anything (fail before any processing).

    Returns:
        The folder to write (a symbolic link's target).
    """
    p = _target(out, "output folder")
    check_not_input(p, inputs)
    check_not_in_recording(p, "output folder")
    check_replaceable(p, subfolders)
    parent = p.parent if str(p.parent) else Path(".")
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent  # the first folder that exists is where it will be created
    if not parent.is_dir():
        raise OutputError(f"cannot write output folder {p}: {parent} is not a folder")
    _probe_writable(parent, "output folder", p)
    if p.exists():
        _mutable(p, "output folder")
    return p


# -- one writer at a time ------------------------------------------------------------------------
#: Locks this process holds, by target: a fleet's lock on its --out and the replay into that same
#: folder (a single recording) are one.
_HELD: dict[Path, list[Any]] = {}


class OutputLock:
    """An exclusive lock on an output target held by one process at a time.

    The lock file ``.ficap-lock.NAME`` beside the target (its folder is created) carries the
    holder's pid; the kernel lets go of the lock when that process dies, however it died. Taking
    it never waits unless ``wait`` (the demo's shared sample): a second writer is refused.

    Raises:
        OutputError: another process writes the target, or its folder is not writable.
    """

    def __init__(self, target: str | os.PathLike[str], what: str = "output",
                 wait: bool = False) -> None:
        self.target = _resolved(target)
        self.path = self.target.with_name(f".ficap-lock.{self.target.name}")
        held = _HELD.get(self.target)
        if held is not None:
            held[1] += 1
            return
        while True:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            except OSError as err:
                raise OutputError(f"cannot write {what} {target}: {_reason(err)}") from err
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
            except OSError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
                os.close(fd)
                raise OutputError(
                    f"{what} {target} is being written by another ficap process"
                    f"{f' (pid {holder})' if holder.isdigit() else ''}; wait for it to end or "
                    "choose another output") from None
            try:  # the file still under its name (not one a finishing holder just unlinked)
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except OSError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        _HELD[self.target] = [fd, 1]

    def release(self) -> None:
        """Let go (the lock file goes first, then the lock: see ``__init__``'s check)."""
        held = _HELD.get(self.target)
        if held is None:
            return
        held[1] -= 1
        if held[1] > 0:
            return
        del _HELD[self.target]
        try:
            self.path.unlink()
        except OSError:
            pass
        os.close(held[0])

    def __enter__(self) -> OutputLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


# -- writing -------------------------------------------------------------------------------------
def write_atomic(path: str | os.PathLike[str], text: str | bytes) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder, then rename.

    A crash or Ctrl-C never leaves a half-written file at ``path``.

    Raises:
        OSError: the folder is not writable, the disk is full (``OutputFile`` makes these one line).
    """
    path = Path(path)
    data = text.encode() if isinstance(text, str) else text
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp's 0600: the permissions open() would give
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


class OutputFile:
    """A single file a verb writes, checked and locked when the verb starts, written when it ends.

    ``OutputFile(path, inputs)`` runs ``check_output_file`` and takes the target's
    ``OutputLock``; ``write(data)`` writes it beside its target and renames it into place;
    ``close()`` (or leaving the ``with`` block) lets go of the lock.

    Args:
        path: the file.
        inputs: the verb's inputs (recordings and configuration files).
        what: what it is, for the messages ("cap model", "report" ...).
        replaceable: says why an existing file at ``path`` must not be replaced ('' when it may).
    """

    def __init__(self, path: str | os.PathLike[str], inputs: Iterable[Any] = (),
                 what: str = "output", replaceable: Callable[[Path], str] | None = None) -> None:
        self.what = what
        self.path = check_output_file(path, inputs, what)
        if replaceable is not None and self.path.is_file():
            if why := replaceable(self.path):
                raise OutputError(f"{self.path} exists and is not {why}; not overwritten")
        self._lock: OutputLock | None = OutputLock(self.path, what)

    def write(self, data: str | bytes) -> Path:
        try:
            write_atomic(self.path, data)
        except OSError as err:
            raise OutputError(f"cannot write {self.what} {self.path}: {_reason(err)}") from err
        return self.path

    def close(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self) -> OutputFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_output_file(path: str | os.PathLike[str], data: str | bytes,
                      inputs: Iterable[Any] = (), what: str = "output") -> Path:
    """One file written at once under the output rule (``OutputFile``); returns its path."""
    with OutputFile(path, inputs, what) as out:
        return out.write(data)


_LOCK = ".lock"


def remove_stale_temporaries(out: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporary folders of ``out`` left by runs that were killed outright (SIGKILL).

    Each run's ``.ficap-NAME.XXXX`` folder has a ``.ficap-NAME.XXXX.lock`` file beside it, which
    the run holds an exclusive ``flock`` on while it lives (the kernel lets go when the process is
    gone, however it died). A lock taken here, on a file still linked under its name, is a dead
    run's: its folder goes, then the lock file. A live run's lock cannot be taken; a folder without
    a lock file (an older ficap's, or one being created) and the previous outputs renamed aside
    during a commit (``.old-PID``) are left alone.

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
            here, held = os.stat(lock), os.fstat(fd)  # still the file under that name
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

    ``with OutputFolder(out, inputs) as tmp:`` write every file into ``tmp`` (or ``write``); on a
    clean exit ``out`` is replaced by it (the old folder renamed away first, removed after), on an
    exception (Ctrl-C included) ``tmp`` is removed and ``out`` left as it was. ``__init__`` checks
    (``check_output_folder``), takes the target's ``OutputLock`` and creates the temporary folder
    beside the target, so a command fails before hours of processing (``OutputError``, one line).

    Args:
        out: the folder (a symbolic link stands for its target).
        inputs: the verb's inputs.
        merge: keep the files of an existing ``out`` this run does not write (``stats``,
            ``evaluate``, ``kit`` add theirs to a folder of ficap's), linked in before the swap.
        subfolders: ``out`` may hold folders of ficap's (``check_replaceable``).
    """

    def __init__(self, out: str | os.PathLike[str], inputs: Iterable[Any] = (),
                 merge: bool = False, subfolders: bool = False) -> None:
        self.out = check_output_folder(out, inputs, subfolders)
        self.merge = merge
        parent = self.out.parent if str(self.out.parent) else Path(".")
        self._lock_fd: int | None = None
        self._target_lock: OutputLock | None = None
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(f"cannot write output folder {self.out}: {_reason(err)}") from err
        self._target_lock = OutputLock(self.out, "output folder")
        try:
            remove_stale_temporaries(self.out)
            # The lock file first, naming the folder (see remove_stale_temporaries).
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

    def write(self, name: str, data: str | bytes) -> Path:
        """Write one file of the folder (atomically, into the temporary folder)."""
        try:
            write_atomic(self.tmp / name, data)
        except OSError as err:
            raise OutputError(f"cannot write {self.out / name}: {_reason(err)}") from err
        return self.out / name

    def _release(self) -> None:
        """Unlink the lock file, then let go of it (in that order: see remove_stale_temporaries);
        then the target's lock."""
        if self._lock_fd is not None:
            try:
                self._lock.unlink()
            except OSError:
                pass
            os.close(self._lock_fd)
            self._lock_fd = None
        if self._target_lock is not None:
            self._target_lock.release()
            self._target_lock = None

    def discard(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)
        self._release()

    def _merge_old(self) -> None:
        """Link the old folder's files this run did not write into the new one."""
        for old in self.out.iterdir():
            new = self.tmp / old.name
            if old.is_file() and not old.is_symlink() and not new.exists() \
                    and not old.name.startswith(".ficap"):
                try:
                    os.link(old, new)
                except OSError:
                    shutil.copy2(old, new)

    def commit(self) -> None:
        """Swap the finished temporary folder in for ``out``."""
        old: Path | None = None
        try:
            os.chmod(self.tmp, 0o777 & ~_umask())
            if self.merge and self.out.is_dir():
                self._merge_old()
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

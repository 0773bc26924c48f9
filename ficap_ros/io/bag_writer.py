"""Writing rosbag2 bags (MCAP or sqlite3) atomically (no ROS install needed).

A bag is written into a hidden temporary folder beside its destination and renamed into place when
complete, so an error or Ctrl-C never leaves a partial bag. Messages come from
``ficap_ros.io.messages``'s builders over ``messages.ROSBAGS``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ficap_ros.errors import BagError, OutputError
from ficap_ros.io.messages import jazzy_typestore

__all__ = ["BagWriter"]


class BagWriter:
    """Write a rosbag2 bag atomically: into a hidden temporary folder, renamed when complete.

    Use as a context manager. ``layout``:
        ``folder``: ``path`` becomes a rosbag2 folder (``metadata.yaml`` + ``<name>.mcap``/``.db3``).
        ``file``: ``path`` is a single ``.mcap`` file (rosbag2 MCAP profile, with the rosbag2
            metadata record inside) and ``metadata.yaml`` is put next to it, so the file's folder
            is also a rosbag2 bag (``ros2 bag info DIR`` and ``ros2 bag info DIR/x.mcap`` both
            work). An existing ``metadata.yaml`` there is replaced.

    An exception (Ctrl-C included) inside the ``with`` block removes the temporary folder and
    leaves ``path`` untouched.

    Raises:
        BagError: the destination folder is not writable.
    """

    def __init__(self, path: str | Path, storage: str = "mcap", layout: str = "folder") -> None:
        if storage not in ("mcap", "sqlite3"):
            raise BagError(f"unknown bag storage {storage!r}; expected mcap or sqlite3")
        if layout not in ("folder", "file"):
            raise BagError(f"unknown bag layout {layout!r}")
        if layout == "file" and storage != "mcap":
            raise BagError("a single-file bag must use MCAP storage")
        self.path = Path(path)
        self.storage = storage
        self.layout = layout
        self.typestore = jazzy_typestore()
        self._writer: Any = None
        self._tmpdir: Path | None = None
        self._conns: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        import shutil
        import tempfile

        from rosbags.rosbag2 import StoragePlugin, Writer

        parent = self.path.parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=parent))
        except OSError as err:
            raise OutputError(f"cannot write to {parent}: {err.strerror or err}") from err
        name = self.path.stem if self.layout == "file" else self.path.name
        plugin = StoragePlugin.MCAP if self.storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self._tmpdir / name, version=9, storage_plugin=plugin)
        try:
            self._writer.open()
        except OSError as err:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            raise OutputError(f"cannot write {self.path}: {err.strerror or err}") from err
        return self

    def set_custom_data(self, key: str, value: str) -> None:
        """A string in metadata.yaml's ``custom_data`` (before the bag is closed)."""
        self._writer.set_custom_data(key, value)

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Declare a topic (once) before writing to it."""
        self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self.typestore)

    def write(self, topic: str, stamp_ns: int, msg: Any) -> None:
        """Serialize ``msg`` (a rosbags message object) and write it with receive time ``stamp_ns``."""
        conn = self._conns[topic]
        try:
            self._writer.write(conn, int(stamp_ns),
                               self.typestore.serialize_cdr(msg, conn.msgtype))
        except OSError as err:  # a full disk: one line, and __exit__ removes the temporary
            raise OutputError(f"cannot write {self.path}: {err.strerror or err}") from err

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        import shutil

        assert self._tmpdir is not None
        try:
            if exc_type is not None:
                try:
                    self._writer.abort() if hasattr(self._writer, "abort") else None
                except Exception:  # noqa: BLE001 - the original error matters, not this one
                    pass
                return
            try:
                self._writer.close()
            except OSError as err:
                raise OutputError(f"cannot write {self.path}: {err.strerror or err}") from err
            inner = self._tmpdir / (self.path.stem if self.layout == "file" else self.path.name)
            try:
                if self.layout == "file":
                    os.replace(inner / self.path.name, self.path)
                    os.replace(inner / "metadata.yaml", self.path.parent / "metadata.yaml")
                else:
                    if self.path.exists():
                        shutil.rmtree(self.path)
                    os.replace(inner, self.path)
            except OSError as err:
                raise OutputError(f"cannot write {self.path}: {err.strerror or err}") from err
        finally:
            shutil.rmtree(self._tmpdir, ignore_errors=True)

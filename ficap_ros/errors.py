"""One exception hierarchy for ficap_ros.

Every error a user can cause (bad image, bad intrinsics, bad model file, bad bag) is a
``FicapError`` subclass whose message is one readable line; the CLI prints it and exits non-zero,
the node logs it (throttled) and reports it in its status.
"""

from __future__ import annotations

__all__ = [
    "FicapError",
    "ModelError",
    "ImageError",
    "IntrinsicsError",
    "ConfigError",
    "CalibrationError",
    "BagError",
    "OutputError",
    "WorkerError",
    "one_line",
    "missing_module",
]


class FicapError(Exception):
    """Root of every error ficap_ros raises on purpose."""


class ModelError(FicapError):
    """A cap model is malformed: wrong shape, duplicate ids, unreadable file."""


class ImageError(FicapError):
    """An image is empty, of the wrong type or shape, or cannot be decoded."""


class IntrinsicsError(FicapError):
    """Camera intrinsics are missing, zero, NaN or of an unknown lens model."""


class ConfigError(FicapError):
    """A configuration value is out of range or of an unknown name."""


class CalibrationError(FicapError):
    """A calibration cannot be computed (too few frames, spread too large)."""


class BagError(FicapError):
    """A bag or video cannot be read or written (corrupt, truncated, missing topic)."""


class OutputError(FicapError):
    """An output cannot be written, or would overwrite an input or a folder ficap did not write."""


class WorkerError(FicapError):
    """A worker process died (killed, out of memory, a crash in a native library) or did not
    start or answer in time, and retrying did not help."""


def one_line(err: BaseException, typed: bool = False) -> str:
    """An error as one line of text, for a message that quotes it.

    A ``FicapError``'s message is one line already. Another error's message is reduced to its
    first line (its type's name when it has none); ``typed`` instead names the type, then gives the
    message's last line: for errors of unknown origin, such as a Ray task's, whose message is a
    traceback that names the task first and ends with the cause.
    """
    lines = str(err).strip().splitlines()
    if typed and not isinstance(err, FicapError):
        return f"{type(err).__name__}: {lines[-1] if lines else ''}".strip()
    return lines[0] if lines else type(err).__name__


#: Third-party modules by the package that brings them: (pip package, rosdep key or '' for none).
_PROVIDERS = {
    "rosbags": ("rosbags", "python3-rosbags-pip"),
    "mcap": ("mcap", "mcap-ros2-support"),
    "pupil_apriltags": ("pupil-apriltags", ""),
    "ray": ("ray", ""),
    "tqdm": ("tqdm", "python3-tqdm"),
    "matplotlib": ("matplotlib", "python3-matplotlib"),
    "yaml": ("PyYAML", "python3-yaml"),
}


def missing_module(err: ModuleNotFoundError) -> str:
    """A missing module as one line naming what to install (the requirements files and
    package.xml list every module ficap_ros imports)."""
    top = (err.name or "?").split(".")[0]
    pip, key = _PROVIDERS.get(top, (top, ""))
    how = f"pip install {pip}" + (f", or rosdep key {key}" if key else "")
    return f"the Python module {top} is not installed ({how})"

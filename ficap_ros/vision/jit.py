"""The compiled kernels' runtime: where numba keeps their machine code, and their warm-up.

The per-pixel kernels (``ficap_ros.vision.kernels``: the corner stage's profiles and line pass;
``ficap_ros.vision.fit_kernels``: its tag-level steps, the border unbias, the cell-edge fit and the
noise ratio; ``ficap_ros.vision.cell_reads``: reading a tag's cells at its corners;
``ficap_ros.vision.photometric_kernels``: the photometric and moving tags' fits;
``ficap_ros.vision.pose_kernels``: the pose solvers' reprojection;
``ficap_ros.vision.uncertainty_kernels``: the pose covariance's unit terms) are numba functions compiled on
their first call and cached on disk (``njit(cache=True)``), so a
later process loads them instead of compiling. numba keeps that cache next to the source
(``__pycache__``) when the package's directory is writable (a clone, an editable install). Where
it is not (an apt or colcon install), the cache goes to the user's cache directory,
``$XDG_CACHE_HOME/ficap_ros/numba`` (``~/.cache/ficap_ros/numba`` without it), through numba's
``NUMBA_CACHE_DIR``: set here before numba is imported, and only when the user has not set it.

``warm_up`` runs every kernel once on a tiny input of the types the pipeline passes (a kernel is
compiled, or loaded, per argument type): the node calls it at start-up, so no frame pays for it.
Importing this module imports numba; the corner stage imports it, so every detecting command does.
A command loads (or compiles) only the kernels it calls: the photometric ones only with
photometric corners or moving tags.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["njit", "cache_dir", "register_warm_up", "warm_up"]

_PACKAGE_DIR = Path(__file__).resolve().parents[1]


def _user_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/ficap_ros/numba``, or ``~/.cache/ficap_ros/numba`` without it."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "ficap_ros" / "numba"


def _choose_cache_dir() -> None:
    """Point numba's cache at the user's cache directory when the package's own directory is not
    writable and the user has not chosen one (``NUMBA_CACHE_DIR``)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    if os.access(_PACKAGE_DIR / "vision", os.W_OK):
        return
    os.environ["NUMBA_CACHE_DIR"] = str(_user_cache_dir())


_choose_cache_dir()

import numba  # noqa: E402  (after the cache directory is chosen: numba reads it at import)

_WARM_UPS: list[Callable[[], None]] = []


def njit(fn: Callable | None = None, *, inline: str = "never", error_model: str = "python") -> Callable:
    """``numba.njit(cache=True)``: compiled on the first call per argument types, kept on disk.
    ``inline="always"`` (as ``@njit(inline="always")``): a small helper inlined into its callers'
    loops (numba passes array arguments to a called kernel with reference counting).
    ``error_model="numpy"``: a float division by zero gives inf or NaN, as numpy's does, instead of
    raising ``ZeroDivisionError``."""
    options = {"cache": True, "inline": inline, "error_model": error_model}
    if fn is None:
        return lambda f: numba.njit(**options)(f)
    return numba.njit(**options)(fn)


def cache_dir() -> Path:
    """Where this process's kernels are cached: ``NUMBA_CACHE_DIR`` when set, else the kernels'
    own ``__pycache__``."""
    chosen = os.environ.get("NUMBA_CACHE_DIR")
    return Path(chosen) if chosen else _PACKAGE_DIR / "vision" / "__pycache__"


def register_warm_up(fn: Callable[[], None]) -> Callable[[], None]:
    """Register ``fn`` (no arguments: calls a module's kernels on a tiny input) for ``warm_up``."""
    _WARM_UPS.append(fn)
    return fn


def warm_up() -> float:
    """Compile (or load from the cache) every kernel for the argument types the pipeline passes;
    returns the seconds it took (wall clock)."""
    # The modules register their kernels' warm-ups when imported.
    import ficap_ros.vision.cell_reads  # noqa: F401
    import ficap_ros.vision.fit_kernels  # noqa: F401
    import ficap_ros.vision.kernels  # noqa: F401
    import ficap_ros.vision.photometric_kernels  # noqa: F401
    import ficap_ros.vision.pose_kernels  # noqa: F401
    import ficap_ros.vision.uncertainty_kernels  # noqa: F401

    t0 = time.perf_counter()
    for fn in _WARM_UPS:
        fn()
    return time.perf_counter() - t0

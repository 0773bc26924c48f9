"""CPU time: of a child command (``os.wait4``'s rusage), and the own time of the package's public
functions inside this process.

``OwnTime`` wraps public functions (never a ``_private`` one) wherever the loaded ``ficap_ros``
modules hold them (a module that did ``from x import f`` holds its own reference), so a stage is
timed wherever it is called from. A stage's own time leaves out the time of the wrapped stages it
calls. Generator functions are timed per item. The wrappers cost about a microsecond a call.
"""

from __future__ import annotations

import functools
import importlib
import inspect
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class ChildRun:
    cpu_s: float  # user + sys of the child
    wall_s: float
    stdout: str
    returncode: int


def run_child(cmd: Sequence[str], env: dict[str, str] | None = None, ok: tuple[int, ...] = (0,)) -> ChildRun:
    """Run ``cmd`` and measure its CPU time (user + sys, its own children included)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(list(cmd), stdout=subprocess.PIPE, text=True, env=env)
    stdout = proc.stdout.read() if proc.stdout else ""
    _pid, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    proc.returncode = code
    if code not in ok:
        raise RuntimeError(f"{' '.join(cmd)} exited {code}")
    return ChildRun(usage.ru_utime + usage.ru_stime, wall, stdout, code)


def ficap_command(*args: str) -> list[str]:
    """The ``ficap`` command line run with this interpreter."""
    return [sys.executable, "-m", "ficap_ros.cli", *args]


class OwnTime:
    """Own CPU time (``time.process_time``) of public functions, by label.

    ``stages``: (module, "function" or "Class.method", label) rows; several rows may share a
    label. Use as a context manager; ``ms_per(n)`` gives each label's total in ms divided by
    ``n``."""

    def __init__(self, stages: Sequence[tuple[str, str, str]]) -> None:
        for _m, attr, _l in stages:
            if any(part.startswith("_") for part in attr.split(".")):
                raise ValueError(f"{attr}: only public functions are timed")
        self.stages = stages
        self.own: dict[str, float] = {}
        self._stack: list[list[float]] = []
        self._undo: list[tuple[object, str, object]] = []

    def _leave(self, t0: float, label: str) -> None:
        dt = time.process_time() - t0
        inner = self._stack.pop()[0]
        self.own[label] = self.own.get(label, 0.0) + dt - inner
        if self._stack:
            self._stack[-1][0] += dt

    def _wrap(self, fn, label: str):  # noqa: ANN001, ANN202
        timer = self
        if inspect.isgeneratorfunction(fn):
            @functools.wraps(fn)
            def timed_gen(*a, **k):  # noqa: ANN002, ANN003, ANN202
                gen = fn(*a, **k)
                while True:
                    timer._stack.append([0.0])
                    t0 = time.process_time()
                    try:
                        item = next(gen)
                    except StopIteration:
                        return
                    finally:
                        timer._leave(t0, label)
                    yield item
            return timed_gen

        @functools.wraps(fn)
        def timed(*a, **k):  # noqa: ANN002, ANN003, ANN202
            timer._stack.append([0.0])
            t0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                timer._leave(t0, label)
        return timed

    def __enter__(self) -> OwnTime:
        for mod_name, attr, label in self.stages:
            owner = importlib.import_module(mod_name)
            *path, name = attr.split(".")
            for part in path:
                owner = getattr(owner, part)
            fn = owner.__dict__[name]
            wrapped = self._wrap(fn, label)
            self._undo.append((owner, name, fn))
            setattr(owner, name, wrapped)
            if not path:  # a module function: also where other modules imported it by name
                for mod in list(sys.modules.values()):
                    if getattr(mod, "__name__", "").startswith("ficap_ros") and mod.__dict__.get(name) is fn:
                        self._undo.append((mod, name, fn))
                        setattr(mod, name, wrapped)
        return self

    def __exit__(self, *exc: object) -> None:
        for owner, name, fn in reversed(self._undo):
            setattr(owner, name, fn)
        self._undo.clear()

    def ms_per(self, n: int) -> dict[str, float]:
        return {k: 1e3 * v / max(n, 1) for k, v in self.own.items()}

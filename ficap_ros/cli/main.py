"""``ficap <verb>``: the command-line face of the core.

Each verb lives in ``ficap_ros/cli/<verb>.py`` and provides ``HELP``, ``add_arguments(parser)``
and ``run(args) -> int``; heavy imports happen inside ``run`` so ``ficap --help`` stays quick.
Errors a user can cause, and a missing optional package, print one line (``ficap: error: ...``)
and exit 1, and so do a file system error or exhausted memory that no check foresaw (never a
traceback). Exit codes: 0 done, 1 error, 2 bad arguments (argparse), 3 done but frames were lost
to a damaged input (the summary line says how many and when), 130 interrupted.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Sequence

from ficap_ros.errors import FicapError, missing_module, one_line

#: Verb -> module under ficap_ros.cli, in the order ``--help`` lists them.
VERBS: dict[str, str] = {
    "demo": "demo",
    "model": "model",
    "detect": "detect",
    "replay": "replay",
    "stats": "stats",
    "calibrate": "calibrate",
    "evaluate": "evaluate",
    "synth": "synth",
    "kit": "kit",
}


def _version() -> str:
    """The running source's version (``ficap_ros.__version__``, which package.xml and setup.py
    repeat): not the installed metadata, which an editable install leaves stale after a pull."""
    from ficap_ros import __version__

    return __version__


def _available_verbs() -> dict[str, object]:
    """Every verb's module; a missing one is a broken install and fails loudly (ImportError), not
    a verb silently absent from ``--help``."""
    return {verb: importlib.import_module(f"ficap_ros.cli.{module_name}")
            for verb, module_name in VERBS.items()}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ficap", description="Fi-Cap head-pose ground truth: tools around the core."
    )
    parser.add_argument("--version", action="version", version=f"ficap {_version()}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for verb, module in _available_verbs().items():
        p = sub.add_parser(verb, help=module.HELP, description=module.HELP)  # type: ignore[attr-defined]
        module.add_arguments(p)  # type: ignore[attr-defined]
        p.set_defaults(_run=module.run)  # type: ignore[attr-defined]
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from ficap_ros.io.native_log import ThrottledStderr

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        from ficap_ros.io.image_codec import max_pixels

        max_pixels()  # a bad FICAP_MAX_PIXELS is one line before anything runs
        # libjpeg/FFmpeg print on fd 2 per damaged frame: throttled to a warning per kind.
        with ThrottledStderr():
            return int(args._run(args) or 0)
    except FicapError as err:
        print(f"ficap: error: {err}", file=sys.stderr)
        return 1
    except ModuleNotFoundError as err:  # an optional package a verb or input needs
        print(f"ficap: error: {missing_module(err)}", file=sys.stderr)
        return 1
    except MemoryError:
        print("ficap: error: out of memory", file=sys.stderr)
        return 1
    except OSError as err:
        if isinstance(err, BrokenPipeError):
            return 0
        where = f": {err.filename}" if err.filename else ""
        print(f"ficap: error: {err.strerror or one_line(err)}{where}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("ficap: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

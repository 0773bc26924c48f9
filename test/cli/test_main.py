"""ficap_ros.cli.main: the parser (--version, every verb's module, every option's help and
default)."""

from __future__ import annotations

import pytest

from ficap_ros.cli.main import main


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from ficap_ros import __version__

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"ficap {__version__}"


def test_version_is_one_number_everywhere() -> None:
    # The fleet's fingerprint holds __version__ (outputs of another version are redone): it must be
    # the version colcon and pip install, bumped whenever labels change.
    import re
    from pathlib import Path

    from ficap_ros import __version__

    root = Path(__file__).resolve().parents[2]
    xml = re.search(r"<version>([^<]+)</version>", (root / "package.xml").read_text()).group(1)
    setup = re.search(r'version="([^"]+)"', (root / "setup.py").read_text()).group(1)
    assert xml == setup == __version__


def test_a_missing_verb_module_fails_loudly(monkeypatch) -> None:
    """A verb whose module is missing is a broken install: an ImportError, not a verb silently
    left out of --help."""
    from ficap_ros.cli import main as cli

    monkeypatch.setitem(cli.VERBS, "ghost", "no_such_verb_module")
    with pytest.raises(ImportError):
        cli.build_parser()


def test_every_option_has_help_that_states_its_default() -> None:
    """`ficap VERB --help`: no option without a help text, and every option with a default says
    which (a user should not have to read the code for it)."""
    import argparse

    from ficap_ros.cli.main import build_parser

    missing = []

    def walk(parser: argparse.ArgumentParser, name: str) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for verb, sub in action.choices.items():
                    walk(sub, f"{name} {verb}")
            elif action.dest in ("help", "version"):
                continue
            elif not action.help:
                missing.append((name, action.dest, "no help"))
            elif action.default not in (None, False) and "default" not in action.help:
                missing.append((name, action.dest, f"default {action.default!r} not stated"))

    walk(build_parser(), "ficap")
    assert missing == []

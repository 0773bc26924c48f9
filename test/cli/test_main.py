"""ficap --version, the demo's options, and the progress bar (tqdm) of replay."""

from __future__ import annotations

import io

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


def test_demo_rejects_what_it_cannot_honour(capsys: pytest.CaptureFixture[str]) -> None:
    # Live: a drive no longer than the 3 s frontal segment cannot be calibrated: one line, exit 1
    # (before anything is rendered or ROS started).
    assert main(["demo", "--frames", "60"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--frames 60" in err[0]
    for bad in (["--lighting", "dusk"], ["--method", "magic"], ["--frames", "0"],
                ["--every", "0"], ["--resolution", "10x10"], ["--seed", "x"]):
        with pytest.raises(SystemExit) as exc:
            main(["demo", *bad])
        assert exc.value.code == 2, bad


def test_demo_offline_honours_its_options(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--offline", "--frames", "3", "--resolution", "640x360",
                 "--lighting", "low", "--method", "naive", "--seed", "4", "--every", "2"]) == 0
    out = capsys.readouterr().out
    assert "3 frames, 640x360, low light, method naive" in out
    rows = [ln for ln in out.splitlines() if ln[:5].strip().isdigit()]
    assert [int(r.split()[0]) for r in rows] == [0, 2]  # every 2nd frame printed


def test_progress_is_per_frame_and_quiet_off_a_terminal() -> None:
    from ficap_ros.tools.replay import Progress

    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    tty = Tty()
    bar = Progress(5, "frames", tty)
    for n in range(1, 6):
        bar.update(1)
        assert bar.n == n
    bar.close()
    assert "5/5" in tty.getvalue() and "frame/s" in tty.getvalue()
    plain = io.StringIO()  # a log file: nothing
    bar = Progress(5, "frames", plain)
    bar.update(5)
    bar.close()
    assert plain.getvalue() == ""


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


@pytest.mark.parametrize("argv", [
    ["evaluate", "--truth", "t.csv", "--estimate", "e.csv", "--max-dt-ms", "-5"],
    ["evaluate", "--truth", "t.csv", "--estimate", "e.csv", "--max-dt-ms", "0"],
    ["calibrate", "l.csv", "--reference", "b:/t", "--out", "c.yaml", "--max-dt-ms", "-5"],
    ["kit", "--out", "k", "--shell-thickness-mm", "nan"],
    ["kit", "--out", "k", "--shell-thickness-mm", "-1"],
])
def test_negative_or_zero_tolerances_are_bad_arguments(argv: list[str],
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """Exit 2 naming the flag, like NaN (calibrate took -5 ms and said 'no reference pose within
    -5 ms'; evaluate and kit exited 1)."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert f"argument {argv[-2]}:" in capsys.readouterr().err


def test_demo_does_not_reuse_a_sample_drive_of_an_earlier_renderer(tmp_path, monkeypatch) -> None:
    # The sample drive is rendered once per set of options and cached; a renderer that draws
    # other pixels (the neutral light became mostly a lamp at the camera) needs its own key, or
    # `make demo` keeps playing the drive an earlier renderer left in the cache.
    from ficap_ros.cli import demo, synth

    monkeypatch.setenv("FICAP_CACHE", str(tmp_path))
    old = tmp_path / "sample_drive_540p_neutral_240_30.0_1_90_3.0_chain2"  # before the lamp
    old.mkdir()
    (old / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    rendered = []

    def fake_write(bag, model, progress=True, **sample):  # noqa: ANN001, ANN003 - records the call
        rendered.append(bag)
        bag.mkdir()
        (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")

    monkeypatch.setattr(synth, "write_synth_bag", fake_write)
    bag = demo.sample_recording(progress=False)
    assert rendered == [bag] and bag != old and bag.parent == tmp_path
    assert demo.sample_recording(progress=False) == bag and rendered == [bag]  # cached from now on

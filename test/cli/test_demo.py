"""ficap demo: the options it refuses before rendering or starting ROS, the offline run's options,
the cached sample recording (keyed on the renderer), and the live run's wiring."""

from __future__ import annotations

from pathlib import Path

import pytest

from ficap_ros.cli.main import main


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


def test_demo_does_not_reuse_a_sample_drive_of_an_earlier_renderer(tmp_path, monkeypatch) -> None:
    # The sample drive is rendered once per set of options and cached; a renderer that draws
    # other pixels has its own key (RENDER_VERSION), or `make demo` would keep playing the drive
    # an earlier renderer left in the cache.
    from ficap_ros.cli import demo, synth

    monkeypatch.setenv("FICAP_CACHE", str(tmp_path))
    old = tmp_path / "sample_drive_540p_neutral_240_30.0_1_90_3.0_chain2"  # RENDER_VERSION 2
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


def test_the_live_demo_plays_the_sample_it_was_asked_for(monkeypatch: pytest.MonkeyPatch) -> None:
    """The live run's options reach the sample recording (its drive) and the node (its method,
    the printing), and its exit code is the demo's."""
    from ficap_ros.cli import demo
    from ficap_ros.ros import demo as ros_demo

    asked: dict[str, object] = {}

    def sample(**options: object) -> Path:
        asked["sample"] = options
        return Path("/cache/sample")

    def play(bag: Path, frontal_s: float, every: int, method: str = "joint") -> int:
        asked["play"] = (bag, frontal_s, every, method)
        return 7

    monkeypatch.setattr(demo, "sample_recording", sample)
    monkeypatch.setattr(ros_demo, "run_demo", play)
    assert main(["demo", "--frames", "120", "--resolution", "640x360", "--lighting", "low",
                 "--seed", "9", "--method", "paper", "--every", "3"]) == 7
    assert asked["sample"] == {"resolution": (640, 360), "lighting": "low", "frames": 120, "seed": 9}
    assert asked["play"] == (Path("/cache/sample"), 3.0, 3, "paper")
    assert main(["demo"]) == 7  # the embedded defaults
    assert asked["sample"] == {"resolution": "540p", "lighting": "neutral", "frames": 240, "seed": 1}
    assert asked["play"] == (Path("/cache/sample"), 3.0, 6, "joint")


def test_each_set_of_options_has_its_own_cached_recording(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    from ficap_ros.cli import demo, synth
    from ficap_ros.tools.synth import RENDER_VERSION

    monkeypatch.setenv("FICAP_CACHE", str(tmp_path))
    written: list[tuple[Path, dict]] = []

    def fake_write(bag, model, progress=True, **sample):  # noqa: ANN001, ANN003 - records the call
        written.append((bag, sample))
        bag.mkdir()
        (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")

    monkeypatch.setattr(synth, "write_synth_bag", fake_write)
    a = demo.sample_recording(progress=False)
    b = demo.sample_recording(progress=False, resolution=(640, 360), seed=2)
    assert a != b and a.name.endswith(f"_chain{RENDER_VERSION}") and "640x360" in b.name
    assert written[0][1] == demo.SAMPLE
    assert written[1][1] == {**demo.SAMPLE, "resolution": (640, 360), "seed": 2}
    assert demo.sample_recording(progress=False, seed=2, resolution=(640, 360)) == b
    assert len(written) == 2

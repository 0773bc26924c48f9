"""ficap detect: JSON output, and one line on a corrupt image."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from recordings import one_error_line

from ficap_ros.cli.main import main as cli_main


def test_cli_json(real_apriltag_dir, capsys):
    path = str(real_apriltag_dir / "apriltags_jl" / "tagtest.jpg")
    assert cli_main(["detect", "--json", path]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["image"] for r in out] == [path]
    dets = out[0]["detections"]
    assert sorted(d["id"] for d in dets) == [5, 6, 9]
    for d in dets:
        assert set(d) == {"id", "corners_px"}
        assert np.asarray(d["corners_px"]).shape == (4, 2)
    assert cli_main(["detect", "--backend", "apriltag", "--refine", "none", path]) == 0
    assert "id" in capsys.readouterr().out


def test_cli_corrupt_image_exits_1_with_one_line(tmp_path, capsys):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    assert cli_main(["detect", str(bad)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("ficap: error:") and "\n" not in err


def test_detect_reports_good_images_beside_a_bad_one(real_apriltag_dir: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    good = str(real_apriltag_dir / "apriltags_jl" / "tagtest.jpg")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    assert cli_main(["detect", good, str(bad)]) == 1
    captured = capsys.readouterr()
    assert captured.out.startswith(f"{good}: 3 tag(s)")
    assert captured.err.strip().count("\n") == 0 and str(bad) in captured.err


def test_an_image_above_the_pixel_budget_is_one_line(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    big = tmp_path / "big.png"
    cv2.imwrite(str(big), np.zeros((6000, 8000), np.uint8))  # 48 MP, a few kB as PNG
    assert cli_main(["detect", str(big)]) == 1
    assert "budget" in one_error_line(capsys)


def test_photometric_is_opt_in(real_apriltag_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--no-photometric is the default's corners to the bit; --photometric moves them (by a fraction
    of a pixel) and needs the edge refinement."""
    path = str(real_apriltag_dir / "apriltags_jl" / "tagtest.jpg")

    def corners(*flags: str) -> np.ndarray:
        assert cli_main(["detect", "--json", *flags, path]) == 0
        dets = sorted(json.loads(capsys.readouterr().out)[0]["detections"], key=lambda d: d["id"])
        return np.array([d["corners_px"] for d in dets])

    default = corners()
    np.testing.assert_array_equal(corners("--no-photometric"), default)
    moved = np.abs(corners("--photometric") - default)
    assert 0.0 < moved.max() < 1.0
    assert cli_main(["detect", "--refine", "subpix", "--photometric", path]) == 1
    assert "photometric" in capsys.readouterr().err

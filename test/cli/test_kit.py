"""ficap kit: the files it writes and prints (paper size, with or without the STL), the ids of
--model on the sheets and the shell, the plate thickness of the STL."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from ficap_ros.cli.main import main


def test_assembly_sheet_and_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "kit"
    assert main(["kit", "--out", str(out), "--paper", "letter", "--no-stl"]) == 0
    printed = capsys.readouterr().out.split()
    names = {Path(p).name for p in printed}
    assert names == {"ficap_tags_letter.pdf", "ficap_tags_letter_p1.svg", "ficap_tags_letter_p2.svg",
                     "ficap_assembly.png", "ficap_assembly.pdf"}
    png = cv2.imread(str(out / "ficap_assembly.png"), cv2.IMREAD_GRAYSCALE)
    assert png is not None and png.shape[1] > png.shape[0] > 1000  # landscape, 150 dpi
    assert (png < 128).mean() > 0.01
    assert (out / "ficap_assembly.pdf").read_bytes().startswith(b"%PDF")


def test_model_ids_and_shell_thickness_reach_the_files(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from ficap_ros.geometry.cap_model import CapModel, nominal_model

    nominal = nominal_model()
    five = CapModel(nominal.ids[:5], nominal.corners_mm[:5])
    five.save(tmp_path / "five.yaml")
    out = tmp_path / "kit"
    assert main(["kit", "--out", str(out), "--model", str(tmp_path / "five.yaml"),
                 "--shell-thickness-mm", "3"]) == 0
    names = {Path(p).name for p in capsys.readouterr().out.split()}
    assert names == {"ficap_tags_a4.pdf", "ficap_tags_a4_p1.svg", "ficap_assembly.png",
                     "ficap_assembly.pdf", "ficap_shell.stl"}  # a4 by default; five tags: a page
    svg = (out / "ficap_tags_a4_p1.svg").read_text()
    assert {int(i) for i in re.findall(r'data-tag-id="(\d+)"', svg)} == set(five.ids)
    data = (out / "ficap_shell.stl").read_bytes()
    (count,) = struct.unpack("<I", data[80:84])
    assert count == 5 * 12  # a closed box of 12 triangles per plate
    tris = np.frombuffer(data[84:], dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)),
                                                   ("a", "<u2")]))["v"].astype(np.float64)
    for plate in tris.reshape(5, 12, 3, 3):
        vol = np.einsum("ij,ij->i", plate[:, 0], np.cross(plate[:, 1], plate[:, 2])).sum() / 6.0
        assert vol == pytest.approx(40 * 40 * 3.0, rel=0.05)  # 40 mm square, 3 mm thick

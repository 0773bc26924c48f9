"""ficap model: the cap model printed as JSON or YAML, or written with --out; an output it cannot
write is one line."""

from __future__ import annotations

from pathlib import Path

import pytest
from recordings import one_error_line

from ficap_ros.cli.main import main


def test_an_output_in_a_missing_folder_is_one_line(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["model", "--out", str(tmp_path / "nodir" / "m.yaml")]) == 1
    one_error_line(capsys)


def test_the_nominal_model_printed_as_json_and_yaml(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    import json

    import numpy as np

    from ficap_ros.geometry.cap_model import load_model, nominal_model

    nominal = nominal_model()
    assert main(["model"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert json.loads(nominal.to_json()) == data
    assert main(["model", "--yaml"]) == 0
    (tmp_path / "printed.yaml").write_text(capsys.readouterr().out)
    printed = load_model(tmp_path / "printed.yaml")
    assert printed.ids == nominal.ids
    np.testing.assert_allclose(printed.corners_mm, nominal.corners_mm, atol=1e-9)
    with pytest.raises(SystemExit) as exc:
        main(["model", "--json", "--yaml"])
    assert exc.value.code == 2


def test_a_model_file_is_read_and_written(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import numpy as np

    from ficap_ros.geometry.cap_model import CapModel, load_model, nominal_model

    nominal = nominal_model()
    moved = CapModel(nominal.ids, nominal.corners_mm + np.array([0.5, -0.25, 0.0]))
    moved.save(tmp_path / "asbuilt.yaml")
    assert main(["model", "--model", str(tmp_path / "asbuilt.yaml"), "--out",
                 str(tmp_path / "copy.yaml")]) == 0
    assert capsys.readouterr().out == ""
    np.testing.assert_allclose(load_model(tmp_path / "copy.yaml").corners_mm, moved.corners_mm,
                               atol=1e-9)
    assert main(["model", "--model", str(tmp_path / "missing.yaml")]) == 1
    assert "missing.yaml" in one_error_line(capsys)

"""The kernels' runtime: where numba caches them, the warm-up that compiles (or loads) every
kernel for the argument types the pipeline passes, so that a frame never compiles one, and the
photometric kernels loaded only for photometric corners."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from corner_eval import drive_frames

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.tools.synth import RenderConfig, default_scene
from ficap_ros.vision import (
    cell_reads,
    fit_kernels,
    jit,
    kernels,
    photometric_kernels,
    pose_kernels,
    uncertainty_kernels,
)
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pipeline import FrameProcessor

ROOT = Path(__file__).resolve().parents[2]
KERNELS = (photometric_kernels.select_pixels, photometric_kernels.fit_steps, kernels.area_steps,
           kernels.line_pass, fit_kernels.boundary_rows, fit_kernels.grouped_normal_equations,
           fit_kernels.grouped_residuals, fit_kernels.grouped_solve, fit_kernels.robust_grouped_solve,
           fit_kernels.edge_fit_round, fit_kernels.edge_fit, fit_kernels.border_unbias,
           fit_kernels.tag_noise_ratios, cell_reads.tag_cell_reads, pose_kernels.reprojection_rt,
           uncertainty_kernels.propagated_terms)


def _cache_dir_in_child(env: dict[str, str], read_only: bool) -> str:
    """``jit.cache_dir()`` in a fresh interpreter (numba reads the variable at import), with the
    package's directory taken as ``read_only`` or writable."""
    code = ("import os; real = os.access\n"
            f"os.access = lambda p, m: (not {read_only}) and real(p, m)\n"
            "from ficap_ros.vision import jit; print(jit.cache_dir())")
    out = subprocess.run([sys.executable, "-c", code], env={**env, "PYTHONPATH": str(ROOT)},
                         capture_output=True, text=True, check=True)
    return out.stdout.strip()


def test_the_cache_goes_to_the_users_directory_where_the_package_is_read_only(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    assert _cache_dir_in_child(env, read_only=True) == str(tmp_path / "xdg" / "ficap_ros" / "numba")
    # Writable (a clone, an editable install): numba's own place, next to the kernels.
    assert _cache_dir_in_child(env, read_only=False) == str(ROOT / "ficap_ros" / "vision" / "__pycache__")
    # The user's choice wins either way.
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")
    assert _cache_dir_in_child(env, read_only=True) == str(tmp_path / "mine")


def test_warm_up_compiles_every_kernel_a_frame_uses() -> None:
    seconds = jit.warm_up()
    assert seconds >= 0.0
    compiled = [len(k.signatures) for k in KERNELS]
    assert all(compiled)
    # Tracked 1080p frames and a searched one, default and photometric corners: no kernel compiles
    # anew.
    frames = drive_frames("1080p", RenderConfig(lighting="low", jpeg_quality=95), n=2)
    camera = default_scene("1080p").camera
    for config in (DetectorConfig(), DetectorConfig(edge_photometric=True)):
        proc = FrameProcessor(nominal_model(), config)
        for k, fr in enumerate(frames):
            result = proc.process(fr.image, camera, k * 33_000_000)
            assert result.pose is not None
        proc_bgr = FrameProcessor(nominal_model(), config, tracking=False)
        proc_bgr.process(np.dstack([frames[0].image] * 3), camera, 0)
    assert [len(k.signatures) for k in KERNELS] == compiled


def test_the_photometric_kernels_load_only_where_the_photometric_fit_runs(
        bag_with_a_corrupt_frame: Path, tmp_path: Path, real_apriltag_dir: Path) -> None:
    """Replay and ``ficap detect`` with ``--no-photometric`` load the corner stage's kernels and
    never the photometric fit's (loading them costs start-up time); ``--photometric`` does."""
    photo = real_apriltag_dir / "apriltags_jl" / "tagtest.jpg"
    code = (
        "import sys\n"
        "from ficap_ros.cli.main import main\n"
        f"assert main(['replay', {str(bag_with_a_corrupt_frame)!r}, '--out', {str(tmp_path / 'out')!r},"
        " '--quiet', '--no-photometric']) == 0\n"
        f"assert main(['detect', '--no-photometric', {str(photo)!r}]) == 0\n"
        "from ficap_ros.vision import kernels\n"
        "print('no-photometric', bool(kernels.line_pass.signatures),"
        " 'ficap_ros.vision.photometric_kernels' in sys.modules)\n"
        f"assert main(['detect', '--photometric', {str(photo)!r}]) == 0\n"
        "print('photometric', 'ficap_ros.vision.photometric_kernels' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": str(ROOT)},
                         capture_output=True, text=True, check=True, cwd=tmp_path)
    said = [line for line in out.stdout.splitlines() if line.startswith(("no-photometric ", "photometric "))]
    assert said == ["no-photometric True False", "photometric True"], out.stderr

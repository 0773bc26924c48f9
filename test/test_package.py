"""The package as a whole: its layering (subpackages stacked bottom up, each importing only from
those below it; only the ROS skin imports rclpy; no private library internals), its dependencies
(package.xml names a rosdep key for every third-party module the package imports, and the pinned
requirements files a pip package for each, so an apt/colcon install and `make` both work), and its
tests mirroring it (ficap_ros/<sub>/<module>.py is tested in test/<sub>/test_<module>.py).
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "ficap_ros"

#: Bottom up. The loose modules (errors, files, process, stamps) are the bottom layer every subpackage uses.
LAYERS = ["", "geometry", "vision", "io", "tools", "ros", "cli"]
#: The loose modules at the top of ficap_ros/ (the bottom layer), besides ``__init__``.
LOOSE = {"errors", "files", "process", "stamps"}


def _layer(path: Path) -> str:
    rel = path.relative_to(PACKAGE)
    return rel.parts[0] if len(rel.parts) > 1 else ""


def _imported_layers(path: Path) -> set[str]:
    out = set()
    for n in ast.walk(ast.parse(path.read_text())):
        names: list[str] = []
        if isinstance(n, ast.ImportFrom) and n.module and n.module.startswith("ficap_ros"):
            names = [n.module + "." + a.name for a in n.names] if n.module == "ficap_ros" else [n.module]
        elif isinstance(n, ast.Import):
            names = [a.name for a in n.names if a.name.startswith("ficap_ros.")]
        for name in names:
            parts = name.split(".")
            out.add(parts[1] if len(parts) > 1 and parts[1] in LAYERS else "")
    return out


def test_subpackages_and_loose_modules() -> None:
    subpackages = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert subpackages == set(LAYERS) - {""}
    loose = {p.stem for p in PACKAGE.glob("*.py")} - {"__init__"}
    assert loose == LOOSE


def test_no_module_imports_a_layer_above_it() -> None:
    upward = []
    for path in sorted(PACKAGE.rglob("*.py")):
        me = LAYERS.index(_layer(path))
        for other in _imported_layers(path):
            if LAYERS.index(other) > me:
                upward.append(f"{path.relative_to(PACKAGE)} imports ficap_ros.{other}")
    assert not upward, upward


def test_only_the_ros_skin_imports_rclpy() -> None:
    for path in sorted(PACKAGE.rglob("*.py")):
        if _layer(path) in ("ros", "cli") and path.stem not in ("live", "live_calibration"):
            continue
        text = path.read_text()
        assert not re.search(r"^\s*(import|from) (rclpy|\w+_msgs|rcl_interfaces)\b", text, re.M), \
            path.relative_to(PACKAGE)


def test_no_private_library_internals() -> None:
    for path in sorted(PACKAGE.rglob("*.py")):
        text = path.read_text()
        assert not re.search(r"_rotation_cy|_minpack|from scipy[.\w]* import _", text), \
            path.relative_to(PACKAGE)


#: Third-party top-level module -> (rosdep key in package.xml or None when optional without one,
#: pip package or None when it is not on PyPI: ``NOT_ON_PYPI`` says how a pip-only machine gets it).
MODULES: dict[str, tuple[str | None, str | None]] = {
    "rclpy": ("rclpy", "ros-jazzy-rclpy"),
    "rcl_interfaces": ("rcl_interfaces", "ros-jazzy-rclpy"),
    "builtin_interfaces": ("builtin_interfaces", "ros-jazzy-rclpy"),
    "sensor_msgs": ("sensor_msgs", "ros-jazzy-common-interfaces"),
    "geometry_msgs": ("geometry_msgs", "ros-jazzy-common-interfaces"),
    "std_msgs": ("std_msgs", "ros-jazzy-common-interfaces"),
    "std_srvs": ("std_srvs", "ros-jazzy-common-interfaces"),
    "diagnostic_msgs": ("diagnostic_msgs", "ros-jazzy-common-interfaces"),
    "visualization_msgs": ("visualization_msgs", "ros-jazzy-common-interfaces"),
    "cv2": ("python3-opencv", "opencv-python-headless"),
    "simplejpeg": ("python3-simplejpeg-pip", "simplejpeg"),
    "numpy": ("python3-numpy", "numpy"),
    "scipy": ("python3-scipy", "scipy"),
    "numba": ("python3-numba", "numba"),
    "yaml": ("python3-yaml", "PyYAML"),
    "matplotlib": ("python3-matplotlib", "matplotlib"),
    "tqdm": ("python3-tqdm", "tqdm"),
    "rosbags": ("python3-rosbags-pip", "rosbags"),
    "mcap": ("mcap-ros2-support", "mcap"),
    # rosbags reads sqlite3 bags with apsw; the salvage reads damaged ones in place with it.
    "apsw": ("python3-rosbags-pip", "rosbags"),
    # Compression codecs of recordings, brought by rosbags and mcap.
    "lz4": ("python3-rosbags-pip", "rosbags"),
    "zstandard": ("python3-rosbags-pip", "rosbags"),
    "backports": ("python3-rosbags-pip", "rosbags"),
    "compression": ("python3-rosbags-pip", "rosbags"),
    "pupil_apriltags": (None, "pupil-apriltags"),
    "ray": (None, "ray"),
    "tf2_ros": ("tf2_ros", None),
    "tf2_msgs": ("tf2_msgs", None),
    "apriltag_msgs": ("apriltag_msgs", None),
    "launch": ("launch", None),
    "launch_ros": ("launch_ros", None),
}
#: Modules not on PyPI, and what a machine whose ROS comes from PyPI does without them.
NOT_ON_PYPI = {
    "tf2_ros": "optional: /tf goes out through tf2_msgs (ficap_ros.ros.tf)",
    "tf2_msgs": "generated by make from ficap_ros/interfaces/tf2_msgs",
    "apriltag_msgs": "generated by make from ficap_ros/interfaces/apriltag_msgs",
    "launch": "the launch files only (test/ros/test_launch.py parses them)",
    "launch_ros": "the launch files only",
}


def _imported_modules() -> set[str]:
    found = set()
    for path in [*(ROOT / "ficap_ros").rglob("*.py"), *(ROOT / "launch").glob("*.py")]:
        for n in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(n, ast.Import):
                names = [a.name for a in n.names]
            elif isinstance(n, ast.ImportFrom) and n.level == 0 and n.module:
                names = [n.module]
            found |= {m.split(".")[0] for m in names}
    return found - set(sys.stdlib_module_names) - {"ficap_ros", "__future__"}


def test_every_import_has_a_rosdep_key_and_a_pinned_pip_package() -> None:
    imported = _imported_modules()
    assert imported <= set(MODULES), f"imports without a mapping: {sorted(imported - set(MODULES))}"
    xml = (ROOT / "package.xml").read_text()
    keys = set(re.findall(r"<(?:exec_)?depend>([^<]+)</(?:exec_)?depend>", xml))
    pinned = set()
    for name in ("requirements.txt", "requirements-extras.txt"):
        pinned |= {line.split("==")[0].strip().lower()
                   for line in (ROOT / name).read_text().splitlines()
                   if "==" in line and not line.lstrip().startswith("#")}
    for module in sorted(imported):
        key, pip = MODULES[module]
        assert key is None or key in keys, f"{module}: package.xml lacks <exec_depend>{key}"
        if pip is None:
            assert module in NOT_ON_PYPI, f"{module}: neither on PyPI nor said how to do without it"
            if "generated by make" in NOT_ON_PYPI[module]:
                assert list((PACKAGE / "interfaces" / module / "msg").glob("*.msg")), module
        else:
            assert pip.lower() in pinned, f"{module}: no pinned {pip} in the requirements files"
    # An optional module without a rosdep key is said so in package.xml.
    for module, (key, pip) in MODULES.items():
        if key is None and module in imported:
            assert pip is not None and pip in xml, f"{module}: package.xml does not name {pip}"


def test_vendored_interfaces_are_no_colcon_package() -> None:
    """ficap_ros/interfaces holds only .msg files with their sources and licences: a COLCON_IGNORE,
    no package.xml or CMakeLists.txt, so a colcon workspace never builds a second tf2_msgs; every
    package's licence is there and named in the README with its source."""
    folder = PACKAGE / "interfaces"
    assert (folder / "COLCON_IGNORE").is_file()
    assert not list(folder.rglob("package.xml")) and not list(folder.rglob("CMakeLists.txt"))
    readme = (folder / "README.md").read_text()
    for pkg in ("tf2_msgs", "apriltag_msgs"):
        assert (folder / pkg / "LICENSE").is_file() and pkg in readme
    assert "github.com/ros2/geometry2" in readme and "github.com/christianrauch/apriltag_msgs" in readme
    # setup.py installs the definitions (labels.mcap's detections are serialised from them).
    assert '"interfaces/*/msg/*.msg"' in (ROOT / "setup.py").read_text()


def test_requirements_are_pinned_exactly() -> None:
    """Every requirement line of every requirements file pins one version (``==``)."""
    for path in sorted(ROOT.glob("requirements*.txt")):
        for line in path.read_text().splitlines():
            line = line.split("#")[0].strip()
            assert not line or re.fullmatch(r"[A-Za-z0-9_.\-]+==[A-Za-z0-9_.+\-]+", line), (path.name, line)


def test_conftest_keeps_the_callers_ros_domain(tmp_path: Path) -> None:
    """test/conftest.py offsets a ROS_DOMAIN_ID the caller set by the xdist worker's number, and
    starts at 60 without one: a robot's own domain is never overwritten with a fixed one."""
    import os
    import subprocess

    code = ("import os, runpy, sys; sys.path.insert(0, 'test/helpers'); "
            "runpy.run_path('test/conftest.py'); print(os.environ['ROS_DOMAIN_ID'])")
    for caller, worker, want in (("37", "gw0", "37"), ("37", "gw1", "38"), ("", "gw1", "61")):
        env = {k: v for k, v in os.environ.items() if k not in ("ROS_DOMAIN_ID",)}
        env.update(PYTEST_XDIST_WORKER=worker, **({"ROS_DOMAIN_ID": caller} if caller else {}))
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True,
                             text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        assert out.stdout.split()[-1] == want, (caller, worker, out.stdout)


# -- the tests mirror the package ------------------------------------------------------------------
TESTS = ROOT / "test"
#: Test modules that mirror no module of ficap_ros, and why (at most three).
UNMIRRORED = {
    "test_package.py": "the package as a whole: its layers, dependencies and tests",
    "test_bad_inputs.py": "bad inputs cross every reader and verb, and one corpus serves them all",
    "ros/test_launch.py": "the launch files (launch/*.launch.py) are no module of ficap_ros",
}


def _test_module_of(module: Path) -> str:
    """ficap_ros/<sub>/<name>.py -> <sub>/test_<name>.py (relative to test/)."""
    rel = module.relative_to(PACKAGE)
    return str(rel.with_name(f"test_{rel.name}"))


def _modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if p.stem not in ("__init__", "__main__"))


def test_every_module_has_its_test_module() -> None:
    missing = [_test_module_of(m) for m in _modules() if not (TESTS / _test_module_of(m)).is_file()]
    assert not missing, f"modules without their test module: {missing}"


def test_every_test_module_mirrors_a_module_or_is_a_stated_exception() -> None:
    assert len(UNMIRRORED) <= 3
    mirrors = {_test_module_of(m) for m in _modules()}
    found = {str(p.relative_to(TESTS)) for p in TESTS.rglob("test_*.py")}
    stray = sorted(found - mirrors - set(UNMIRRORED))
    assert not stray, f"test modules that mirror no module: {stray}"
    assert set(UNMIRRORED) <= found  # an exception that is gone is no exception
    assert not list((TESTS / "helpers").glob("test_*.py"))  # helpers hold no tests

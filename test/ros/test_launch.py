"""The launch files: launch and launch_ros are not on PyPI, so they cannot run here. Each file is
parsed, and every parameter and remapping its ``Node`` actions name is checked against a real
``FicapNode`` (its declared parameters, the topics it subscribes and publishes), every launch
argument it uses against those it declares, and the params file it points at against the repo."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context

from ficap_ros.io.camera_info import camera_info_beside
from ficap_ros.ros.node import FicapNode
from ficap_ros.ros.params import PARAMETERS, validate_parameter
from ficap_ros.ros.params import frames_reason as _frames_reason

ROOT = Path(__file__).resolve().parents[2]
LAUNCH_FILES = sorted((ROOT / "launch").glob("*.launch.py"))


def _call_name(node: ast.AST) -> str:
    if isinstance(node, ast.Call):
        f = node.func
        return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
    return ""


def _kwarg(call: ast.Call, name: str) -> ast.AST | None:
    return next((k.value for k in call.keywords if k.arg == name), None)


def _literals(tree: ast.Module) -> dict[str, object]:
    """Module-level constant assignments (the two-camera table)."""
    out = {}
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign) and len(stmt.targets) == 1 and isinstance(stmt.targets[0], ast.Name):
            try:
                out[stmt.targets[0].id] = ast.literal_eval(stmt.value)
            except ValueError:
                pass
    return out


@pytest.fixture(scope="module")
def node_interface() -> tuple[set[str], set[str]]:
    """(declared parameter names, relative topic names) of a real node with default parameters."""
    context = Context()
    rclpy.init(context=context)
    try:
        node = FicapNode(context=context)
        try:
            params = set(node._parameters)
            topics = {s.topic_name.lstrip("/") for s in node.subscriptions}
            topics |= {p.topic_name.lstrip("/") for p in node.publishers}
            # image_transport 'compressed' subscribes to <image>/compressed (same remap source).
            topics.add("image/compressed")
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    return params, topics


def test_launch_files_exist_and_are_installed() -> None:
    names = {p.name for p in LAUNCH_FILES}
    assert {"ficap.launch.py", "ficap_two_cameras.launch.py"} <= names
    setup = ast.parse((ROOT / "setup.py").read_text())
    strings = {n.value for n in ast.walk(setup) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    assert "launch/*.launch.py" in strings  # data_files glob into share/ficap_ros/launch


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_names_only_what_the_node_has(path: Path, node_interface) -> None:
    declared_params, topics = node_interface
    source = path.read_text()
    tree = ast.parse(source, filename=str(path))
    compile(tree, str(path), "exec")
    assert any(isinstance(s, ast.FunctionDef) and s.name == "generate_launch_description"
               for s in tree.body)
    literals = _literals(tree)
    declared_args = {c.args[0].value for c in ast.walk(tree)
                     if _call_name(c) == "DeclareLaunchArgument" and isinstance(c.args[0], ast.Constant)}
    used_args = {c.args[0].value for c in ast.walk(tree)
                 if _call_name(c) == "LaunchConfiguration" and isinstance(c.args[0], ast.Constant)}
    assert used_args <= declared_args, f"undeclared launch arguments {used_args - declared_args}"

    nodes = [c for c in ast.walk(tree) if _call_name(c) == "Node"]
    assert nodes
    for call in nodes:
        assert ast.literal_eval(_kwarg(call, "package")) == "ficap_ros"
        assert ast.literal_eval(_kwarg(call, "executable")) == "ficap_node"
        params = _kwarg(call, "parameters")
        assert isinstance(params, ast.List)
        files = [e for e in params.elts if not isinstance(e, ast.Dict)]
        assert files, "the params file is passed"
        for d in (e for e in params.elts if isinstance(e, ast.Dict)):
            values: dict[str, object] = {}
            from_table = set()
            for k, v in zip(d.keys, d.values):
                assert isinstance(k, ast.Constant)
                assert k.value in declared_params, f"{path.name}: unknown parameter {k.value}"
                if isinstance(v, ast.Name) and v.id not in literals:
                    from_table.add(k.value)  # a loop variable: the table's rows are checked below
                    continue
                try:
                    values[k.value] = ast.literal_eval(v)
                except ValueError:
                    continue  # a substitution, resolved by launch
                assert validate_parameter(k.value, values[k.value]) == "", (k.value, values[k.value])
            if "camera_mount" not in from_table:
                full = {p.name: p.default for p in PARAMETERS} | values
                assert _frames_reason(full) == ""
        remaps = _kwarg(call, "remappings")
        assert isinstance(remaps, ast.List) and remaps.elts
        for pair in remaps.elts:
            assert isinstance(pair, ast.Tuple) and isinstance(pair.elts[0], ast.Constant)
            assert pair.elts[0].value in topics, f"{path.name}: remaps unknown topic {pair.elts[0].value}"
    # The params file the defaults point at exists in the package.
    for c in ast.walk(tree):
        if _call_name(c) == "PathJoinSubstitution":
            parts = [e.value for e in c.args[0].elts if isinstance(e, ast.Constant)]
            assert (ROOT.joinpath(*parts)).is_file(), parts
    # The two-camera table: each row's mount is a valid camera_mount in base_link; its CameraInfo
    # is found beside the image, in the camera's namespace.
    for row in literals.get("CAMERAS", ()):
        namespace, image, mount = row
        assert validate_parameter("camera_mount", mount) == ""
        assert _frames_reason({"output_frame": "base_link", "camera_mount": mount}) == ""
        assert camera_info_beside(image) == f"/{namespace}/camera_info"

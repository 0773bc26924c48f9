"""The package's layering (README 'Layout'): no module imports one above it, and the README's
table lists every module."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Bottom up, as in README's Layout section.
LAYERS = [
    ["errors", "stamps", "native_log", "mailbox"],
    ["files", "transform", "metrics"],
    ["image_codec", "bag_salvage"],
    ["camera", "cap_model"],
    ["calibration", "messages"],
    ["photometric"],
    ["detection", "bag_io"],
    ["bag_writer"],
    ["pose"],
    ["tracking"],
    ["pipeline"],
    ["report"],
    ["live"],
    ["labels", "synth", "model_build", "kit"],
    ["replay", "evaluation"],
    ["fleet"],
    ["ros_msgs", "ros_params"],
    ["node"],
    ["ros_demo"],
    ["cli", "commands"],
]
#: (importer, imported) pairs allowed to break the layering: none.
EXCEPTIONS: set[tuple[str, str]] = set()


def _imports(path: Path) -> set[str]:
    out = set()
    for n in ast.walk(ast.parse(path.read_text())):
        if isinstance(n, ast.ImportFrom) and n.module and n.module.startswith("ficap_ros"):
            parts = n.module.split(".")
            out |= {a.name for a in n.names} if len(parts) == 1 else {parts[1]}
        elif isinstance(n, ast.Import):
            out |= {a.name.split(".")[1] for a in n.names if a.name.startswith("ficap_ros.")}
    return out


def test_no_module_imports_one_above_it() -> None:
    level = {m: i for i, row in enumerate(LAYERS) for m in row}
    modules = {p.stem for p in (ROOT / "ficap_ros").glob("*.py")} - {"__init__"}
    assert modules | {"commands"} == set(level), "a module missing from LAYERS (or gone)"
    upward = []
    for path in sorted((ROOT / "ficap_ros").rglob("*.py")):
        me = "commands" if path.parent.name == "commands" else path.stem
        if me == "__init__":
            continue
        for other in _imports(path) & set(level):
            if other != me and level[other] >= level[me] and me != "commands" \
                    and (me, other) not in EXCEPTIONS:
                upward.append(f"{path.name} imports {other}")
    assert not upward, upward


def test_readme_layout_lists_every_module() -> None:
    text = (ROOT / "README.md").read_text()
    block = text[text.index("## Layout"):]
    block = block[:block.index("\n## ", 5)]
    listed = set(re.findall(r"\b([a-z_]+)\.py\b", block))
    modules = {p.stem for p in (ROOT / "ficap_ros").glob("*.py")} - {"__init__"}
    assert modules <= listed, sorted(modules - listed)


def test_only_the_ros_skin_imports_rclpy() -> None:
    for path in sorted((ROOT / "ficap_ros").rglob("*.py")):
        if path.name == "node.py" or path.name.startswith("ros_"):
            continue
        text = path.read_text()
        assert not re.search(r"^\s*(import|from) rclpy\b", text, re.M), path.name

"""The package's layers: imports only point down, and ROS stays in the shells.

Layers (``rsvo_ros/__init__.py``): core <- twoview <- odometry; core <- sim; the ROS shells
(``ros``) may use every layer below them; the tools may use everything, the ROS shells' bag I/O
included; nothing imports the tools.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from conftest import REPO_ROOT

PACKAGE = REPO_ROOT / "rsvo_ros"
# what each layer may import from the package (besides itself)
ALLOWED = {
    "core": set(),
    "twoview": {"core"},
    "odometry": {"core", "twoview"},
    "sim": {"core"},
    "ros": {"core", "twoview", "odometry", "sim"},
    "tools": {"core", "twoview", "odometry", "sim", "ros"},
}
ROS_ONLY = ("rclpy", "rosbags", "rcl_interfaces", "builtin_interfaces")  # and every *_msgs/_srvs
# inside the two-view estimator, each module uses only the ones below it
TWOVIEW_ORDER = ["estimator", "search", "essential", "solver", "kernels", "state", "options"]


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append(node.module)
            out += [f"{node.module}.{a.name}" for a in node.names]
    return out


def _modules():
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def test_every_module_belongs_to_a_layer():
    loose = [p.name for p in PACKAGE.glob("*.py")]
    assert sorted(loose) == ["__init__.py", "estimation.py"]  # the contract's import path
    assert {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"} \
        == set(ALLOWED)


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_down_the_layers(path):
    rel = path.relative_to(PACKAGE)
    layer = rel.parts[0] if len(rel.parts) > 1 else None
    for name in _imports(path):
        top = name.split(".")[0]
        if layer not in (None, "ros", "tools"):
            assert top not in ROS_ONLY and not top.endswith(("_msgs", "_srvs")), \
                f"{rel} imports {name}: only rsvo_ros.ros and rsvo_ros.tools may use ROS"
        if top != "rsvo_ros" or len(name.split(".")) < 2 or layer is None:
            continue
        target = name.split(".")[1]
        if target in ALLOWED and target != layer:
            assert target in ALLOWED[layer], f"{rel} imports {name}: {layer} may not use {target}"


def test_two_view_modules_call_only_down():
    for i, module in enumerate(TWOVIEW_ORDER):
        below = set(TWOVIEW_ORDER[i + 1:])
        for name in _imports(PACKAGE / "twoview" / f"{module}.py"):
            parts = name.split(".")
            if parts[:2] == ["rsvo_ros", "twoview"] and len(parts) > 2 \
                    and parts[2] in TWOVIEW_ORDER:
                assert parts[2] in below, f"twoview.{module} imports {name}"
    # the numpy reference model is for the tests: nothing at run time imports it
    for path in _modules():
        assert not any(n.startswith("rsvo_ros.twoview.reference") for n in _imports(path)), path


def test_contract_import_path_and_console_scripts():
    from rsvo_ros.estimation import estimate_relative_pose, warm_up  # noqa: F401

    setup = (REPO_ROOT / "setup.py").read_text()
    for script in ("rsvo_node", "rsvo_replay", "rsvo_synth", "rsvo_bench", "rsvo_play"):
        assert f'"{script} = rsvo_ros.' in setup

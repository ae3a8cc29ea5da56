"""The core never imports rclpy or message packages (it must run and test without ROS)."""

import ast
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parent.parent / 'terrain_perception'


def _imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module


@pytest.mark.parametrize('path', sorted(CORE.rglob('*.py')), ids=lambda p: str(p.relative_to(CORE)))
def test_core_module_imports_no_ros(path):
    bad = [m for m in _imports(path)
           if m.split('.')[0] in ('rclpy', 'terrain_ros', 'rosidl_runtime_py')
           or m.split('.')[0].endswith('_msgs')]
    assert not bad, f'{path.name} imports {bad}: the core must stay ROS-free'

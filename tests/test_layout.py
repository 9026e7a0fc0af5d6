"""The layout rules of DESIGN.md, enforced: the pure core does no I/O, shared/ imports no side."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
IO_MODULES = {"zenoh", "msgpack", "matplotlib", "rich", "json", "gzip", "pickle", "socket", "time"}
PURE = sorted((ROOT / "robot_agent" / "slam").glob("*.py")) + [
    p
    for p in (
        ROOT / "robot_agent" / "explore.py",
        ROOT / "map_server" / "alignment.py",
        ROOT / "map_server" / "candidates.py",
        ROOT / "map_server" / "fleet.py",
        ROOT / "map_server" / "fusion.py",
        ROOT / "map_server" / "registration.py",
        ROOT / "map_server" / "state.py",
    )
    if p.exists()
]


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module.split(".")[0])
    return names


def called_names(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    return {n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}


@pytest.mark.parametrize("path", PURE, ids=lambda p: p.name)
def test_pure_core_has_no_io(path):
    assert not imported_modules(path) & IO_MODULES
    assert not called_names(path) & {"open", "print", "input"}
    assert "np.random.default_rng" not in path.read_text()  # randomness is passed in
    assert "np.random.seed" not in path.read_text()


def test_pure_modules_found():
    assert len(PURE) >= 10


def test_shared_imports_no_side_and_server_no_agent():
    for path in (ROOT / "shared").glob("*.py"):
        assert not imported_modules(path) & {"robot_agent", "map_server", "fleet_slam"}, path
    for path in (ROOT / "map_server").glob("*.py"):
        assert "robot_agent" not in imported_modules(path), path

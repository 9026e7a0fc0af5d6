"""The layout rules of docs/design.md, enforced on the import graph at any depth (tests/import_graph.py):
the pure core reaches no I/O, shared/ imports no side, map_server and robot_agent not each other."""

from pathlib import Path

import pytest

from tests.import_graph import ImportGraph, UnresolvedImport

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("robot_agent", "map_server", "shared", "fleet_slam")
GRAPH = ImportGraph(ROOT, PACKAGES)

IO_LIBRARIES = {
    "zenoh", "msgpack", "matplotlib", "rich", "json", "gzip", "pickle",  # wire, files, plots, console
    "os", "sys", "io", "pathlib", "shutil", "tempfile", "subprocess", "signal", "resource",  # files, OS
    "zipfile", "tarfile", "bz2", "lzma", "csv", "sqlite3", "shelve",
    "socket", "select", "selectors", "asyncio", "http", "urllib", "multiprocessing",  # network, processes
    "time", "datetime",  # the clock is an argument
    "random", "uuid", "secrets",  # randomness is a np.random.Generator argument
    "importlib",  # an import by computed name would hide from this test
}  # fmt: skip
# logging is not in the list: map_server/fleet.py logs why it refused a robot; where the records
# go is the driver's choice (server.py / service.py configure the handlers).
IO_CALLS = {
    "open", "print", "input",  # builtins
    "loadtxt", "savetxt", "genfromtxt", "fromfile", "tofile", "load", "save", "savez",  # numpy files
    "savez_compressed", "savefig", "read_text", "write_text", "read_bytes", "write_bytes",
}  # fmt: skip
# Project modules that do I/O, decided by reading each module of shared/ (the only package both
# sides import); a pure module may not reach one at any depth:
IO_MODULES = {
    "shared.bus",  # the zenoh user: sessions, a router, signal handlers, a JSON5 config file
    "shared.codec",  # the msgpack user: bytes on the wire
    "shared.viz",  # draws with matplotlib, writes SVG / PNG / GeoJSON files
    "shared.metrics",  # reads and writes relations, pose and TUM files (open, np.loadtxt/savetxt)
    "shared.memory",  # reads /proc, calls the C library's malloc_trim (ctypes)
    "shared.entry",  # a command's errors printed to standard error (print, sys)
}
# Read and found pure: shared.chunks (splits and reassembles messages in memory; its threading.Lock
# only guards the Assembler's state — no bytes, no file, no clock), shared.messages, shared.keys,
# shared.geometry, shared.matching, shared.occupancy.
PURE = [
    *sorted(n for n in GRAPH.modules if n.startswith("robot_agent.slam.")),
    "robot_agent.explore",
    "robot_agent.freespace",
    "shared.occupancy",
    "map_server.alignment",
    "map_server.candidates",
    "map_server.config",
    "map_server.contradiction",
    "map_server.fleet",
    "map_server.freespace",
    "map_server.fusion",
    "map_server.incremental",
    "map_server.placing",
    "map_server.policy",
    "map_server.posegraph",
    "map_server.registration",
    "map_server.schedule",
    "map_server.state",
]


def modules_of(package: str) -> list[str]:
    """The modules of ``package`` (its entry point ``__main__`` too), sorted."""
    return sorted(n for n in GRAPH.modules if n.split(".")[0] == package)


def assert_pure(graph: ImportGraph, name: str) -> None:
    problems = graph.io_violations(name, IO_LIBRARIES, IO_CALLS, IO_MODULES)
    for dep in graph.reach(name):  # randomness is passed in, at any depth too
        text = graph.modules[dep].path.read_text()
        problems += [f"{dep}: uses {s}" for s in ("np.random.default_rng", "np.random.seed") if s in text]
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("name", PURE)
def test_pure_core_reaches_no_io(name):
    assert name in GRAPH.modules
    assert_pure(GRAPH, name)


def test_pure_modules_found():
    assert len(PURE) >= 20
    assert all(n in GRAPH.modules for n in PURE)


def test_the_listed_io_modules_are_the_shared_modules_that_do_io():
    """The list above stays true: every shared module that imports an I/O library or makes an
    I/O call is listed, and every listed one does."""
    doing_io = {
        n for n in GRAPH.modules if n.startswith("shared.") and GRAPH.io_use(n, IO_LIBRARIES, IO_CALLS)
    }
    assert doing_io == IO_MODULES


@pytest.mark.parametrize("name", modules_of("shared"))
def test_shared_imports_no_side(name):
    assert not GRAPH.forbidden(name, ("robot_agent", "map_server", "fleet_slam"))


@pytest.mark.parametrize("name", modules_of("map_server"))
def test_map_server_never_imports_robot_agent(name):
    chains = GRAPH.forbidden(name, ("robot_agent",))
    assert not chains, "\n".join(chains)


@pytest.mark.parametrize("name", modules_of("robot_agent"))
def test_robot_agent_never_imports_map_server(name):
    chains = GRAPH.forbidden(name, ("map_server",))
    assert not chains, "\n".join(chains)


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycles(package):
    """No two modules of a package import each other, at any depth and in any form (a
    ``TYPE_CHECKING`` or function-level import too): the map server's configuration lives in
    map_server/config.py so that the modules configured by it need not import each other; the
    simulated worlds' ``builtin_world`` in worlds.py (it imported worlds.py, which imports
    world.py); the fused map's file writers in fleet_slam/export.py (subscribe and export imported
    each other). A package ``__init__`` re-exporting its submodules is no cycle (import_graph)."""
    assert GRAPH.cycles(package) == []


def test_the_cycle_finder_finds_cycles(tmp_path):
    for rel, text in {
        "pkg/__init__.py": "",
        "pkg/a.py": "from pkg import b\n",
        "pkg/b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.c import X\n",
        "pkg/c.py": "import pkg.a\n",
        "pkg/d.py": "from pkg import a\n",
        "pkg/sub/__init__.py": "from pkg.sub.e import E\n",  # a package re-exporting its module ...
        "pkg/sub/e.py": "E = 1\n",
        "pkg/sub/f.py": "from pkg.sub import E\n",  # ... and a sibling importing the package: no cycle
    }.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    assert ImportGraph(tmp_path, ("pkg",)).cycles("pkg") == [["pkg.a", "pkg.b", "pkg.c"]]


# --- the checker finds what it must: a synthetic package with one violation of each kind ---------

SYNTHETIC = {
    "pkg/__init__.py": "",
    "pkg/core/__init__.py": "",
    # from x import y, y a submodule; zenoh two levels below it
    "pkg/core/deep.py": "import numpy as np\nfrom pkg.helpers import mid\n",
    "pkg/helpers/__init__.py": "",
    "pkg/helpers/mid.py": "import pkg.helpers.low as low\n",
    "pkg/helpers/low.py": "import zenoh\n",
    # relative imports, one and two levels up
    "pkg/core/rel.py": "from . import sibling\n",
    "pkg/core/sibling.py": "import json\n",
    "pkg/core/rel_up.py": "from ..helpers.low import session\n",
    # an I/O module of the project, imported inside a function
    "pkg/core/lazy.py": "def f():\n    from pkg.io import bus\n    return bus\n",
    "pkg/io/__init__.py": "",
    "pkg/io/bus.py": "HANDLE = None\n",
    # an I/O call and a computed-name import
    "pkg/core/printer.py": "from pkg.core import quiet\n",
    "pkg/core/quiet.py": "def f(x):\n    print(x)\n",
    "pkg/core/dyn.py": "import importlib\nm = importlib.import_module('pkg.helpers.mid')\n",
    "pkg/core/clean.py": "import numpy as np\nfrom pkg.core import sibling_free\n",
    "pkg/core/sibling_free.py": "from dataclasses import dataclass\n",
    # layering: left reaches right at depth two, inside a function
    "left/__init__.py": "",
    "left/a.py": "from left import b\n",
    "left/b.py": "def f():\n    import right.c\n",
    "right/__init__.py": "",
    "right/c.py": "",
}


@pytest.fixture
def synthetic(tmp_path):
    for rel, text in SYNTHETIC.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    return ImportGraph(tmp_path, ("pkg", "left", "right"))


def io(graph, name):
    return graph.io_violations(name, IO_LIBRARIES, IO_CALLS, {"pkg.io.bus"})


def test_checker_follows_submodule_imports_to_depth(synthetic):
    assert io(synthetic, "pkg.core.deep") == [
        "pkg.core.deep -> pkg.helpers.mid -> pkg.helpers.low: imports zenoh"
    ]
    with pytest.raises(AssertionError, match="imports zenoh"):
        assert_pure(synthetic, "pkg.core.deep")


def test_checker_resolves_relative_imports(synthetic):
    assert io(synthetic, "pkg.core.rel") == ["pkg.core.rel -> pkg.core.sibling: imports json"]
    assert io(synthetic, "pkg.core.rel_up") == ["pkg.core.rel_up -> pkg.helpers.low: imports zenoh"]


def test_checker_sees_function_level_imports_of_io_modules(synthetic):
    assert io(synthetic, "pkg.core.lazy") == ["pkg.core.lazy -> pkg.io.bus: is an I/O module of the project"]


def test_checker_sees_io_calls_and_computed_imports(synthetic):
    assert io(synthetic, "pkg.core.printer") == ["pkg.core.printer -> pkg.core.quiet: calls print()"]
    assert io(synthetic, "pkg.core.dyn") == [
        "pkg.core.dyn: imports importlib",
        "pkg.core.dyn -> pkg.helpers.mid -> pkg.helpers.low: imports zenoh",
    ]


def test_checker_passes_a_clean_module_and_finds_forbidden_sides(synthetic):
    assert io(synthetic, "pkg.core.clean") == []
    assert set(synthetic.reach("pkg.core.clean")) == {
        "pkg",
        "pkg.core",
        "pkg.core.clean",
        "pkg.core.sibling_free",
    }
    assert synthetic.forbidden("left.a", ("right",)) == [
        "left.a -> left.b -> right",
        "left.a -> left.b -> right.c",
    ]
    assert synthetic.forbidden("right.c", ("left",)) == []


def test_checker_refuses_imports_it_cannot_resolve(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("from pkg import nothing\nimport pkg.missing\n")
    with pytest.raises(UnresolvedImport, match=r"pkg\.missing"):
        ImportGraph(tmp_path, ("pkg",))
    (tmp_path / "pkg" / "a.py").write_text("from ... import x\n")
    with pytest.raises(UnresolvedImport, match="beyond the top"):
        ImportGraph(tmp_path, ("pkg",))

"""The project's import graph, read from the source (``ast``, nothing is imported).

Every import statement counts wherever it stands: at the top, inside a function, under
``if TYPE_CHECKING:`` or in a ``try`` — the layout rules are about what a module *may* pull in,
not about what one run happens to execute. An import of a project module is followed:
``import a.b.c`` and ``from a.b import c`` load ``a`` and ``a.b`` (their ``__init__``), and ``c``
too when it is a submodule; relative imports are resolved against the importing module's
package; ``importlib.import_module("x")`` / ``__import__("x")`` with a literal name count as
``import x``. A module also depends on its own parent packages (importing it runs them).
Anything else is an external library, known by its top-level name.
"""

from __future__ import annotations

import ast
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

DYNAMIC_IMPORTS = {"import_module", "__import__"}


class UnresolvedImport(ValueError):
    """A project import that names no module of the project (or climbs out of it)."""


@dataclass
class Module:
    name: str  # dotted
    path: Path
    is_package: bool
    tree: ast.Module
    project: set[str] = field(default_factory=set)  # project modules it imports directly
    named: set[str] = field(default_factory=set)  # those an import statement names (no implicit parents)
    external: set[str] = field(default_factory=set)  # top-level names of the other imports

    def calls(self) -> set[str]:
        """Names called as ``f(...)`` or ``x.f(...)`` (``f`` either way)."""
        out = set()
        for n in ast.walk(self.tree):
            if isinstance(n, ast.Call):
                if isinstance(n.func, ast.Name):
                    out.add(n.func.id)
                elif isinstance(n.func, ast.Attribute):
                    out.add(n.func.attr)
        return out


def _parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


class ImportGraph:
    """Modules of ``packages`` (top-level package directories under ``root``) and their imports."""

    def __init__(self, root: Path, packages: tuple[str, ...]):
        self.root, self.packages = Path(root), tuple(packages)
        self.modules: dict[str, Module] = {}
        for pkg in self.packages:
            for path in sorted((self.root / pkg).rglob("*.py")):
                parts = path.relative_to(self.root).with_suffix("").parts
                is_package = parts[-1] == "__init__"
                name = ".".join(parts[:-1] if is_package else parts)
                self.modules[name] = Module(name, path, is_package, ast.parse(path.read_text(), str(path)))
        for m in self.modules.values():
            self._read_imports(m)

    def is_project(self, name: str) -> bool:
        return name.split(".")[0] in self.packages

    def _add(self, m: Module, target: str, line: int, submodules: tuple[str, ...] = ()) -> None:
        if not self.is_project(target):
            m.external.add(target.split(".")[0])
            return
        if target not in self.modules:
            raise UnresolvedImport(f"{m.path}:{line}: {target!r} is no module of the project")
        m.project.update(p for p in [*_parents(target), target] if p in self.modules)
        m.project.update(f"{target}.{s}" for s in submodules if f"{target}.{s}" in self.modules)
        subs = {f"{target}.{s}" for s in submodules if f"{target}.{s}" in self.modules}
        # ``from pkg import sub``: the statement names sub; ``from pkg import name``: pkg itself
        m.named.update(subs if subs and len(subs) == len(submodules) else {target, *subs})

    def _read_imports(self, m: Module) -> None:
        m.project.update(p for p in _parents(m.name) if p in self.modules)
        for n in ast.walk(m.tree):
            if isinstance(n, ast.Import):
                for alias in n.names:
                    self._add(m, alias.name, n.lineno)
            elif isinstance(n, ast.ImportFrom):
                base = n.module or ""
                if n.level:
                    pkg = m.name.split(".") if m.is_package else m.name.split(".")[:-1]
                    if n.level - 1 >= len(pkg):
                        raise UnresolvedImport(f"{m.path}:{n.lineno}: relative import beyond the top")
                    pkg = pkg[: len(pkg) - (n.level - 1)]
                    base = ".".join([*pkg, base] if base else pkg)
                self._add(m, base, n.lineno, tuple(a.name for a in n.names))
            elif isinstance(n, ast.Call) and n.args and isinstance(n.args[0], ast.Constant):
                func = n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", None)
                if func in DYNAMIC_IMPORTS and isinstance(n.args[0].value, str):
                    self._add(m, n.args[0].value, n.lineno)

    def reach(self, start: str) -> dict[str, str | None]:
        """Every project module ``start`` imports at any depth (itself included), each mapped to
        the module it was first reached from (breadth first: shortest chains)."""
        parent: dict[str, str | None] = {start: None}
        todo = deque([start])
        while todo:
            name = todo.popleft()
            for dep in sorted(self.modules[name].project):
                if dep not in parent:
                    parent[dep] = name
                    todo.append(dep)
        return parent

    @staticmethod
    def chain(parent: dict[str, str | None], name: str) -> str:
        out = [name]
        while parent[out[-1]] is not None:
            out.append(parent[out[-1]])
        return " -> ".join(reversed(out))

    def cycles(self, package: str) -> list[list[str]]:
        """The import cycles among the modules of ``package``: each a strongly connected set of
        more than one module, sorted. Edges are the modules an import statement names: a package
        ``__init__`` that re-exports its submodules closes no cycle with them (Python runs a
        module's parent packages first, but that is the package's own order), while a submodule
        that imports names from its package — or two modules that import each other — do."""
        names = sorted(n for n in self.modules if n == package or n.startswith(package + "."))
        edges = {n: sorted(d for d in self.modules[n].named if d in names and d != n) for n in names}
        index: dict[str, int] = {}
        low: dict[str, int] = {}
        stack: list[str] = []
        on: set[str] = set()
        out: list[list[str]] = []

        def visit(v: str) -> None:  # Tarjan's strongly connected components (recursive: small graphs)
            index[v] = low[v] = len(index)
            stack.append(v)
            on.add(v)
            for w in edges[v]:
                if w not in index:
                    visit(w)
                    low[v] = min(low[v], low[w])
                elif w in on:
                    low[v] = min(low[v], index[w])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))

        for n in names:
            if n not in index:
                visit(n)
        return sorted(out)

    def forbidden(self, start: str, prefixes: tuple[str, ...]) -> list[str]:
        """Import chains from ``start`` to any project module under one of ``prefixes``."""
        parent = self.reach(start)
        hit = [n for n in parent if n.split(".")[0] in prefixes]
        return [self.chain(parent, n) for n in sorted(hit)]

    def io_use(self, name: str, io_libraries: set[str], io_calls: set[str]) -> list[str]:
        """What makes module ``name`` itself do I/O: libraries it imports, I/O calls it makes."""
        m = self.modules[name]
        return [f"imports {x}" for x in sorted(m.external & io_libraries)] + [
            f"calls {c}()" for c in sorted(m.calls() & io_calls)
        ]

    def io_violations(
        self, start: str, io_libraries: set[str], io_calls: set[str], io_modules: set[str]
    ) -> list[str]:
        """Import chains by which ``start`` reaches I/O at any depth: a module that imports an I/O
        library or makes an I/O call, or a project module listed as doing I/O."""
        parent = self.reach(start)
        out = []
        for name in sorted(parent):
            why = self.io_use(name, io_libraries, io_calls)
            if name in io_modules:
                why.append("is an I/O module of the project")
            out += [f"{self.chain(parent, name)}: {w}" for w in why]
        return out

"""The package's layers (docs/architecture.md): a package imports only packages of lower layers (and its own
modules), never one beside it or above it; no import cycle between modules; no private name crosses a package
boundary.  Every import counts, those inside functions included, read from the source (nothing is imported)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "lightplane"

#: layer of each package; packages on one layer do not import each other
LAYERS = {
    "version": -1, "core": 0,
    "camera": 1, "stripe": 1, "ellipse": 1,
    "plane": 2, "motion": 2,
    "measure": 3,
    "simulate": 4,
    "evaluate": 5, "plan": 5,
    "report": 6,
    "live": 7,
    "cli": 8,
    "__init__": 9, "__main__": 10,
}
#: optional heavy dependencies: imported inside functions, each in one named module
OPTIONAL = {"dask": {"measure.batch"}, "distributed": {"measure.batch"}, "pyarrow": {"measure.batch", "live.recording"},
            "matplotlib": {"report.plots"},
            "starlette": {"live.server"}, "uvicorn": {"live.server"}, "serial": {"live.hardware"},
            "harvesters": {"live.genicam"}, "gi": {"live.aravis"}}


def _modules() -> dict[str, Path]:
    out = {}
    for p in sorted(SRC.rglob("*.py")):
        rel = p.relative_to(SRC).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__" and len(parts) > 1:
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


MODULES = _modules()


def _package(mod: str) -> str:
    return mod.split(".")[0]


def _imports(mod: str, path: Path):
    """(target module, imported name or None, line, inside a function) for every import of the package."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    in_func: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            in_func.update(id(s) for s in ast.walk(node) if s is not node)
    ispkg = path.name == "__init__.py"
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name == "lightplane" or a.name.startswith("lightplane."):
                    yield a.name.removeprefix("lightplane").lstrip(".") or "__init__", None, node.lineno, \
                        id(node) in in_func
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod.split(".") if mod != "__init__" else []
                if not ispkg:
                    base = base[:-1]
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            elif node.module and (node.module == "lightplane" or node.module.startswith("lightplane.")):
                target = node.module.removeprefix("lightplane").lstrip(".")
            else:
                continue
            for a in node.names:
                sub = f"{target}.{a.name}" if target else a.name
                if sub in MODULES:
                    yield sub, None, node.lineno, id(node) in in_func
                else:
                    yield target or "__init__", a.name, node.lineno, id(node) in in_func


EDGES = [(m, t, name, line, f) for m, p in MODULES.items() for t, name, line, f in _imports(m, p)]


def test_only_packages_at_the_top():
    top = {p.name for p in SRC.glob("*.py")}
    assert top <= {"__init__.py", "__main__.py", "version.py"}, sorted(top)
    assert {_package(m) for m in MODULES} <= set(LAYERS), sorted({_package(m) for m in MODULES} - set(LAYERS))


def test_no_import_runs_up_or_sideways():
    bad = []
    for m, t, name, line, _ in EDGES:
        a, b = _package(m), _package(t)
        if a != b and LAYERS[b] >= LAYERS[a]:
            bad.append(f"{MODULES[m].relative_to(SRC)}:{line} imports lightplane.{t}")
    assert not bad, "\n".join(bad)


def test_no_private_name_crosses_a_package():
    bad = []
    for m, t, name, line, _ in EDGES:
        if _package(m) == _package(t):
            continue
        private_module = any(part.startswith("_") and part not in ("__init__", "__main__") for part in t.split("."))
        if private_module or (name and name.startswith("_") and name != "__version__"):
            bad.append(f"{MODULES[m].relative_to(SRC)}:{line} takes {name or ''} from lightplane.{t}")
    assert not bad, "\n".join(bad)


def test_no_import_cycle():
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for m, t, _, _, _ in EDGES:
        if t in graph and t != m and not _is_ancestor(t, m):
            graph[m].add(t)
    cycles = _cycles(graph)
    assert not cycles, cycles


def _is_ancestor(pkg: str, mod: str) -> bool:
    """A module importing its own package's ``__init__`` is not a cycle that matters (it is loaded first)."""
    return mod.startswith(pkg + ".")


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_imports_at_module_top():
    """The package's own modules are imported at the top of a module, never inside a function."""
    inside = [f"{MODULES[m].relative_to(SRC)}:{line} imports lightplane.{t}" for m, t, _, line, f in EDGES if f]
    assert not inside, "\n".join(inside)


@pytest.mark.parametrize("dependency", sorted(OPTIONAL))
def test_optional_dependency_in_one_place(dependency):
    users = set()
    for m, p in MODULES.items():
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            if any(n == dependency or n.startswith(dependency + ".") for n in names):
                users.add(m)
    assert users <= OPTIONAL[dependency], sorted(users)

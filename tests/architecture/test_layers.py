"""Layers of the import graph (issue 28): `shared/` is the contract and imports no service; no service imports
another. Every import counts, also the late ones inside functions: a late import is still a dependency.

Known exceptions are listed with their reason and fail the test once they are gone, so the list only shrinks."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# (importing module, imported module): why it still stands.
KNOWN: dict[tuple[str, str], str] = {}


def imports_of(path: Path, module: str) -> set[str]:
    """Absolute names of every module `path` (module `module`) imports, at any depth of its code."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                name = ".".join([*base, *([node.module] if node.module else [])])
            else:
                name = node.module or ""
            # `from services import x` imports the module services.x; `from m import f` imports m (the
            # check trims a name to its longest module prefix)
            out.update(f"{name}.{a.name}" for a in node.names)
    return out


def owner(module: str) -> str | None:
    """The layer room of a module: 'shared' or 'services.<name>'; None outside both."""
    parts = module.split(".")
    if parts[0] == "shared":
        return "shared"
    if parts[0] == "services" and len(parts) > 1:
        return f"services.{parts[1]}"
    return None


def violations(root: Path) -> dict[tuple[str, str], str]:
    """(importer, imported) pairs that break the layers, with the rule each breaks."""
    found: dict[tuple[str, str], str] = {}
    for top in ("shared", "services"):
        for path in sorted((root / top).rglob("*.py")):
            rel = path.relative_to(root).with_suffix("")
            module = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
            mine = owner(module)
            for name in imports_of(path, module):
                theirs = owner(name)
                if theirs is None or theirs == mine or not theirs.startswith("services."):
                    continue
                found[(module, _module_part(root, name))] = (
                    "shared/ imports a service" if mine == "shared" else "a service imports another service")
    return found


def _module_part(root: Path, name: str) -> str:
    """`name` trimmed to the longest prefix that is a module or package (drops an imported function's name)."""
    parts = name.split(".")
    while parts:
        p = root.joinpath(*parts)
        if p.with_suffix(".py").exists() or (p / "__init__.py").exists():
            return ".".join(parts)
        parts.pop()
    return name


def test_no_service_imports_another_and_shared_imports_none():
    found = violations(ROOT)
    new = {k: v for k, v in found.items() if k not in KNOWN}
    assert not new, "layer violations:\n" + "\n".join(f"  {a} -> {b}: {why}" for (a, b), why in sorted(new.items()))
    gone = set(KNOWN) - set(found)
    assert not gone, f"known exceptions no longer exist, remove them from KNOWN: {sorted(gone)}"


def test_the_check_sees_late_relative_and_from_package_imports(tmp_path):
    """The check itself: it catches imports inside functions, relative ones and `from services import x`."""
    (tmp_path / "shared").mkdir()
    (tmp_path / "shared" / "__init__.py").write_text("")
    (tmp_path / "shared" / "ok.py").write_text("import json\nfrom shared import other\n")
    (tmp_path / "shared" / "bad.py").write_text("def f():\n    from services.a import x\n")
    for name in ("a", "b"):
        d = tmp_path / "services" / name
        d.mkdir(parents=True)
        (d / "__init__.py").write_text("")
        (d / "x.py").write_text("")
    (tmp_path / "services" / "__init__.py").write_text("")
    (tmp_path / "services" / "a" / "y.py").write_text("from . import x\nfrom services import b\n")
    (tmp_path / "services" / "b" / "z.py").write_text("from ..a.x import thing\nfrom shared.ok import json\n")
    assert violations(tmp_path) == {
        ("shared.bad", "services.a.x"): "shared/ imports a service",
        ("services.a.y", "services.b"): "a service imports another service",
        ("services.b.z", "services.a.x"): "a service imports another service",
    }


def module_graph(root: Path) -> dict[str, set[str]]:
    """module -> the modules of shared/ and services/ it imports (any depth of its code, TYPE_CHECKING too)."""
    modules: dict[str, Path] = {}
    for top in ("shared", "services"):
        for path in sorted((root / top).rglob("*.py")):
            rel = path.relative_to(root).with_suffix("")
            modules[".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)] = path
    graph: dict[str, set[str]] = {}
    for module, path in modules.items():
        targets = {_module_part(root, n) for n in imports_of(path, module)}
        graph[module] = {t for t in targets if t in modules and t != module}
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every import circle: the strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[v] = min(low[v], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_no_import_circles():
    found = circles(module_graph(ROOT))
    assert not found, "import circles:\n" + "\n".join("  " + " <-> ".join(c) for c in found)


def test_the_circle_check_finds_a_circle_through_a_package_and_a_late_import(tmp_path):
    pkg = tmp_path / "services" / "a"
    pkg.mkdir(parents=True)
    (tmp_path / "services" / "__init__.py").write_text("")
    (tmp_path / "shared").mkdir()
    (pkg / "__init__.py").write_text("from services.a import impl\n")
    (pkg / "impl.py").write_text("from services.a.base import register\n")
    (pkg / "base.py").write_text("def make():\n    from services import a\n")
    (pkg / "alone.py").write_text("import services.a.base\n")
    assert circles(module_graph(tmp_path)) == [["services.a", "services.a.base", "services.a.impl"]]

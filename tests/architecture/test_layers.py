"""Layers of the import graph (issue 28): three rooms, each reading alone.

- `shared` (the contract) depends on nothing of the project but itself;
- `services.<name>` (one per service) depends on `shared` and itself: not another service, not the application;
- `aermani` (the application: CLI, launcher, demo, evaluation) may depend on anything.

A dependency is any import, also a late one inside a function, and any string in `shared/` or `services/` that
names another room's module, which is how code reaches a module past the import system: `importlib`,
`find_spec`, `python -m services.<name>`. Such a string is a whole dotted name that resolves to a module
(`"services.sim"`, `"aermani.launcher"`) or an f-string whose constant head names one (`f"services.{name}.cli"`:
some service). `aermani.` also starts the project's logger and schema names (`"aermani.recorder"`,
`f"aermani.{cls.__name__}"`), which name no module and do not count, except as the name handed to an import
function or to `-m`.

Known exceptions are listed with their reason and fail the test once they are gone, so the list only shrinks."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TOPS = ("shared", "services", "aermani")

# (importing module, imported module or string): why it still stands.
KNOWN: dict[tuple[str, str], str] = {}

DOTTED = re.compile(r"^(services|aermani)(\.[A-Za-z_]\w*)+$")
# Calls whose first argument is a module name.
IMPORTERS = {"import_module", "find_spec", "__import__", "run_module", "find_loader"}


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


def _module_names(tree: ast.AST) -> set[int]:
    """ids of the nodes used as a module name: first argument of an import function, the item after `-m`."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and node.args:
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
            if name in IMPORTERS:
                out.add(id(node.args[0]))
        elif isinstance(node, ast.List | ast.Tuple):
            for flag, item in zip(node.elts, node.elts[1:], strict=False):
                if isinstance(flag, ast.Constant) and flag.value == "-m":
                    out.add(id(item))
    return out


def string_refs(root: Path, path: Path) -> set[str]:
    """The strings of `path` that name a module of `services` or `aermani` (module docstring above); an
    f-string is given with `{}` for its placeholders."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    as_module = _module_names(tree)
    in_fstring = {id(v) for node in ast.walk(tree) if isinstance(node, ast.JoinedStr) for v in node.values}
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in in_fstring:
            text = node.value
            if DOTTED.match(text) and (text.startswith("services.") or id(node) in as_module
                                       or _names_a_module(root, text)):
                out.add(text)
        elif isinstance(node, ast.JoinedStr) and node.values:
            head = node.values[0]
            if not (isinstance(head, ast.Constant) and isinstance(head.value, str)):
                continue
            text = "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in node.values)
            named = head.value.rpartition(".")[0]  # the complete dotted parts before the first placeholder
            if head.value.startswith("services.") or (head.value.startswith("aermani.") and (
                    id(node) in as_module or _names_a_module(root, named))):
                out.add(text)
    return out


def _names_a_module(root: Path, name: str) -> bool:
    """Whether a prefix of `name` longer than its top package is a module or package under `root`."""
    parts = name.split(".")
    return any(_is_module(root, parts[:n]) for n in range(2, len(parts) + 1))


def _is_module(root: Path, parts: list[str]) -> bool:
    p = root.joinpath(*parts)
    return p.with_suffix(".py").exists() or (p / "__init__.py").exists()


def owner(module: str) -> str | None:
    """The room of a module: 'shared', 'services.<name>' or 'aermani'; None outside them (third party).
    `services.{}` (a service named at run time) is 'services.*', any service."""
    parts = module.split(".")
    if parts[0] in ("shared", "aermani"):
        return parts[0]
    if parts[0] == "services" and len(parts) > 1:
        return "services.*" if "{" in parts[1] else f"services.{parts[1]}"
    return None


def broken_rule(mine: str, theirs: str) -> str | None:
    """The rule a dependency of room `mine` on room `theirs` breaks, or None when the layers allow it."""
    if mine == "aermani" or theirs == mine or theirs == "shared":
        return None
    who = "shared/" if mine == "shared" else "a service"
    return f"{who} imports the application" if theirs == "aermani" else (
        f"{who} imports a service" if mine == "shared" else "a service imports another service")


def modules(root: Path) -> dict[str, Path]:
    """Every module of the three rooms under `root`, by its dotted name."""
    out: dict[str, Path] = {}
    for top in TOPS:
        for path in sorted((root / top).rglob("*.py")):
            rel = path.relative_to(root).with_suffix("")
            out[".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)] = path
    return out


def violations(root: Path) -> dict[tuple[str, str], str]:
    """(importer, imported module or naming string) pairs that break the layers, with the rule each breaks."""
    found: dict[tuple[str, str], str] = {}
    for module, path in modules(root).items():
        mine = owner(module)
        if mine is None or mine == "aermani":
            continue
        for name in imports_of(path, module):
            theirs = owner(name)
            rule = broken_rule(mine, theirs) if theirs else None
            if rule:
                found[(module, _module_part(root, name))] = rule
        for text in string_refs(root, path):
            theirs = owner(text)
            rule = broken_rule(mine, theirs) if theirs else None
            if rule:
                found[(module, text)] = f"{rule} (named in a string)"
    return found


def _module_part(root: Path, name: str) -> str:
    """`name` trimmed to the longest prefix that is a module or package (drops an imported function's name)."""
    parts = name.split(".")
    while parts:
        if _is_module(root, parts):
            return ".".join(parts)
        parts.pop()
    return name


def test_each_room_imports_only_what_its_layer_allows():
    found = violations(ROOT)
    new = {k: v for k, v in found.items() if k not in KNOWN}
    assert not new, "layer violations:\n" + "\n".join(f"  {a} -> {b}: {why}" for (a, b), why in sorted(new.items()))
    gone = set(KNOWN) - set(found)
    assert not gone, f"known exceptions no longer exist, remove them from KNOWN: {sorted(gone)}"


def _package(root: Path, dotted: str, files: dict[str, str]) -> None:
    """Make package `dotted` under `root` (with every parent package) holding `files` (name -> source)."""
    parts = dotted.split(".")
    d = root.joinpath(*parts)
    d.mkdir(parents=True, exist_ok=True)
    for n in range(1, len(parts) + 1):
        init = root.joinpath(*parts[:n], "__init__.py")
        if not init.exists():
            init.write_text("")
    for name, text in files.items():
        (d / name).write_text(text)


def test_the_check_sees_late_relative_and_from_package_imports(tmp_path):
    """The check itself: it catches imports inside functions, relative ones and `from services import x`."""
    _package(tmp_path, "shared", {"ok.py": "import json\nfrom shared import other\n",
                                  "bad.py": "def f():\n    from services.a import x\n"})
    for name in ("a", "b"):
        _package(tmp_path, f"services.{name}", {"x.py": ""})
    (tmp_path / "services" / "a" / "y.py").write_text("from . import x\nfrom services import b\n")
    (tmp_path / "services" / "b" / "z.py").write_text("from ..a.x import thing\nfrom shared.ok import json\n")
    assert violations(tmp_path) == {
        ("shared.bad", "services.a.x"): "shared/ imports a service",
        ("services.a.y", "services.b"): "a service imports another service",
        ("services.b.z", "services.a.x"): "a service imports another service",
    }


def test_the_check_fails_on_each_kind_of_upward_or_sideways_dependency(tmp_path):
    """One violation of each kind in a made-up tree, each reported; the application's own imports and strings,
    logger and schema names, and a service naming its own modules are not."""
    _package(tmp_path, "shared", {
        "cli.py": "import importlib\n\ndef load(name):\n    return importlib.import_module(f'services.{name}.cli')\n",
        "spec.py": "from importlib.util import find_spec\nHAVE = find_spec('services.a')\n",
        "run.py": "import sys\nCMD = [sys.executable, '-m', 'aermani.app']\n",
        "up.py": "def f():\n    import aermani.app\n",
        "names.py": "import logging\nlog = logging.getLogger('aermani.a')\n\ndef schema(t):\n"
                    "    return f'aermani.{t.__name__}'\n"})
    _package(tmp_path, "services.a", {"x.py": "from services.b import y\n",
                                      "up.py": "from aermani.app import main\n",
                                      "own.py": "WORKER = 'services.a.x'\nLOG = 'aermani.a.x'\n",
                                      "__main__.py": "import importlib\nM = importlib.import_module(f'aermani.{1}')\n"})
    _package(tmp_path, "services.b", {"y.py": "import subprocess\nsubprocess.run(['python', '-m', 'services.a'])\n"})
    _package(tmp_path, "aermani", {"app.py": "import importlib\nfrom services.a import x\n"
                                             "M = importlib.import_module('services.b.y')\n"})
    assert violations(tmp_path) == {
        ("shared.cli", "services.{}.cli"): "shared/ imports a service (named in a string)",
        ("shared.spec", "services.a"): "shared/ imports a service (named in a string)",
        ("shared.run", "aermani.app"): "shared/ imports the application (named in a string)",
        ("shared.up", "aermani.app"): "shared/ imports the application",
        ("services.a.x", "services.b.y"): "a service imports another service",
        ("services.a.up", "aermani.app"): "a service imports the application",
        ("services.a.__main__", "aermani.{}"): "a service imports the application (named in a string)",
        ("services.b.y", "services.a"): "a service imports another service (named in a string)",
    }


def module_graph(root: Path) -> dict[str, set[str]]:
    """module -> the project's modules it imports (any depth of its code, TYPE_CHECKING too), in all rooms."""
    found = modules(root)
    graph: dict[str, set[str]] = {}
    for module, path in found.items():
        targets = {_module_part(root, n) for n in imports_of(path, module)}
        graph[module] = {t for t in targets if t in found and t != module}
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


def test_the_circle_check_covers_the_application(tmp_path):
    _package(tmp_path, "aermani", {"cli.py": "from aermani import demo\n",
                                   "demo.py": "def f():\n    import aermani.cli\n"})
    assert circles(module_graph(tmp_path)) == [["aermani.cli", "aermani.demo"]]

"""The docs cannot rot: every shell command in README.md and docs/*.md is run here or covered by a named test.

Each command in a ```bash / ```sh / ```shell / ```console block must be one of:

(a) run by this test, cheaply: `aermani ...` runs the (sub)command's `--help` and every `--option` the doc uses
    must be in it; `make X` runs `make -n X`; `python benchmarks/X.py ...` runs its `--help` (options checked the
    same way); `python -m shared.keydoc --check` runs; `python -m services.X` must name a service module;
    `pytest ...` must name existing test files, tests and markers;
(b) covered by an existing test named in a marker comment right above the block:
    `<!-- tested-by: tests/gateway/test_fullstack.py::test_full_stack_task_restart_and_abort -->`;
(c) marked as needing what this machine has not: `<!-- needs: hardware -->` (also `model-key`, `docker`, `long`,
    `ros2`: a ROS 2 install).

An unmarked command that is not run fails with its file and line. Markers must name tests that exist. Every
relative link in the docs must point to an existing file (and, for a markdown file, an existing heading).
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import re
import runpy
import shlex
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHELL = {"bash", "sh", "shell", "console"}
NEEDS = {"hardware", "model-key", "docker", "long", "ros2"}
FENCE = re.compile(r"^(\s*)```(\S*)")
MARKER = re.compile(r"<!--\s*(tested-by|needs):\s*(.*?)\s*-->")
ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
OPERATORS = {"&&", "||", ";", "|", "&"}


@dataclass
class Block:
    path: Path
    line: int  # 1-based line of the opening fence
    lines: list[tuple[int, str]]
    tested_by: list[str] = field(default_factory=list)
    needs: list[str] = field(default_factory=list)


@dataclass
class Command:
    block: Block
    line: int
    text: str
    argv: list[str]

    @property
    def where(self) -> str:
        return f"{self.block.path.relative_to(ROOT)}:{self.line}"


def _markers(lines: list[str], fence: int) -> tuple[list[str], list[str]]:
    """tested-by and needs values from the comment lines directly above line index `fence`."""
    tested, needs = [], []
    i = fence - 1
    while i >= 0 and lines[i].strip().startswith("<!--"):
        for kind, value in MARKER.findall(lines[i]):
            items = [v.strip() for v in value.split(",") if v.strip()]
            (tested if kind == "tested-by" else needs).extend(items)
        i -= 1
    return tested, needs


def blocks(path: Path) -> list[Block]:
    """The shell blocks of one markdown file with their markers."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out: list[Block] = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        start, lang = i, m.group(2).lower()
        i += 1
        body = []
        while i < len(lines) and not lines[i].strip().startswith("```"):
            body.append((i + 1, lines[i]))
            i += 1
        i += 1
        if lang in SHELL:
            tested, needs = _markers(lines, start)
            out.append(Block(path, start + 1, body, tested, needs))
    return out


def _strip_comment(text: str) -> str:
    """Drop a shell comment (a `#` at a word start, outside quotes)."""
    quote = ""
    for i, ch in enumerate(text):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or text[i - 1].isspace()):
            return text[:i]
    return text


def commands(block: Block) -> list[Command]:
    """The commands of a block: continuation lines joined, comments dropped, `a && b` split, pipes cut."""
    out: list[Command] = []
    pending, first = "", 0
    for n, raw in block.lines:
        line = _strip_comment(raw[2:] if raw.startswith("$ ") else raw).rstrip()
        if not pending:
            first = n
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        text = (pending + line).strip()
        pending = ""
        if text:
            out += _split(block, first, text)
    return out


def _split(block: Block, line: int, text: str) -> list[Command]:
    lexer = shlex.shlex(re.sub(r"\$\([^)]*\)", "SUBST", text), posix=True, punctuation_chars="|&;")
    lexer.whitespace_split = True
    lexer.commenters = ""
    out: list[Command] = []
    argv: list[str] = []
    skip = False
    for tok in [*lexer, ";"]:
        if tok in OPERATORS:
            if argv and not skip:
                out.append(Command(block, line, text, argv))
            skip = tok == "|"  # what a pipe feeds (jq, tee) is not the documented command
            argv = []
        elif not skip:
            argv.append(tok)
    return out


# ------------------------------------------------------------------------------------------ cheap runs


@functools.cache
def _cli():
    import typer.main

    import aermani.cli as cli

    cli._register_commands()
    return cli.app, typer.main.get_command(cli.app)


@functools.cache
def _cli_help(path: tuple[str, ...]) -> str:
    from typer.testing import CliRunner

    app, _ = _cli()
    res = CliRunner().invoke(app, [*path, "--help"], env={"COLUMNS": "200", "NO_COLOR": "1"})
    assert res.exit_code == 0, f"aermani {' '.join(path)} --help exited {res.exit_code}: {res.output[-500:]}"
    return res.output


def _options(help_text: str) -> set[str]:
    return set(re.findall(r"--[a-z][a-z0-9-]*", help_text))


def _used_options(args: list[str]) -> set[str]:
    return {a.split("=", 1)[0] for a in args if a.startswith("--") and len(a) > 2}


GLOBAL_OPTIONS = {"--client-certs", "--identity"}  # `aermani --client-certs DIR [--identity X] <command> ...`


def check_aermani(args: list[str]) -> None:
    _, cmd = _cli()
    path: list[str] = []
    while args and args[0].split("=", 1)[0] in GLOBAL_OPTIONS:
        assert args[0].split("=", 1)[0] in _options(_cli_help(())), f"aermani has no global option {args[0]}"
        args = args[1:] if "=" in args[0] else args[2:]
    for tok in args:
        if tok.startswith("-"):
            break
        group = getattr(cmd, "commands", None)  # a group (typer ships its own click: no isinstance)
        if group is not None and tok in group:
            cmd = group[tok]
            path.append(tok)
        else:
            assert group is None or path, f"aermani has no sub-command {tok!r}"
            break
    missing = _used_options(args) - _options(_cli_help(tuple(path)))
    assert not missing, f"aermani {' '.join(path)} has no option(s) {sorted(missing)}"


@functools.cache
def _bench_help(script: str) -> str:
    path = ROOT / script
    assert path.is_file(), f"{script} does not exist"
    out, argv = io.StringIO(), sys.argv
    sys.argv = [str(path), "--help"]
    try:
        with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exc:
            runpy.run_path(str(path), run_name="__main__")
    finally:
        sys.argv = argv
    assert exc.value.code in (0, None), f"{script} --help exited {exc.value.code}"
    return out.getvalue()


def check_benchmark(script: str, args: list[str]) -> None:
    missing = _used_options(args) - _options(_bench_help(script))
    assert not missing, f"{script} has no option(s) {sorted(missing)}"


@functools.cache
def _make_n(target: str) -> None:
    res = subprocess.run(["make", "-n", target], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, f"make -n {target}: {res.stderr[-500:]}"


@functools.cache
def _markers_declared() -> set[str]:
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return {m.split(":", 1)[0].strip() for m in cfg["tool"]["pytest"]["ini_options"]["markers"]}


def check_pytest(args: list[str]) -> None:
    for i, a in enumerate(args):
        if a == "-m" and i + 1 < len(args):
            words = set(re.findall(r"[a-z_]+", args[i + 1])) - {"not", "and", "or"}
            assert words <= _markers_declared(), f"unknown marker(s) {sorted(words - _markers_declared())}"
        elif a.startswith("tests"):
            check_test_ref(a)


def check_python(args: list[str]) -> None:
    if args[:2] == ["-m", "shared.keydoc"]:
        from shared import keydoc

        assert keydoc.main(["--check"]) == 0, "python -m shared.keydoc --check: a generated doc is stale"
    elif args[:1] == ["-m"] and args[1].startswith("services."):
        assert (ROOT / args[1].replace(".", "/") / "__main__.py").is_file(), f"no service module {args[1]}"
    elif args[:1] == ["-m"] and args[1] == "pytest":
        check_pytest(args[2:])
    elif args and args[0].startswith("benchmarks/") and args[0].endswith(".py"):
        check_benchmark(args[0], args[1:])
    else:
        raise LookupError


def run_cheap(argv: list[str]) -> bool:
    """Run the cheap form of a command; False when it has none (it then needs a marker)."""
    args = list(argv)
    while args and (ASSIGNMENT.match(args[0]) or args[0] == "sudo"):
        args.pop(0)
    if not args:
        return False
    prog, rest = Path(args[0]).name, args[1:]
    try:
        if prog == "aermani":
            check_aermani(rest)
        elif prog == "make":
            targets = [a for a in rest if not a.startswith("-") and "=" not in a] or ["setup"]
            for t in targets:
                _make_n(t)
        elif prog in ("python", "python3"):
            check_python(rest)
        elif prog == "pytest":
            check_pytest(rest)
        else:
            return False
    except LookupError:
        return False
    return True


def check_test_ref(ref: str) -> None:
    """`tests/x.py`, `tests/x.py::test_y` or a tests directory must exist."""
    file, _, name = ref.partition("::")
    path = ROOT / file
    assert path.exists(), f"{file} does not exist"
    if name:
        name = name.split("[", 1)[0].split("::")[-1]
        assert re.search(rf"^\s*(async\s+)?def {re.escape(name)}\(", path.read_text(), re.M), \
            f"{file} has no test {name}"


# ------------------------------------------------------------------------------------------------ tests

ALL_BLOCKS = [b for p in DOCS for b in blocks(p)]
ALL_COMMANDS = [c for b in ALL_BLOCKS for c in commands(b)]


def test_the_docs_have_commands() -> None:
    assert len(ALL_COMMANDS) > 40 and {c.block.path.name for c in ALL_COMMANDS} >= {"README.md", "quickstart.md"}


@pytest.mark.parametrize("cmd", ALL_COMMANDS, ids=[c.where for c in ALL_COMMANDS])
def test_command_is_run_or_covered(cmd: Command) -> None:
    ran = run_cheap(cmd.argv)
    covered = bool(cmd.block.tested_by or cmd.block.needs)
    assert ran or covered, (f"{cmd.where}: `{cmd.text}` is neither run by tests/docs/test_docs.py nor marked: add "
                            "<!-- tested-by: tests/...::test_x --> or <!-- needs: hardware|model-key|docker|long --> "
                            "right above its block")


@pytest.mark.parametrize("block", [b for b in ALL_BLOCKS if b.tested_by or b.needs],
                         ids=lambda b: f"{b.path.relative_to(ROOT)}:{b.line}")
def test_markers_name_existing_tests_and_known_needs(block: Block) -> None:
    for ref in block.tested_by:
        check_test_ref(ref)
    unknown = set(block.needs) - NEEDS
    assert not unknown, f"unknown needs {sorted(unknown)}; use one of {sorted(NEEDS)}"


def test_the_installed_aermani_command_runs() -> None:
    """The entry point itself (the in-process help checks above share its code, not its installation)."""
    exe = Path(sys.executable).parent / "aermani"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "aermani.cli"]
    res = subprocess.run([*cmd, "--help"], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert res.returncode == 0 and "eval" in res.stdout, res.stderr[-500:]


def test_the_command_parser_splits_and_joins() -> None:
    b = Block(ROOT / "README.md", 1, [(2, "A=1 aermani eval --out x \\"), (3, "    --split dev  # comment"),
                                      (4, "aermani certs init --out c && chown -R 1000 c"),
                                      (5, "curl -s http://x/#a | jq .metrics")])
    got = [(c.line, c.argv) for c in commands(b)]
    assert got == [(2, ["A=1", "aermani", "eval", "--out", "x", "--split", "dev"]),
                   (4, ["aermani", "certs", "init", "--out", "c"]), (4, ["chown", "-R", "1000", "c"]),
                   (5, ["curl", "-s", "http://x/#a"])]
    assert run_cheap(["aermani", "eval", "--split", "dev"])
    assert run_cheap(["aermani", "--client-certs", "certs", "--identity", "ground", "health", "--connect", "tls/x"])
    assert not run_cheap(["curl", "http://127.0.0.1:8080/api/v1/live"])
    with pytest.raises(AssertionError, match="no option"):
        run_cheap(["aermani", "eval", "--no-such-option"])
    with pytest.raises(AssertionError, match="no sub-command"):
        run_cheap(["aermani", "no-such-command"])


# ------------------------------------------------------------------------------------------------ links

LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


@functools.cache
def _anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.S)
    return {_slug(m) for m in re.findall(r"^#{1,6}\s+(.*)$", text, re.M)}


def test_relative_links_resolve() -> None:
    bad = []
    for doc in DOCS:
        text = re.sub(r"```.*?```", "", doc.read_text(encoding="utf-8"), flags=re.S)
        for target in LINK.findall(text):
            if re.match(r"^[a-z]+:", target):
                continue  # http(s), mailto
            file, _, anchor = target.partition("#")
            path = (doc.parent / file).resolve() if file else doc
            if not path.exists():
                bad.append(f"{doc.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
                bad.append(f"{doc.relative_to(ROOT)}: {target} (no heading #{anchor})")
    assert not bad, "\n".join(bad)


# ------------------------------------------------------------------------------- benchmarks and layout


def test_every_benchmark_is_in_run_all_and_its_arguments_exist() -> None:
    sys.path.insert(0, str(ROOT))
    from benchmarks import run_all

    assert set(run_all.discover()) == set(run_all.BENCHMARKS), "benchmarks/run_all.py BENCHMARKS is out of date"
    for name, bench in run_all.BENCHMARKS.items():
        check_benchmark(f"benchmarks/{name}.py", [*bench.args, *bench.quick, "--json"])


def test_foxglove_layout_uses_recorded_channels_and_real_fields() -> None:
    from shared.keys import DECLARATIONS, Topic
    from shared.messages import MESSAGES_BY_SCHEMA

    layout = json.loads((ROOT / "docs" / "foxglove" / "aermani-layout.json").read_text())
    declared = {f"aermani/v1/am1/{d.name}": d for d in DECLARATIONS if isinstance(d, Topic)}
    text = json.dumps(layout)
    topics = set(re.findall(r"aermani/v1/am1/[a-z_/]+", text))
    assert topics and topics <= set(declared), sorted(topics - set(declared))
    paths = re.findall(r"(aermani/v1/am1/[a-z_/]+)((?:\.[a-z_]+)+)", text)
    assert paths, "the layout plots no message field"
    for topic, fields in paths:
        model = declared[topic].type
        assert isinstance(model, type) and f"aermani.{model.__name__}" in MESSAGES_BY_SCHEMA
        for name in fields.strip(".").split("."):
            assert name in model.model_fields, f"{topic}: {model.__name__} has no field {name}"
            ann = model.model_fields[name].annotation
            model = ann if isinstance(ann, type) and hasattr(ann, "model_fields") else model
    panels = {k.split("!")[0] for k in layout["configById"]}
    assert {"Image", "3D", "RawMessages", "Plot"} <= panels


# ------------------------------------------------------------------------------------ extension examples

EXAMPLES = [  # (doc, first line of the python block, registry module, registry name, registered name)
    ("docs/skills.md", "# services/executor/skills/inspect.py", "services.executor.registry", "REGISTRY",
     "descend_to_inspect"),
    ("docs/reasoner.md", "# my_lab/aermani_backend.py", "services.reasoner.backends.base", "BACKENDS", "my_server"),
    ("docs/perception.md", "# services/perception/segmenters/bright.py", "services.perception.segmenters.base",
     "SEGMENTERS", "bright"),
]


@pytest.mark.parametrize(("doc", "head", "module", "registry", "name"), EXAMPLES, ids=[e[4] for e in EXAMPLES])
def test_extension_example_registers(doc: str, head: str, module: str, registry: str, name: str) -> None:
    """The 'add a skill / backend / segmenter' examples run as written and register under their name."""
    import importlib
    import types

    text = (ROOT / doc).read_text(encoding="utf-8")
    m = re.search(rf"```python\n({re.escape(head)}.*?)```", text, re.S)
    assert m, f"{doc}: no python block starting with {head!r}"
    reg = getattr(importlib.import_module(module), registry)
    if module.startswith("services.perception"):
        importlib.import_module("services.perception.segmenters")  # the built-ins first, as the service does
    assert name not in reg
    mod = types.ModuleType(f"docs_example_{name}")
    sys.modules[mod.__name__] = mod
    try:
        exec(compile(m.group(1), f"{doc} example", "exec"), mod.__dict__)  # noqa: S102 - our own docs
        assert name in reg and reg[name].__module__ == mod.__name__
    finally:
        reg.pop(name, None)
        sys.modules.pop(mod.__name__, None)

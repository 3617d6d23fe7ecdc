"""The report's provenance (aermani/evaluation/provenance.py): the commit that froze the test split and the last
change to the policy stack, on a real git history built here, and the files called "not policy" are never
imported by a running service."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from aermani.evaluation.provenance import NOT_POLICY, POLICY_PATHS, source_revision, split_frozen

ENV = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@example.org", "GIT_COMMITTER_NAME": "t",
       "GIT_COMMITTER_EMAIL": "t@example.org"}
SUITE = "aermani/evaluation/suites/search.jsonl"


def _commit(root: Path, message: str, files: dict[str, str]) -> str:
    for path, text in files.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_text(text)
    subprocess.run(["git", "add", "-A"], cwd=root, check=True, env=ENV)
    subprocess.run(["git", "commit", "-qm", message], cwd=root, check=True, env=ENV)
    return subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, check=True, env=ENV, capture_output=True,
                          text=True).stdout.strip()


def _suite(*test_lines: dict) -> str:
    dev = {"split": "dev", "command": "Find the red cup.", "target_object": "red cup"}
    return "\n".join(json.dumps(line) for line in (dev, *test_lines)) + "\n"


def test_the_freeze_and_the_last_policy_change_on_a_real_history(tmp_path: Path) -> None:
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True, env=ENV)
    line = {"split": "test", "command": "Go up a bit and find the banana.", "target_object": "banana"}
    base = _commit(tmp_path, "suites and code", {SUITE: _suite(), "services/reasoner/loop.py": "a\n",
                                                 "services/reasoner/cli.py": "a\n",
                                                 "services/executor/skills/motion.py": "a\n",
                                                 "services/sim/physics.py": "a\n"})
    frozen = _commit(tmp_path, "the test split", {SUITE: _suite(line)})
    rev = source_revision(tmp_path)
    assert rev["split_frozen"] == frozen and rev["policy_changed"] == base
    assert rev["policy_changed_after_freeze"] is False
    loop = _commit(tmp_path, "the loop changes", {"services/reasoner/loop.py": "b\n"})
    rev = source_revision(tmp_path)
    assert rev["policy_changed"] == loop and rev["policy_changed_after_freeze"] is True
    assert rev["policy_changed_subject"] == "the loop changes"
    assert rev["policy_changed_files"] == "services/reasoner/loop.py"
    _commit(tmp_path, "a tool and the simulator", {"services/reasoner/cli.py": "b\n", "services/sim/physics.py": "b\n"})
    assert source_revision(tmp_path)["policy_changed"] == loop  # neither decides an episode on the policy's side
    skill = _commit(tmp_path, "a skill changes", {"services/executor/skills/motion.py": "b\n"})
    assert source_revision(tmp_path)["policy_changed"] == skill
    # Scoring fields on the test line (and a dev line's change) do not move the freeze: same commands, same layouts.
    scored = {**line, "motions": [{"skill": "up"}], "criteria": {"lift_m": 0.05}}
    _commit(tmp_path, "score the motions", {SUITE: _suite(scored).replace("Find the red cup.", "Find the cup.")})
    assert split_frozen(tmp_path) == frozen
    # A changed command does: the split is new, and the skill change came before it.
    refrozen = _commit(tmp_path, "a new test command", {SUITE: _suite({**scored, "command": "Climb, then find it."})})
    rev = source_revision(tmp_path)
    assert rev["split_frozen"] == refrozen and rev["policy_changed_after_freeze"] is False


def test_no_running_service_imports_what_is_called_not_policy() -> None:
    """The services as they run: their service modules, every backend and every skill module loaded."""
    code = """
import importlib, json, pkgutil, sys
import services.executor.skills as sk
import services.reasoner.backends as bk
for svc in ("reasoner", "executor", "perception"):
    importlib.import_module(f"services.{svc}.service")
for pkg in (sk, bk):
    for m in pkgutil.iter_modules(pkg.__path__):
        importlib.import_module(f"{pkg.__name__}.{m.name}")
importlib.import_module("services.reasoner.profiles")
print(json.dumps(sorted(sys.modules)))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[2], env={**os.environ, "PYTHONPATH": "."}, timeout=120)
    loaded = set(json.loads(out.stdout))
    assert "services.executor.skills.motion" in loaded and "services.reasoner.loop" in loaded
    for path in NOT_POLICY:
        assert any(path.startswith(p) for p in POLICY_PATHS), path
        module = path.removesuffix(".py").replace("/", ".")
        assert module not in loaded, f"{path} is imported by a running service: it is policy"


@pytest.mark.parametrize("path", NOT_POLICY)
def test_every_not_policy_file_exists(path: str) -> None:
    assert (Path(__file__).resolve().parents[2] / path).is_file(), path

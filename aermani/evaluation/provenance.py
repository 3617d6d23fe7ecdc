"""Where a run's code comes from: its commit, whether the work tree was dirty, the commit that froze the test split
and the last commit that changed the policy stack (docs/evaluation.md, "Suites and splits")."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SUITE_PATHS = ("aermani/evaluation/suites",)
"""Where the built-in suites live (the split's freezing commit is looked up there)."""
POLICY_PATHS = ("services/reasoner", "services/executor", "services/perception", "shared/skill_library.json")
"""Every file whose change can change an episode's decisions or outcomes on the policy's side: the reasoner (its
loop, the rules baseline and its command reader, the baselines, the prompt, the answer schema and parser, every
backend and its model profiles), the executor (its skills, working memory and settings) and perception (what
the policy sees), and the Skill Library text every model is shown. The simulator (the world and its judge) and
the autopilot bridge are the test bench, not the policy. A change to any of these after the test split froze
is a change the split must not have seen."""
NOT_POLICY = ("services/reasoner/__main__.py", "services/reasoner/cli.py", "services/reasoner/probe.py",
              "services/reasoner/rereason.py", "services/executor/__main__.py", "services/executor/cli.py",
              "services/perception/__main__.py", "services/perception/cli.py")
"""Files under POLICY_PATHS that no running service imports (command-line tools, the endpoint probe, offline
re-reasoning): their changes cannot change an episode (tests/evaluation/test_provenance.py checks that the
services never import them)."""
SCORING_FIELDS = ("motions", "choice", "criteria", "not_found_max_steps")
"""Fields of a suite line that say how an episode is scored, not what is commanded or laid out: adding them to
test lines does not move the split's freeze (the commands and layouts the policy meets are unchanged)."""


def _git(root: Path, *args: str) -> str:
    try:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=30,
                              check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def _policy_pathspec() -> list[str]:
    return [*POLICY_PATHS, *(f":(exclude){p}" for p in NOT_POLICY)]


def _test_lines(root: Path, commit: str) -> frozenset[str]:
    """The test lines of the suites at `commit`, each without its scoring fields, as canonical JSON."""
    out: set[str] = set()
    for path in _git(root, "ls-tree", "-r", "--name-only", commit, "--", *SUITE_PATHS).splitlines():
        if not path.endswith(".jsonl"):
            continue
        for line in _git(root, "show", f"{commit}:{path}").splitlines():
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            try:
                doc = json.loads(line)
            except json.JSONDecodeError:
                out.add(f"{path}: {line}")  # a broken line is a change of the split too
                continue
            if isinstance(doc, dict) and doc.get("split") == "test":
                kept = {k: v for k, v in doc.items() if k not in SCORING_FIELDS}
                out.add(f"{path}: {json.dumps(kept, sort_keys=True)}")
    return frozenset(out)


def split_frozen(root: Path = ROOT) -> str:
    """The last commit that changed what the test split commands or lays out: among the commits touching a test
    line, the newest whose test lines (scoring fields aside) differ from its parent's; "" when unknown."""
    candidates = _git(root, "log", "--format=%H %P", "-G", '"split": "test"', "--", *SUITE_PATHS).splitlines()
    for row in candidates:
        commit, *parents = row.split()
        before = _test_lines(root, parents[0]) if parents else frozenset()
        if _test_lines(root, commit) != before:
            return commit
    return ""


def source_revision(root: Path = ROOT) -> dict[str, str | bool]:
    """The commit of the code that runs the evaluation and whether the work tree had uncommitted changes (a dirty
    run cannot be reproduced from the commit alone); the commit that froze the test split, the last change to
    the policy stack (with its subject) and whether that came after the freeze."""
    commit = _git(root, "rev-parse", "HEAD")
    dirty = bool(_git(root, "status", "--porcelain", "--untracked-files=no")) if commit else False
    out: dict[str, str | bool] = {"commit": commit or "unknown (not a git checkout)", "dirty": dirty}
    if not commit:
        return out
    frozen = split_frozen(root)
    policy = _git(root, "log", "-1", "--format=%H", "--", *_policy_pathspec())
    out["split_frozen"] = frozen or "unknown"
    out["policy_changed"] = policy or "unknown"
    if policy:
        out["policy_changed_subject"] = _git(root, "log", "-1", "--format=%s", policy)[:200]
        out["policy_changed_files"] = " ".join(_git(root, "show", "--format=", "--name-only", policy, "--",
                                                    *_policy_pathspec()).split()[:12])
    if frozen and policy and frozen != policy:
        after = subprocess.run(["git", "merge-base", "--is-ancestor", frozen, policy], cwd=root,
                               capture_output=True, timeout=30).returncode == 0
        out["policy_changed_after_freeze"] = after
    elif frozen and policy:
        out["policy_changed_after_freeze"] = False
    return out

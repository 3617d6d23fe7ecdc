"""Structured output shared by the benchmarks: `--json PATH` writes a benchmark's figures as JSON.

Every benchmark prints its figures for a reader; with `--json PATH` it also writes them, with the arguments
that produced them, so `benchmarks/run_all.py` reads numbers instead of scraping text. Not a benchmark itself
(the leading underscore keeps `run_all.py` from running it).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def add_json_option(ap: argparse.ArgumentParser) -> None:
    """The `--json PATH` option every benchmark takes."""
    ap.add_argument("--json", type=Path, default=None, metavar="PATH",
                    help="also write the figures as JSON to PATH (read by benchmarks/run_all.py)")


def _clean(value: Any) -> Any:
    """JSON-safe: NaN/inf become None, numpy scalars plain numbers, tuples lists."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def git_commit() -> str:
    """The checkout's short commit, marked when tracked files have uncommitted changes."""
    root = Path(__file__).resolve().parent.parent

    def git(*a: str) -> str:
        try:
            return subprocess.run(["git", *a], cwd=root, capture_output=True, text=True, timeout=30).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""
    head = git("rev-parse", "--short", "HEAD") or "unknown"
    dirty = git("status", "--porcelain", "--untracked-files=no")
    return head + (" (with uncommitted changes)" if dirty else "")


def write_json(path: Path | None, benchmark: str, figures: dict[str, Any], args: argparse.Namespace | None = None,
               **extra: Any) -> None:
    """Write `figures` (name -> number, or a nested dict) for `benchmark` to `path`; nothing when path is None."""
    if path is None:
        return
    config = {k: v for k, v in vars(args).items() if k != "json"} if args else {}
    doc = {"benchmark": benchmark, "commit": git_commit(), "argv": sys.argv[1:], "config": config, "figures": figures,
           "load_average": os.getloadavg(), "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **extra}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_clean(doc), indent=2) + "\n")


def pin_all_threads(cpu: int) -> int:
    """Pin every thread of this process to `cpu` (os.sched_setaffinity(0, ...) pins only the calling thread:
    BLAS, OpenCV and Zenoh threads started earlier would still run on every core, and a "one core" figure would
    use more). Threads started later inherit the affinity. Returns how many threads were pinned."""
    import os

    pinned = 0
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), {cpu})
            pinned += 1
        except (ProcessLookupError, PermissionError):
            continue  # a thread that just ended
    return pinned

"""The suite's own layout: `make test` serialises the whole-stack tests by file name (tests/conftest.py STACK)."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import STACK

ROOT = Path(__file__).resolve().parents[2]


def test_every_stack_file_exists() -> None:
    """A renamed or moved whole-stack test file would leave the group silently and run beside another stack."""
    missing = [f for f in STACK if not (ROOT / f).is_file()]
    assert not missing, f"tests/conftest.py STACK names files that do not exist: {missing}"
    assert len(set(STACK)) == len(STACK)

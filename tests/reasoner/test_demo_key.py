"""`aermani demo` with a model backend and no key fails before anything starts, saying what to set."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

CMD = "pick up the red cup and place it on the table"


def _demo(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items()
             if k not in ("AERMANI_REASONER_API_KEY", "OPENAI_API_KEY", "ANTHROPIC_API_KEY", "AERMANI_TEST_KEY")}
    return subprocess.run([sys.executable, "-m", "aermani.cli", "demo", CMD, *args], capture_output=True, text=True,
                          timeout=120, env={**clean, "COLUMNS": "200", **env}, check=False)


@pytest.mark.parametrize(("backend", "var"), [("openai", "OPENAI_API_KEY"), ("anthropic", "ANTHROPIC_API_KEY")])
def test_missing_key_fails_before_takeoff_with_what_to_set(backend: str, var: str) -> None:
    r = _demo("--backend", backend)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "no API key: set AERMANI_REASONER_API_KEY or " + var in r.stdout, r.stdout
    assert "starting" not in r.stdout  # nothing was started


def test_api_key_env_names_a_variable_that_must_be_set() -> None:
    r = _demo("--backend", "openai", "--api-key-env", "AERMANI_TEST_KEY")
    assert r.returncode == 2 and "AERMANI_TEST_KEY, which is not set" in r.stdout, r.stdout


def test_the_key_is_read_from_the_named_variable() -> None:
    from aermani.demo import backend_key_env

    os.environ["AERMANI_TEST_KEY"] = "sk-test-not-a-real-key"
    try:
        assert backend_key_env("openai", "AERMANI_TEST_KEY") == {"AERMANI_REASONER_API_KEY": "sk-test-not-a-real-key"}
    finally:
        del os.environ["AERMANI_TEST_KEY"]
    assert backend_key_env("rules", None) == {}
    assert "no-such-backend" in str(backend_key_env("no-such-backend", None))


def test_up_with_a_model_backend_and_no_key_fails_before_anything_starts() -> None:
    """`aermani up` with a model backend and no key says what to set and starts nothing (it used to start the
    stack with a reasoner that crashed in a loop, the reason only in the reasoner's log)."""
    clean = {k: v for k, v in os.environ.items()
             if k not in ("AERMANI_REASONER_API_KEY", "OPENAI_API_KEY", "ANTHROPIC_API_KEY")}
    r = subprocess.run([sys.executable, "-m", "aermani.cli", "up", "--services", "reasoner", "--port", "1"],
                       capture_output=True, text=True, timeout=120, check=False,
                       env={**clean, "COLUMNS": "200", "AERMANI_REASONER_BACKEND": "anthropic"})
    assert r.returncode == 2, r.stdout + r.stderr
    assert "no API key: set AERMANI_REASONER_API_KEY or ANTHROPIC_API_KEY" in r.stdout, r.stdout
    assert "router on" not in r.stdout and "starting" not in r.stdout

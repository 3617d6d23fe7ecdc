"""shared/skill_library.json, the built-in Skill Library offline tools read, is what the executor's registry
serves at default settings."""

from __future__ import annotations

from services.executor import registry
from shared.skills import builtin_library


def test_the_contract_library_file_is_current():
    assert registry.main(["--check"]) == 0, "stale: run python -m services.executor.registry --write"
    assert builtin_library().skills == registry.builtin_library().skills


def test_it_is_what_a_default_executor_serves():
    served = {s.name: s for s in registry.library(registry.ExecutorSettings.model_construct()).skills}
    assert {s.name: s for s in builtin_library().skills}.items() <= served.items()

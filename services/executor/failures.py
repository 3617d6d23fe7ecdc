"""A skill's coded failure, apart from the skill context so working memory can raise one too."""

from __future__ import annotations

from shared.errors import SkillError
from shared.messages import OutcomeCode, SkillFacts


class SkillFailed(SkillError):
    """A skill could not reach its termination condition: `code` and `facts` are what a policy decides from,
    the message is the same for a person (and a VLM) to read."""

    def __init__(self, message: str, code: OutcomeCode | None = OutcomeCode.FAILED,
                 facts: SkillFacts | None = None) -> None:
        super().__init__(message)
        self.code = code or OutcomeCode.FAILED
        self.facts = facts or SkillFacts()

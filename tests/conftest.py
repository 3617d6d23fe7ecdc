"""Session-wide test configuration."""

from __future__ import annotations

import os

# Never let a developer's real keys or endpoints leak into tests.
for var in ("OPENAI_API_KEY", "ANTHROPIC_API_KEY", "AERMANI_REASONER_API_KEY", "AERMANI_GATEWAY_TOKEN"):
    os.environ.pop(var, None)
os.environ.setdefault("RUST_LOG", "error")

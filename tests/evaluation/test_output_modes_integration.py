"""`aermani eval --output-mode both` on the real stack through the local OpenAI-compatible stand-in: the same
episode once with the answer schema sent, once as free text, compared with IAR per mode."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from aermani.evaluation.records import RESULTS_FILE, ResultsFile
from tests.reasoner.fake_vlm import FakeVLMServer

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_eval_both_output_modes(tmp_path) -> None:
    with FakeVLMServer(fault_every=4) as vlm:
        env = {**os.environ, "AERMANI_REASONER_API_KEY": "none", "AERMANI_SIM_FPS": "5"}
        res = subprocess.run([sys.executable, "-m", "aermani.cli", "eval", "--backend", "openai", "--model", "fake-vlm",
                              "--base-url", vlm.openai_base_url, "--suites", "localization", "--episodes", "1",
                              "--t-max", "240", "--speed-factor", "4", "--output-mode", "both", "--no-progress",
                              "--out", str(tmp_path)], capture_output=True, text=True, env=env, timeout=900)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    calls = {}
    for mode in ("schema", "text"):
        recs = ResultsFile(tmp_path / mode / RESULTS_FILE).load()
        assert len(recs) == 1 and not recs[0].harness_error and recs[0].steps
        calls[mode] = [c for s in recs[0].steps for c in s.calls]
        assert "IAR by answer decoding" in (tmp_path / mode / "report.md").read_text()
    assert calls["schema"] and all(c.structured for c in calls["schema"])
    assert calls["text"] and not any(c.structured for c in calls["text"])
    assert any(not c.valid for c in calls["schema"]) and any(not c.valid for c in calls["text"])  # every 4th
    md = (tmp_path / "modes.md").read_text()
    assert "| [schema](schema/report.md) |" in md and "| [text](text/report.md) |" in md
    assert vlm.schema_errors == []

"""`aermani vlm probe` (a real process) against the local stand-in servers."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import pytest

from aermani.launcher import available_services
from tests.reasoner.fake_vlm import FakeVLMServer

pytestmark = pytest.mark.integration


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def probe(args: list[str], out) -> tuple[subprocess.CompletedProcess, dict]:
    res = subprocess.run([sys.executable, "-m", "aermani.cli", "vlm", "probe", "--api-key", "none", "--model",
                          "fake-vlm", "--connect", f"tcp/127.0.0.1:{closed_port()}", "--out", str(out), *args],
                         capture_output=True, text=True, timeout=240)
    return res, json.loads(out.read_text()) if out.exists() else {}


@pytest.mark.skipif("sim" not in available_services(), reason="the simulator is not in this checkout")
def test_probe_openai_compatible_with_a_simulator_frame(tmp_path) -> None:
    with FakeVLMServer() as vlm:
        res, rep = probe(["--base-url", vlm.openai_base_url, "--backend", "openai", "--calls", "4"],
                         tmp_path / "p.json")
    assert res.returncode == 0, res.stdout + res.stderr
    assert "schema mode supported" in res.stdout and "RT median over 4 calls" in res.stdout
    assert rep["frame_source"].startswith("simulator started") and rep["frame_bytes"] > 1000
    assert rep["image_accepted"] and rep["schema_supported"] and rep["mode_used"] == "schema"
    assert rep["valid_rate"] == 1.0 and 0 < rep["rt_median_s"] <= rep["rt_p95_s"]
    assert rep["tokens_in_mean"] > 0 and rep["tokens_out_mean"] > 0 and len(rep["calls"]) == 6
    # what the stand-in received: the image every time, the schema on all but the free-text check
    assert all(vlm.images) and len(vlm.requests) == 6
    assert [sc is not None for sc in vlm.schemas] == [True, False, True, True, True, True]
    assert vlm.schema_errors == []


def test_probe_anthropic_reports_a_refused_schema(tmp_path) -> None:
    with FakeVLMServer(reject_schema=True) as vlm:
        res, rep = probe(["--base-url", vlm.anthropic_base_url, "--backend", "anthropic", "--calls", "3",
                          "--no-sim"], tmp_path / "p.json")
    assert res.returncode == 0, res.stdout + res.stderr
    assert rep["frame_source"].startswith("generated") and "generated" in res.stdout
    assert rep["schema_supported"] is False and rep["mode_used"] == "text" and rep["text_mode_valid"]
    assert "rejected the answer schema" in " ".join(rep["notes"])
    assert rep["valid_rate"] == 1.0 and rep["rt_median_s"] > 0


def test_probe_names_a_missing_key(tmp_path, monkeypatch) -> None:
    monkeypatch.delenv("ANTHROPIC_API_KEY", raising=False)
    monkeypatch.delenv("AERMANI_REASONER_API_KEY", raising=False)
    res = subprocess.run([sys.executable, "-m", "aermani.cli", "vlm", "probe", "--backend", "anthropic", "--no-sim",
                          "--connect", f"tcp/127.0.0.1:{closed_port()}", "--out", str(tmp_path / "p.json")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and "no API key: set AERMANI_REASONER_API_KEY or ANTHROPIC_API_KEY" in res.stdout


@pytest.mark.parametrize(("server", "image", "schema"), [
    ({"reject_images": True}, False, True),  # a text-only model's server: the image, not the schema
    ({"outage": True}, None, None),  # HTTP 503 to everything: nothing is known of either
])
def test_probe_tells_image_schema_and_server_errors_apart(tmp_path, server: dict, image, schema) -> None:
    with FakeVLMServer(**server) as vlm:
        res, rep = probe(["--base-url", vlm.openai_base_url, "--backend", "openai", "--calls", "1", "--no-sim"],
                         tmp_path / "p.json")
    assert res.returncode == 1, res.stdout + res.stderr  # not usable as a VLM either way
    assert rep["image_accepted"] is image and rep["schema_supported"] is schema, rep
    assert bool(rep["server_error"]) == (image is None), rep["notes"]
    assert ("refuses the image" in " ".join(rep["notes"])) == (image is False)

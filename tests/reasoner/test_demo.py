"""End to end: `aermani demo` on the real stack (sim, bridge, perception, executor, reasoner, recorder)."""

from __future__ import annotations

import pytest

from services.reasoner.cli import run_demo, scenario_for
from shared.launcher import available_services
from tests.reasoner.fake_vlm import FakeVLMServer

pytestmark = [pytest.mark.integration, pytest.mark.slow]
NEEDED = {"sim", "autopilot_bridge", "perception", "executor", "reasoner"}
if not set(available_services()) >= NEEDED:
    pytest.skip("the full stack is not in this checkout", allow_module_level=True)

CMD = "pick up the red cup and place it on the table"


def demo(tmp_path, env: dict[str, str], command: str = CMD) -> tuple[int, dict]:
    scenario, accepted = scenario_for(command, None, None, 0)
    result: dict = {}
    code = run_demo(command, scenario, accepted, env={"AERMANI_SIM_SPEED_FACTOR": "2", **env}, t_max=400,
                    log_dir=tmp_path / "logs", services=("sim", "autopilot_bridge", "perception", "executor",
                                                         "reasoner"), result=result)
    return code, result


def test_demo_rules(tmp_path) -> None:
    code, result = demo(tmp_path, {"AERMANI_REASONER_BACKEND": "rules"})
    assert code == 0 and result["success"], result.get("verdict")
    skills = [s.ste.skill for s in result["steps"]]
    assert skills[-1] == "done" and "grasp" in skills and "place" in skills
    # The default demo: real computer vision on the rendered pixels, realistic camera and pose noise, as the
    # running services report it.
    assert result["segmenter"] == "color" and result["realism"] == "realistic", result


def test_demo_openai_compatible_with_injected_faults(tmp_path) -> None:
    with FakeVLMServer() as vlm:
        vlm.faults.extend(["invalid_json", None, "fences", "500", None, "unknown_skill"])
        code, result = demo(tmp_path, {"AERMANI_REASONER_BACKEND": "openai", "AERMANI_REASONER_API_KEY": "none",
                                       "AERMANI_REASONER_BASE_URL": vlm.openai_base_url,
                                       "AERMANI_REASONER_MODEL": "fake-vlm"})
    assert code == 0 and result["success"], result.get("verdict")
    final, steps = result["final"], result["steps"]
    assert [s.retries for s in steps[:4]] == [1, 0, 0, 1]
    assert final.invalid_answers == 2 and final.model_calls == sum(len(s.calls) for s in steps)

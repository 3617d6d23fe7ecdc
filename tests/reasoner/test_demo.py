"""End to end: `aermani demo` on the real stack (sim, bridge, perception, executor, reasoner, recorder)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from aermani.demo import run_demo, scenario_for
from aermani.launcher import available_services
from shared import mcaplog
from shared.keys import Keys
from shared.sensors import CompressedImage, decode_proto, stamp_to_ns
from tests.reasoner.fake_vlm import FakeVLMServer

pytestmark = [pytest.mark.integration, pytest.mark.slow]
NEEDED = {"sim", "autopilot_bridge", "perception", "executor", "reasoner"}
if not set(available_services()) >= NEEDED:
    pytest.skip("the full stack is not in this checkout", allow_module_level=True)

CMD = "pick up the red cup and place it on the table"
# Where a test asserts that the task succeeds, the world is the ideal one: no gusts, no drift, no sensor noise,
# so the grasp's outcome is not left to chance (in the realistic world about 1 demo in 20 knocks the cup off the
# table). test_demo_rules covers the realistic default.
IDEAL = {"AERMANI_SIM_REALISM": "ideal"}


def demo(tmp_path, env: dict[str, str], command: str = CMD,
         services: tuple[str, ...] = ("sim", "autopilot_bridge", "perception", "executor", "reasoner"),
         ) -> tuple[int, dict]:
    scenario, accepted = scenario_for(command, None, None, 0)
    result: dict = {}
    code = run_demo(command, scenario, accepted, env={"AERMANI_SIM_SPEED_FACTOR": "2", **env}, t_max=400,
                    log_dir=tmp_path / "logs", services=services, result=result)
    return code, result


def test_demo_rules(tmp_path) -> None:
    """The default demo in the default (realistic) world, recorded; its log exported as a ROS 2 bag reads back in
    full with rosbags and with mcap-ros2-support (every message deserialized by both, the same counts).

    In the realistic world the pick-and-place succeeds by chance, not always: the multirotor drifts and gusts
    push it, and a grasp can knock the cup off the table where no viewpoint sees it again (CI, stop 46: 1 demo
    in about 20). What holds every time is asserted here: the task ends, a success is claimed only when the
    simulator's judge confirms it, a failure says why, and the log is complete either way. That the stack does
    the whole pick-and-place is asserted in the ideal world below (the same policy through a model backend),
    where the outcome does not depend on the weather; the realistic rates are measured by benchmarks/grasp.py."""
    code, result = demo(tmp_path, {"AERMANI_REASONER_BACKEND": "rules",
                                   "AERMANI_RECORDER_OUT_DIR": str(tmp_path / "rec")},
                        services=("sim", "autopilot_bridge", "perception", "executor", "reasoner", "recorder"))
    assert "final" in result, f"the task never ended (exit {code})"
    final, skills = result["final"], [s.ste.skill for s in result["steps"] if s.ste]
    assert "grasp" in skills, skills  # it found the cup and tried
    claimed = final.state.value == "succeeded"
    assert not claimed or result["success"], f"claimed success the judge denies: {result['verdict']}"
    assert (code == 0) == (claimed and result["success"])
    if claimed:
        assert skills[-1] == "done" and "place" in skills
    else:
        assert final.message, final  # a failure says why
    # The default demo: real computer vision on the rendered pixels, realistic camera and pose noise, the
    # multirotor, as the running services report them.
    assert result["segmenter"] == "color" and result["realism"] == "realistic", result
    assert result["dynamics"] == "multirotor", result  # the simulator's default body (issue 24)
    (log,) = sorted((tmp_path / "rec").glob("*.mcap"))
    # The recorder keeps 1 frame pair a second, and every frame a step was decided on.
    colour = list(mcaplog.iter_samples(log, Keys("am1").camera_color.key))
    logged = {stamp_to_ns(decode_proto(CompressedImage, s.payload).timestamp) for s in colour}
    assert {s.image_stamp_ns for s in result["steps"]} <= logged
    # Every recorded step says where its time went (issue 27), and the parts fit inside the whole.
    for st in mcaplog.reasoning_steps(log):
        t = st.timing
        assert t is not None and t.model_s > 0 and t.skill_s > 0, st
        assert t.frame_wait_s + t.detections_wait_s + t.state_wait_s + t.link_wait_s + t.prompt_s <= t.to_model_s, t
        assert t.skill_s <= st.skill_duration_s + 0.05, (t, st.skill_duration_s)  # the executor's part of it
    bag = tmp_path / "bag"
    out = subprocess.run([sys.executable, "-m", "aermani.cli", "log", "export", str(log), "--out", str(bag), "--ros2"],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    by_rosbags, by_mcap = read_bag_both_ways(bag)
    assert by_rosbags == by_mcap
    assert {"/am1/camera/color/image/compressed", "/am1/camera/depth/image", "/am1/camera/color/camera_info", "/tf",
            "/am1/pose", "/am1/reasoner/step", "/am1/reasoner/task_status"} <= set(by_rosbags)
    assert by_rosbags["/am1/reasoner/step"] == len(result["steps"])


def read_bag_both_ways(bag: Path) -> tuple[Counter, Counter]:
    """Messages per topic, every one deserialized: by rosbags (the rosbag2 directory, its own typestore) and by
    mcap-ros2-support (the MCAP file alone, from the schemas it carries)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    a: Counter = Counter()
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for con, _t, raw in reader.messages():
            msg = reader.deserialize(raw, con.msgtype)
            if con.msgtype == "geometry_msgs/msg/PoseStamped":
                assert msg.header.frame_id == "world"
            a[con.topic] += 1
    b: Counter = Counter()
    (mcap_file,) = bag.glob("*.mcap")
    with mcap_file.open("rb") as f:
        for _schema, channel, _message, ros_msg in make_reader(
                f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            if channel.topic == "/am1/camera/depth/image":
                assert ros_msg.encoding == "16UC1" and len(ros_msg.data) == ros_msg.step * ros_msg.height
            b[channel.topic] += 1
    return a, b


@pytest.mark.parametrize("kind", ["openai", "anthropic"])
def test_demo_model_backend_with_schema_reprompt_and_done(tmp_path, kind: str) -> None:
    """The demo through a model backend against the local stand-in (OpenAI-compatible chat completions, or the
    Anthropic Messages API): every request carries the camera image and the skill-enum answer schema, an
    invalid answer is re-prompted with its error, and the task ends on the model's `done`."""
    with FakeVLMServer() as vlm:
        vlm.faults.extend(["invalid_json", None, "fences", "500", None, "unknown_skill"])
        base = vlm.openai_base_url if kind == "openai" else vlm.anthropic_base_url
        code, result = demo(tmp_path, {"AERMANI_REASONER_BACKEND": kind, "AERMANI_REASONER_API_KEY": "none",
                                       "AERMANI_REASONER_BASE_URL": base, "AERMANI_REASONER_MODEL": "fake-vlm",
                                       **IDEAL})
    assert code == 0 and result["success"], result.get("verdict")
    assert result["realism"] == "ideal"
    skills = [s.ste.skill for s in result["steps"]]
    assert "grasp" in skills and "place" in skills  # the whole pick-and-place, confirmed by the judge
    final, steps = result["final"], result["steps"]
    assert [s.retries for s in steps[:4]] == [1, 0, 0, 1]
    assert final.invalid_answers == 2 and final.model_calls == sum(len(s.calls) for s in steps)
    assert steps[-1].ste.skill == "done" and final.state.value == "succeeded"
    assert all(s.image_stamp_ns for s in steps)  # the simulator's camera frame went with every step
    # every request: the image and a schema whose skill enum is the executor's policy skills
    assert len(vlm.requests) == final.model_calls + 1  # + the injected 500, retried by the transport
    assert all(vlm.images) and all(sc is not None for sc in vlm.schemas) and vlm.schema_errors == []
    enum = json.dumps(vlm.schemas[0])
    assert all(f'"{n}"' in enum for n in ("yaw_left", "obj_localization", "grasp", "place", "done"))
    assert '"takeoff"' not in enum
    reprompts = [r for r in vlm.requests if len(r["messages"]) > 1]
    assert len(reprompts) == 2
    first_error = steps[0].calls[0].error
    assert first_error and first_error in json.dumps(reprompts[0]["messages"][-1])
    assert all(c.structured for s in steps for c in s.calls)


def test_demo_with_the_speculative_next_step(tmp_path) -> None:
    """AERMANI_REASONER_SPECULATE=1 on the whole stack, the model a local server answering after 0.3 s: steps are
    asked for while the skill before them flies (motions, localizations), each used one is recorded as such, and the
    pick-and-place completes as without it."""
    with FakeVLMServer(latency_s=0.3) as vlm:
        code, result = demo(tmp_path, {"AERMANI_REASONER_BACKEND": "openai", "AERMANI_REASONER_API_KEY": "none",
                                       "AERMANI_REASONER_BASE_URL": vlm.openai_base_url,
                                       "AERMANI_REASONER_MODEL": "fake-vlm", "AERMANI_REASONER_SPECULATE": "1",
                                       **IDEAL})
    assert code == 0 and result["success"], result.get("verdict")
    final, steps = result["final"], result["steps"]
    skills = [s.ste.skill for s in steps]
    assert "grasp" in skills and "place" in skills and skills[-1] == "done"
    assert final.speculations >= 1  # the task's first motions and its localization were speculated on
    assert final.speculations_used == sum(s.speculative for s in steps) <= final.speculations
    # a used answer's calls count once; a discarded one's are not in model_calls
    assert final.model_calls == sum(len(s.calls) for s in steps)
    assert len(vlm.requests) >= final.model_calls  # (a discarded one may be cancelled before it was sent)


def test_demo_refuses_to_take_off_after_a_failed_preflight_until_overridden(tmp_path, monkeypatch) -> None:
    """The simulated PX4 configured unsafely (offboard loss -> Disarm, no geofence action): the demo stops
    before the task with the preflight's reasons; overridden, it flies the task (the bridge logs the override)."""
    monkeypatch.setenv("AERMANI_SIM_PX4_PARAMS", "COM_OBL_RC_ACT=7,GF_ACTION=0")
    code, result = demo(tmp_path / "refused", {"AERMANI_REASONER_BACKEND": "rules"})
    assert code == 2 and result.get("preflight") == "refused", result
    assert "steps" not in result  # no task was started
    # overridden, it arms and flies a task (a pick without the place: the flight, not the task, is under test)
    code, result = demo(tmp_path / "overridden", {"AERMANI_REASONER_BACKEND": "rules",
                                                  "AERMANI_AUTOPILOT_BRIDGE_PREFLIGHT_OVERRIDE": "1", **IDEAL},
                        command="pick up the red cup")
    assert code == 0 and result["success"], result.get("verdict")
    log = (tmp_path / "overridden" / "logs" / "autopilot_bridge-am1.log").read_text()
    assert "arming with a failed preflight" in log and "COM_OBL_RC_ACT" in log

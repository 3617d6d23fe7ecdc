"""Motion primitives, the registry and run_skill/status semantics against fakes on a real Zenoh bus."""

from __future__ import annotations

import math

from services.executor.registry import REGISTRY, build_library
from services.executor.settings import ExecutorSettings
from shared import skills as names
from shared.keys import Keys
from shared.messages import SkillState
from tests.executor.rig import rig
from tests.helpers import wait_until


def test_registry_covers_every_shared_skill_name_with_settings_in_the_text():
    s = ExecutorSettings(yaw_step_deg=45, horizontal_step=0.4)
    lib = build_library(s)
    expected = set(names.MOTION_PRIMITIVES) | set(names.OPERATOR_SKILLS) | {names.GRASP, names.PLACE, names.DONE}
    assert expected <= set(lib)
    specs = {n: sk.spec() for n, sk in lib.items()}
    assert "45 deg" in specs["yaw_left"].description
    assert "0.4 m" in specs["forward"].description
    assert {p.name: p.value for p in specs["forward"].parameters}["distance"] == 0.4
    assert specs["obj_localization"].argument_required
    assert not specs["takeoff"].policy_visible and specs["grasp"].policy_visible
    assert len(REGISTRY) == len(lib)


async def test_skills_queryable_and_forward_moves_one_step():
    async with rig() as r:
        lib = await r.bus.query(r.keys.skills, None, timeout=5)
        assert [s.name for s in lib.skills][:8] == list(names.MOTION_PRIMITIVES)
        acc = await r.request("forward")
        assert acc.accepted and acc.goal_id
        running = await r.statuses.recv(timeout=5)
        assert running.state == SkillState.RUNNING and running.goal_id == acc.goal_id
        st = await r.terminal(acc.goal_id)
        assert st.state == SkillState.SUCCEEDED, st.message
        assert st.outcome.start_pose is not None and st.outcome.end_pose is not None
        assert math.isclose(st.outcome.end_pose.position.x - st.outcome.start_pose.position.x, 0.5, abs_tol=0.09)


async def test_each_motion_primitive_ends_at_its_fixed_step():
    async with rig() as r:
        r.vehicle.yaw = r.vehicle.target_yaw = math.pi / 2  # facing +y: body axes differ from world axes
        await wait_until(lambda: abs(r.executor.state.value.yaw - math.pi / 2) < 1e-6, 10, what="yaw seen")
        yaw = ExecutorSettings().yaw_step_deg
        expect = {"yaw_left": (0, 0, 0, yaw), "yaw_right": (0, 0, 0, -yaw), "forward": (0, 0.5, 0, 0),
                  "backward": (0, -0.5, 0, 0), "left": (-0.5, 0, 0, 0), "right": (0.5, 0, 0, 0),
                  "up": (0, 0, 0.3, 0), "down": (0, 0, -0.3, 0)}
        for skill, (dx, dy, dz, dyaw) in expect.items():
            st = await r.run_skill(skill)
            assert st.state == SkillState.SUCCEEDED, (skill, st.message)
            a, b = st.outcome.start_pose, st.outcome.end_pose
            assert math.isclose(b.position.x - a.position.x, dx, abs_tol=0.09), skill
            assert math.isclose(b.position.y - a.position.y, dy, abs_tol=0.09), skill
            assert math.isclose(b.position.z - a.position.z, dz, abs_tol=0.09), skill
            turned = math.degrees((b.yaw - a.yaw + math.pi) % (2 * math.pi) - math.pi)
            assert math.isclose(turned, dyaw, abs_tol=6), skill
        mem = r.executor.memory.snapshot()
        assert [e.split(":")[0] for e in mem.executed] == list(expect)


async def test_one_skill_at_a_time_and_done_and_unknown():
    async with rig() as r:
        first = await r.request("forward")
        assert first.accepted
        second = await r.request("yaw_left")
        assert not second.accepted and "still running" in second.reason
        assert (await r.terminal(first.goal_id)).state == SkillState.SUCCEEDED
        st = await r.run_skill("done")
        assert st.state == SkillState.SUCCEEDED
        bad = await r.request("fly_to_moon")
        assert not bad.accepted and "unknown skill" in bad.reason and "forward" in bad.reason
        rej = await r.terminal(bad.goal_id, 5)
        assert rej.state == SkillState.REJECTED


def test_keys_are_per_vehicle():
    assert Keys("am2").run_skill.key.endswith("am2/executor/run_skill")


async def test_the_documented_example_skill_registers_and_runs():
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[2] / "docs" / "skills.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    try:
        exec(compile(code, "docs/skills.md", "exec"), {})
        assert "descend_to_inspect" in REGISTRY

        async with rig() as r:
            lib = await r.bus.query(r.keys.skills, None, timeout=5)
            spec = next(s for s in lib.skills if s.name == "descend_to_inspect")
            assert "0.3 m" in spec.description
            st = await r.run_skill("descend_to_inspect")
            assert st.state == SkillState.SUCCEEDED, st.message
            assert abs(r.vehicle.pos[2] - 0.3) < 0.09
    finally:
        REGISTRY.pop("descend_to_inspect", None)

"""One valid instance of every bus message type, camera frames, and a scripted task's reasoning steps."""

from __future__ import annotations

import numpy as np

from shared import messages as m
from shared.keys import Keys
from shared.sensors import Intrinsics, calibration_message, color_message, depth_message, raw16_message

K = Keys("am1")


def example(cls: type[m.Message], i: int = 0) -> m.Message:
    """A valid instance of `cls` (fields vary with `i`)."""
    v = m.Vec3(x=0.1 * i, y=0.2, z=1.0)
    pose = m.Pose(position=v, yaw=0.1)
    examples = {
        m.VehicleState: lambda: m.VehicleState(position=v, armed=True, mode="OFFBOARD"),
        m.ArmCommand: lambda: m.ArmCommand(),
        m.DisarmCommand: lambda: m.DisarmCommand(),
        m.TakeoffCommand: lambda: m.TakeoffCommand(altitude=1.5),
        m.GotoCommand: lambda: m.GotoCommand(position=v, yaw=0.2),
        m.HoldCommand: lambda: m.HoldCommand(),
        m.LandCommand: lambda: m.LandCommand(),
        m.GripperCommand: lambda: m.GripperCommand(action="close"),
        m.AutopilotResult: lambda: m.AutopilotResult(ok=True, command="arm"),
        m.PreflightCommand: lambda: m.PreflightCommand(),
        m.PreflightReport: lambda: m.PreflightReport(
            trigger="operator", ok=True, checks=(m.PreflightCheck(name="camera", ok=True, value="15 fps"),)),
        m.LocalizeRequest: lambda: m.LocalizeRequest(query="red cup"),
        m.ObjectEstimate: lambda: m.ObjectEstimate(query="red cup", found=True, pose=pose, size=v),
        m.PlacementEstimate: lambda: m.PlacementEstimate(query="table", found=True, pose=pose, plane=(0, 0, 1, -0.7)),
        m.Detections: lambda: m.Detections(items=(m.Detection(label="red cup", centroid=v),)),
        m.SkillLibrary: lambda: m.SkillLibrary(skills=(m.SkillSpec(name="forward", category="motion",
                                                                   description="move forward"),)),
        m.SkillRequest: lambda: m.SkillRequest(skill="forward", task_id="t", step=i),
        m.SkillAccept: lambda: m.SkillAccept(accepted=True, goal_id="g1"),
        m.WorkingMemory: lambda: m.WorkingMemory(objects=(m.MemoryObject(label="red cup", position=v),)),
        m.SkillStatus: lambda: m.SkillStatus(goal_id="g1", skill="forward", state=m.SkillState.SUCCEEDED),
        m.Abort: lambda: m.Abort(),
        m.AbortAck: lambda: m.AbortAck(abort_stamp_ns=1),
        m.ReasoningStep: lambda: step_message("task-x", i + 1, "forward"),
        m.TaskRequest: lambda: m.TaskRequest(command="pick up the red cup"),
        m.TaskAccept: lambda: m.TaskAccept(accepted=True, task_id="t"),
        m.TaskStatus: lambda: m.TaskStatus(task_id="t", command="pick up the red cup", state=m.TaskState.RUNNING),
        m.Health: lambda: m.Health(service="test", ok=True, details={"i": i}),
        m.Scenario: lambda: m.Scenario(seed=i, target_object="red cup"),
        m.SimLabels: lambda: m.SimLabels(labels=(m.SimLabel(id=1, name="red cup", category="object"),)),
        m.JudgeRequest: lambda: m.JudgeRequest(),
        m.JudgeResult: lambda: m.JudgeResult(held="red cup", checks=(m.JudgeCheck(name="hold", ok=i % 2 == 0),)),
        m.SimResetResult: lambda: m.SimResetResult(ok=True),
        m.SimState: lambda: m.SimState(task_id="t", step=i, skill="forward", state='{"format": 1}'),
        m.MemoryRestore: lambda: m.MemoryRestore(task_id="t", memory=m.WorkingMemory(), taken_ns=1 + i),
        m.CancelGoal: lambda: m.CancelGoal(goal_id=f"g{i}"),
        m.GoalRef: lambda: m.GoalRef(goal_id=f"g{i}"),
        m.CancelReply: lambda: m.CancelReply(accepted=True),
        m.ResetNotice: lambda: m.ResetNotice(seed=i),
        m.ApprovalStatus: lambda: m.ApprovalStatus(skill="grasp", step=i),
        m.ApprovalDecision: lambda: m.ApprovalDecision(approval_id=f"a{i}", approved=True),
        m.Heartbeat: lambda: m.Heartbeat(service="executor", pid=1000 + i, loop_lag_ms=0.5),
    }
    return examples[cls]()


def step_message(task_id: str, step: int, skill: str, argument: str | None = None, image_stamp_ns: int = 0,
                 latency: float = 0.5, invalid: int = 0, state: m.SkillState = m.SkillState.SUCCEEDED,
                 command: str = "pick up the red cup") -> m.ReasoningStep:
    calls = tuple(m.ModelCall(raw_answer="oops", valid=False, error="not JSON", latency_s=latency)
                  for _ in range(invalid))
    answer = f'{{"skill": "{skill}", "argument": {"null" if argument is None else repr(argument)}}}'
    calls += (m.ModelCall(raw_answer=answer, valid=True, latency_s=latency),)
    return m.ReasoningStep(
        task_id=task_id, step=step, backend="rules", variant="full", image_stamp_ns=image_stamp_ns,
        prompt={"command": command, "history": f"{step - 1} steps so far"}, calls=calls,
        drt=m.DescriptiveReasoningTrace(image_description=f"view at step {step}", summary=f"summary {step}",
                                        reasoning=f"because step {step}"),
        ste=m.SkillToExecute(skill=skill, argument=argument), valid=True, retries=invalid, skill_state=state,
        skill_message="done", skill_duration_s=1.5,
    )


def frames(stamp_ns: int, seed: int = 0) -> dict[str, bytes]:
    """Colour (JPEG CompressedImage), depth (16-bit PNG CompressedImage) and segmentation (RawImage 16UC1) at
    160x120 for speed."""
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)
    depth = np.full((120, 160), 1500 + seed, dtype=np.uint16)
    seg = np.zeros((120, 160), dtype=np.uint16)
    seg[40:80, 60:100] = 1
    return {
        K.camera_color: color_message(rgb, stamp_ns),
        K.camera_depth: depth_message(depth, stamp_ns),
        K.camera_segmentation: raw16_message(seg, stamp_ns),
    }


def calibration(stamp_ns: int) -> bytes:
    return calibration_message(Intrinsics(640, 480, 350.0, 350.0, 320.0, 240.0), stamp_ns)

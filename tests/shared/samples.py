"""One valid instance of every bus message type, for round-trip tests."""

from __future__ import annotations

from shared import messages as m


def sample_messages() -> list[m.Message]:
    pose = m.Pose(position=m.Vec3(x=1.0, y=-0.5, z=1.5), yaw=0.3)
    est = m.ObjectEstimate(query="red cup", found=True, label="red cup", pose=pose, size=m.Vec3(x=0.08, y=0.08, z=0.11),
                           top_z=0.86, support_z=0.75, confidence=0.9, n_points=420,
                           bbox=m.BBox2D(x0=10, y0=20, x1=50, y1=80), frame_stamp_ns=123)
    place = m.PlacementEstimate(query="table", found=True, label="table", pose=pose, surface_z=0.75,
                                plane=(0.0, 0.0, 1.0, -0.75), vertical_offset=0.02, clearance=0.2)
    drt = m.DescriptiveReasoningTrace(image_description="a red cup on a table", summary="took off",
                                      action_predictions={"forward": "closer"}, reasoning="localize first")
    out = m.SkillOutcome(start_pose=pose, end_pose=pose, perceived="red cup at (1, 0, 0.8)", estimate=est)
    return [
        m.VehicleState(position=m.Vec3(x=1, y=2, z=3), armed=True, mode="OFFBOARD", landed_state=m.LandedState.IN_AIR,
                       gripper=m.GripperState.CLOSED, link_ok=True, offboard_ok=True, battery_remaining=87.5),
        m.ArmCommand(), m.DisarmCommand(force=True), m.TakeoffCommand(altitude=1.5),
        m.GotoCommand(position=m.Vec3(x=1, y=1, z=1.5), yaw=1.0, max_speed=0.5), m.HoldCommand(), m.LandCommand(),
        m.GripperCommand(action="close"),
        m.AutopilotResult(ok=False, command="arm", ack_code=2, ack_name="MAV_RESULT_DENIED", message="denied"),
        m.PreflightCommand(),
        m.PreflightReport(trigger="takeoff", ok=False, overridden=True, override_reason="bench test, props off",
                          checks=(m.PreflightCheck(name="GF_ACTION", ok=False, value="0 (None)"),)),
        m.AutopilotResult(ok=False, command="preflight", message="preflight failed: GF_ACTION",
                          checks=(m.PreflightCheck(name="GF_ACTION", ok=False, value="0 (None)",
                                                   expected="2 Hold or 5 Land", reason="a runaway vehicle leaves"),
                                  m.PreflightCheck(name="link", ok=True, value="heartbeats"))),
        m.LocalizeRequest(query="red cup", object_size=m.Vec3(x=0.1, y=0.1, z=0.1)), est, place,
        m.Detections(frame_stamp_ns=5, segmenter="sim", items=(m.Detection(label="red cup", centroid=m.Vec3()),)),
        m.SkillLibrary(skills=(m.SkillSpec(name="forward", category="motion", description="move 0.5 m",
                                           parameters=(m.SkillParameter(name="distance", value=0.5, unit="m"),)),)),
        m.SkillRequest(skill="obj_localization", argument="red cup", task_id="t1", step=2),
        m.SkillAccept(accepted=True, goal_id="g1"),
        m.WorkingMemory(objects=(m.MemoryObject(label="red cup", position=m.Vec3(x=1)),), held_object="red cup"),
        m.SkillStatus(goal_id="g1", skill="grasp", state=m.SkillState.SUCCEEDED, outcome=out),
        m.Abort(reason="test", task_id="t1"), m.AbortAck(abort_stamp_ns=1, goal_id="g1"),
        m.ReasoningStep(task_id="t1", step=1, prompt={"command": "pick"}, drt=drt,
                        ste=m.SkillToExecute(skill="obj_localization", argument="red cup"),
                        calls=(m.ModelCall(raw_answer="{}", valid=False, error="no skill"),
                               m.ModelCall(raw_answer="{...}", valid=True, latency_s=0.9, tokens_in=10)),
                        valid=True, retries=1, skill_state=m.SkillState.SUCCEEDED, outcome=out),
        m.TaskRequest(command="pick up the red cup and place it on the table", variant="drt_v2"),
        m.TaskAccept(accepted=False, reason="busy"),
        m.TaskStatus(task_id="t1", command="pick", state=m.TaskState.RUNNING),
        m.TaskRequest(command="pick up the red cup", resume=m.Resume(
            origin=m.ForkOrigin(log="aermani-1.mcap", task_id="t0", step=3),
            history=(m.ResumeStep(step=1, skill="obj_localization", argument="red cup", state="succeeded",
                                  outcome=out), m.ResumeStep(step=2, skill="(invalid answer)")))),
        m.TaskStatus(task_id="t2", command="pick", state=m.TaskState.SUCCEEDED,
                     forked_from=m.ForkOrigin(log="aermani-1.mcap", task_id="t0", step=3)),
        m.SimState(task_id="t0", step=2, skill="grasp", sim_time_s=12.5, state='{"format": 1}'),
        m.MemoryRestore(task_id="t2", memory=m.WorkingMemory(held_object="red cup"), taken_ns=123),
        m.Health(service="sim", ok=True, details={"fps": 15.2}),
        m.Heartbeat(service="executor", pid=4242, loop_lag_ms=0.8),
        m.Scenario(seed=3, target_object="red cup", destination="table", target_out_of_view=True,
                   criteria=m.JudgeCriteria(rest_s=3.0, upright_tolerance_deg=15.0)),
        m.SimLabels(labels=(m.SimLabel(id=1, name="red cup", category="object", color="red"),)),
        m.JudgeRequest(op="on_surface", object="red cup", surface="table"),
        m.JudgeResult(objects=(m.SimObjectTruth(name="red cup", category="object", position=m.Vec3(),
                                                size=m.Vec3(x=0.08, y=0.08, z=0.11)),),
                      collisions=("vehicle-shelf", "gripper-table", "knocked-apple", "dropped-red cup"),
                      incidents=(m.SimIncident(kind="vehicle", thing="shelf", t_s=3.5, detail="0.20 m/s"),
                                 m.SimIncident(kind="dropped", thing="red cup", t_s=41.0,
                                               detail="fell 0.95 m after leaving the pads")),
                      sim_time_s=41.25),
        m.JudgeResult(ok=False, message="red cup at rest for only 1.20 s (needs 2.00 s)", pending_s=0.8,
                      checks=(m.JudgeCheck(name="upright", ok=True, detail="tilt 2 deg", measured=2.0, limit=20.0,
                                           unit="deg"),
                              m.JudgeCheck(name="rest", ok=False, measured=1.2, limit=2.0, unit="s"))),
        m.SimResetResult(ok=True, scenario=m.Scenario(seed=1)),
        m.CancelGoal(goal_id="goal-1", reason="operator changed their mind"),
        m.GoalRef(goal_id="goal-1"),
        m.CancelReply(accepted=False, reason="goal goal-1 is not running"),
        m.ResetNotice(seed=3),
        m.ApprovalStatus(skill="grasp", argument="red cup", reasoning="the cup is within reach", task_id="t1", step=4,
                         expires_ns=1),
        m.ApprovalDecision(approval_id="appr-1", approved=False, reason="wrong cup"),
    ]

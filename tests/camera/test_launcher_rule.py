"""The launcher's one-camera rule: the camera service starts only when configured, and then the simulator in
the same stack keeps its camera off while the bridge publishes world->base_link (explicit settings win)."""

from __future__ import annotations

from aermani.launcher import Stack, available_services, camera_configured, default_services


def test_camera_is_started_only_when_configured():
    assert "camera" in available_services()
    assert "camera" not in default_services({})
    assert "camera" not in default_services({"AERMANI_CAMERA_SOURCE": "none"})
    assert "camera" in default_services({"AERMANI_CAMERA_SOURCE": "realsense"})
    assert camera_configured({"AERMANI_CAMERA_SOURCE": " ZED "}) and not camera_configured({})


def test_a_configured_camera_turns_the_simulators_camera_off(tmp_path, monkeypatch):
    for var in ("AERMANI_CAMERA_SOURCE", "AERMANI_SIM_CAMERA", "AERMANI_AUTOPILOT_BRIDGE_PUBLISH_TF"):
        monkeypatch.delenv(var, raising=False)
    names = ["sim", "camera", "autopilot_bridge", "perception"]
    stack = Stack(names, env={"AERMANI_CAMERA_SOURCE": "file"}, log_dir=tmp_path, router=False)
    for name in names:
        env = stack.find(name).env
        assert env["AERMANI_SIM_CAMERA"] == "false" and env["AERMANI_AUTOPILOT_BRIDGE_PUBLISH_TF"] == "true"
    assert stack.find("camera").label == "am1/camera"

    idle = Stack(names, env={"AERMANI_CAMERA_SOURCE": "none"}, log_dir=tmp_path, router=False)
    assert "AERMANI_SIM_CAMERA" not in idle.find("sim").env

    explicit = Stack(names, env={"AERMANI_CAMERA_SOURCE": "file", "AERMANI_SIM_CAMERA": "true"}, log_dir=tmp_path,
                     router=False)
    assert explicit.find("sim").env["AERMANI_SIM_CAMERA"] == "true"

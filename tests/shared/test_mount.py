"""One mount definition (`AERMANI_MOUNT_*`): the executor, the simulator's vehicle and tf, and the camera
service all take the camera and gripper frames from it; bad values are refused with the variable named."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from shared.frames import Mount, base_to_camera, base_to_gripper
from shared.launcher import free_udp_port
from shared.sensors import parse_transforms

MOUNT_ENV = {"AERMANI_MOUNT_CAMERA_OFFSET": "0.2, 0.01, -0.08", "AERMANI_MOUNT_CAMERA_PITCH_DEG": "50",
             "AERMANI_MOUNT_GRIPPER_OFFSET": "[0.05, 0, -0.3]"}


@pytest.fixture
def mount_env(monkeypatch):
    for k, v in MOUNT_ENV.items():
        monkeypatch.setenv(k, v)


def test_defaults_are_the_simulators_airframe(monkeypatch):
    for k in MOUNT_ENV:
        monkeypatch.delenv(k, raising=False)
    m = Mount()
    assert np.allclose(m.base_to_camera(), base_to_camera()) and np.allclose(m.base_to_gripper(), base_to_gripper())
    for k in MOUNT_ENV:
        monkeypatch.setenv(k, "")  # compose passes unset variables as empty strings
    assert Mount() == m


def test_bad_values_name_the_field(monkeypatch):
    monkeypatch.setenv("AERMANI_MOUNT_CAMERA_OFFSET", "0.2,0")
    with pytest.raises(ValidationError, match="camera_offset[\\s\\S]*three numbers"):
        Mount()


def test_every_consumer_uses_the_one_mount(mount_env):
    from services.executor.envelope import DepthClearance
    from services.executor.settings import ExecutorSettings
    from services.sim.app import CameraPublisher, build
    from services.sim.settings import SimSettings
    from shared.frames import DEFAULT_INTRINSICS

    m = Mount()
    ex = ExecutorSettings()
    assert ex.gripper_offset_z == -0.3 and ex.camera_pitch_deg == 50.0
    assert np.allclose(DepthClearance(DEFAULT_INTRINSICS, mount=ex.mount).base_from_camera, m.base_to_camera())

    sim = SimSettings(camera=False, api_local_port=free_udp_port(), gcs_enabled=False)
    core, server = build(sim)  # binds its MAVLink socket: a free port, closed below
    try:
        assert core.vehicle.params.gripper_offset == (0.05, 0.0, -0.3)
        publisher = CameraPublisher(None, core, sim)  # camera off: no renderer is started
        tf = parse_transforms(publisher.transforms(core.snapshot(), 1))
    finally:
        server.stop()
    assert np.allclose(tf[("base_link", "camera")][1], m.base_to_camera())
    assert np.allclose(tf[("base_link", "gripper")][1][:3, 3], (0.05, 0.0, -0.3))
    cam = m.base_to_camera()
    assert math.isclose(math.degrees(math.asin(-cam[2, 2])), 50.0, abs_tol=1e-6)  # optical axis 50 deg down

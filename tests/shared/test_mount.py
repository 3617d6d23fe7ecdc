"""One mount definition (`AERMANI_MOUNT_*`): the executor, the simulator's vehicle and tf, and the camera
service all take the camera and gripper frames from it; bad values are refused with the variable named."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from aermani.launcher import free_udp_port
from shared.frames import Mount, base_to_camera, base_to_gripper
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


def test_executor_and_camera_service_use_the_one_mount(mount_env):
    from services.camera.service import Capturer
    from services.camera.settings import CameraSettings
    from services.camera.sources import make_source
    from services.executor.envelope import DepthClearance
    from services.executor.settings import ExecutorSettings
    from shared.frames import DEFAULT_INTRINSICS

    m = Mount()
    ex = ExecutorSettings()
    assert ex.gripper_offset_z == -0.3 and ex.camera_pitch_deg == 50.0
    assert np.allclose(DepthClearance(DEFAULT_INTRINSICS, mount=ex.mount).base_from_camera, m.base_to_camera())
    cam = CameraSettings(source="mcap", path=__file__)
    mounts = Capturer(make_source(cam), cam, lambda _: None).mounts
    assert np.allclose(mounts[0][2], m.base_to_camera()) and np.allclose(mounts[1][2][:3, 3], (0.05, 0.0, -0.3))
    assert math.isclose(math.degrees(math.asin(-m.base_to_camera()[2, 2])), 50.0, abs_tol=1e-6)  # 50 deg down


def test_the_simulator_refuses_a_mount_its_airframe_does_not_have(mount_env):
    from services.sim.app import build
    from services.sim.settings import SimSettings
    from shared.errors import ConfigError

    with pytest.raises(ConfigError, match="unset AERMANI_MOUNT_\\* when flying the simulator"):
        build(SimSettings(camera=False, api_local_port=free_udp_port(), gcs_enabled=False))


def test_the_simulator_publishes_its_airframe_on_tf(monkeypatch):
    from services.sim.app import AIRFRAME, CameraPublisher
    from services.sim.core import Snapshot

    for k in MOUNT_ENV:
        monkeypatch.setenv(k, "")  # compose's empty variables are the defaults
    tf = parse_transforms(CameraPublisher.transforms(
        Snapshot(version=0, xml="", qpos=np.zeros(0), geom_instance=np.zeros(0, dtype=int),
                 position=np.zeros(3), yaw=0.0), 1))  # the real snapshot type, so a new field cannot be missed
    assert np.allclose(tf[("base_link", "camera")][1], Mount().base_to_camera())
    assert np.allclose(tf[("base_link", "gripper")][1], AIRFRAME.base_to_gripper())

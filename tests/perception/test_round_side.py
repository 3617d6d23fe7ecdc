"""A round object whose top is not in its mask (a can's bare lid, a bottle's cap and shoulder) is seen as its
near side only: the footprint's circle, not the rectangle around the arc (which sat ~2.4 cm nearer the camera
than a can's axis, and 2 cm across instead of 6.6)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.perception import query as q
from services.perception.geometry import round_from_side, upright_box
from services.perception.pipeline import Perception
from services.perception.segmenters import make_segmenter
from services.perception.settings import PerceptionSettings
from services.sim.physics import World
from shared.messages import LocalizeRequest
from tests.perception.scenes import _versions, furniture, manual_world, render_view, thing

CAMERA = np.array([0.0, 0.0])


def _fit(xy: np.ndarray) -> tuple[np.ndarray, float] | None:
    pts = np.column_stack([xy, np.zeros(len(xy))])
    cxy, yaw, lw = upright_box(pts)
    return round_from_side(pts, CAMERA, cxy, yaw, lw)


def test_the_near_arc_of_a_cylinder_gives_its_axis_and_radius() -> None:
    rng = np.random.default_rng(0)
    centre, r = np.array([0.3, 0.05]), 0.033
    # the half facing the camera (at the origin), with a millimetre of noise
    facing = math.atan2(-centre[1], -centre[0])
    ang = facing + rng.uniform(-math.pi / 2 + 0.2, math.pi / 2 - 0.2, 400)
    xy = centre + r * np.column_stack([np.cos(ang), np.sin(ang)]) + rng.normal(0, 0.001, (400, 2))
    found = _fit(xy)
    assert found is not None
    assert np.linalg.norm(found[0] - centre) < 0.003 and abs(found[1] - r) < 0.003, found


def test_box_faces_and_a_whole_ring_are_left_to_the_rectangle() -> None:
    rng = np.random.default_rng(1)
    # two faces of a 16 x 7 cm box seen across a corner: an L, which a circle fits badly
    a = np.column_stack([rng.uniform(0, 0.16, 300), np.zeros(300)])
    b = np.column_stack([np.zeros(150), rng.uniform(0, 0.07, 150)])
    corner = np.array([0.4, -0.05])
    rot = np.array([[math.cos(0.6), -math.sin(0.6)], [math.sin(0.6), math.cos(0.6)]])
    xy = np.vstack([a, b]) @ rot.T + corner + rng.normal(0, 0.001, (450, 2))
    assert _fit(xy) is None
    # a cup's whole rim (its top in view): square already, the rectangle's centre is the axis
    ang = rng.uniform(-math.pi, math.pi, 400)
    assert _fit(np.array([0.3, 0.0]) + 0.04 * np.column_stack([np.cos(ang), np.sin(ang)])) is None


@pytest.mark.parametrize("name", ["coke can", "green bottle"])
def test_a_can_and_a_bottle_from_grasp_height_are_localized_on_their_axis(name: str) -> None:
    table = furniture("table", 2.0, 0.0)
    obj = thing(name, 1.8, 0.1, table)
    world = World(entities=manual_world(table, obj).entities, version=next(_versions), look="textured")
    top = obj.center[2] + obj.size[2] / 2
    s = PerceptionSettings(segmenter="color")
    p = Perception(make_segmenter(s), s)
    # the grasp's last view: the gripper point 0.3 m behind, a quarter of the height below the top
    for yaw in (0.0, 2.0):
        x, y = obj.center[0] - 0.3 * math.cos(yaw), obj.center[1] - 0.3 * math.sin(yaw)
        view = render_view(world, x, y, top - obj.size[2] / 4 + 0.22, yaw)
        est = p.localize_object(view.frame, LocalizeRequest(query=name), q.parse(name))
        assert est.found and est.pose is not None and est.size is not None, est.message
        err = math.hypot(est.pose.position.x - obj.center[0], est.pose.position.y - obj.center[1])
        assert err < 0.006, (yaw, err)
        assert abs(min(est.size.x, est.size.y) - obj.size[0]) < 0.01, (yaw, est.size)

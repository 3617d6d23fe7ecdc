"""The grasp's alignment window (`in_window`): along the pads' width and across them, in the body frame, and with a
lead the point where the present velocity carries the gripper must be inside too (benchmarks/close_timing.py)."""

from __future__ import annotations

import math

import pytest

from services.executor.skills.manipulation import in_window

WINDOW = (0.018, 0.03)  # the executor's defaults: along the pad width (body x), along the closing axis (body y)


@pytest.mark.parametrize(("ex", "ey", "yaw", "inside"), [
    (0.015, 0.025, 0.0, True),
    (0.020, 0.0, 0.0, False),  # past the pad-width window
    (0.0, 0.032, 0.0, False),  # past the closing-axis window
    (0.025, 0.0, math.pi / 2, True),  # facing north, world x is across the pads: 3 cm allowed
    (0.0, 0.025, math.pi / 2, False),  # and world y along them: 1.8 cm
    (-0.012, -0.012, math.pi / 4, True),  # 1.7 cm along the pads at 45 deg
    (0.015, 0.015, math.pi / 4, False),  # 2.1 cm along them
])
def test_window_is_in_the_body_frame(ex: float, ey: float, yaw: float, inside: bool) -> None:
    assert in_window(ex, ey, 0.0, 0.0, yaw, WINDOW) is inside
    assert in_window(ex, ey, 0.0, 0.0, yaw, WINDOW, lead=0.4) is inside  # standing still: the lead changes nothing


def test_lead_holds_back_a_close_while_drifting_out() -> None:
    # 1 cm short of the object along the pads, the gripper moving away from it at 3 cm/s: inside now, 2.2 cm out
    # when the pads arrive.
    assert in_window(0.01, 0.0, -0.03, 0.0, 0.0, WINDOW)
    assert not in_window(0.01, 0.0, -0.03, 0.0, 0.0, WINDOW, lead=0.4)


def test_lead_lets_a_close_through_while_drifting_in() -> None:
    # The same offset, the gripper moving toward the object: inside now and ahead.
    assert in_window(0.01, 0.0, 0.03, 0.0, 0.0, WINDOW, lead=0.4)
    # Moving fast enough to overshoot the window on the far side: held back too.
    assert not in_window(0.01, 0.0, 0.08, 0.0, 0.0, WINDOW, lead=0.4)


def test_lead_applies_across_the_pads_too() -> None:
    assert in_window(0.0, 0.02, 0.0, 0.0, 0.0, WINDOW, lead=0.4)
    assert not in_window(0.0, 0.02, 0.0, -0.05, 0.0, WINDOW, lead=0.4)  # 4 cm across when the pads arrive

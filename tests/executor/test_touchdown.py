"""Place's touch-down detector on descent traces sampled at the bridge's 50 Hz: a held object that reaches the
surface above the planned release height stops the vehicle's descent, and that, not a descent that merely
slows into its target or a hover's wander, is what it reports."""

from __future__ import annotations

import numpy as np

from services.executor.skills.manipulation import TouchDown
from shared.messages import Vec3, VehicleState

DT_NS = 20_000_000


def run(zs, holding: bool | None = True, target: float = 1.0) -> tuple[bool, int]:
    """Feed the heights in order; (touched down, at which sample)."""
    touch = TouchDown(target)
    for i, z in enumerate(zs):
        if touch(VehicleState(stamp_ns=10**18 + i * DT_NS, position=Vec3(x=0.0, y=0.0, z=float(z)),
                              gripper_holding=holding)):
            return True, i
    return False, len(zs)


def test_a_descent_that_stalls_above_its_target_touched_down():
    # 0.25 m/s from 1.5 m, the object meeting the surface with the vehicle at 1.14 m (14 cm above its target)
    zs = list(np.maximum(1.5 - 0.25 * 0.02 * np.arange(150), 1.14))
    down, at = run(zs)
    assert down
    assert (at - zs.index(1.14)) * 0.02 <= 0.8  # within the window after the stall


def test_a_descent_into_its_target_or_a_hover_there_is_not_a_touch_down():
    zs = list(np.maximum(1.5 - 0.25 * 0.02 * np.arange(150), 1.0))  # arrives and hovers on the target
    assert not run(zs)[0]
    rng = np.random.default_rng(3)  # hovering on it with the estimate's wander
    assert not run(list(1.0 + 0.005 * rng.standard_normal(200)))[0]


def test_a_descent_that_is_only_slow_or_has_let_go_is_not_a_touch_down():
    assert not run(list(1.5 - 0.1 * 0.02 * np.arange(200)))[0]  # 10 cm/s, the final descent's speed
    zs = list(np.maximum(1.5 - 0.25 * 0.02 * np.arange(150), 1.14))
    assert not run(zs, holding=False)[0]  # nothing in the gripper: no object to stand on the surface
    assert run(zs, holding=None)[0]  # a gripper without sensing: the stall alone


def test_a_stall_far_above_the_target_is_something_else():
    zs = list(np.maximum(1.5 - 0.25 * 0.02 * np.arange(150), 1.3))  # 30 cm above: not an object touching down
    assert not run(zs)[0]

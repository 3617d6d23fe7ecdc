"""What a closed gripper's finger gap says about the hold (`Grasp.hold_problem`): something else in the fingers,
or a round object pinched on a chord at the pads' edge, which falls out in transit (dev grasp runs: held 0.3-1.8 cm
narrower than its catalogued diameter)."""

from __future__ import annotations

import pytest

from services.executor.registry import build_library
from services.executor.settings import ExecutorSettings
from services.executor.skills.manipulation import lying_by_catalog
from shared.messages import OutcomeCode, Vec3

CAN = Vec3(x=0.066, y=0.066, z=0.12)  # perception's catalogue, standing: x long, y short, z tall
CUP = Vec3(x=0.08, y=0.08, z=0.11)
CRACKER_BOX = Vec3(x=0.16, y=0.07, z=0.21)
HAMMER = Vec3(x=0.33, y=0.1, z=0.035)


@pytest.fixture(scope="module")
def grasp():  # type: ignore[no-untyped-def]
    return build_library(ExecutorSettings(), ["grasp"])["grasp"]


@pytest.mark.parametrize(("width", "measured", "catalog", "code"), [
    (0.067, Vec3(x=0.07, y=0.068, z=0.12), CAN, None),  # held across its diameter (the pads squeeze 1 mm less)
    (0.066, None, CAN, None),  # no measurement: the catalogue alone
    (0.063, Vec3(x=0.07, y=0.068, z=0.12), CAN, OutcomeCode.MISALIGNED),  # within perception's error only
    (0.063, None, CAN, OutcomeCode.MISALIGNED),
    (0.062, Vec3(x=0.075, y=0.074, z=0.11), CUP, OutcomeCode.MISALIGNED),
    (0.079, Vec3(x=0.075, y=0.074, z=0.11), CUP, None),
    (0.110, None, CUP, None),  # a cup lying with its axis across the pads: wider than its diameter, not a chord
    (0.070, Vec3(x=0.16, y=0.07, z=0.21), CRACKER_BOX, None),  # not round: a box is held across its short side
    (0.035, None, HAMMER, None),  # thin things are held at gaps their boxes do not predict
    (0.020, Vec3(x=0.07, y=0.068, z=0.12), CAN, OutcomeCode.MISSED),  # far narrower than it measures: something else
    (0.063, Vec3(x=0.07, y=0.068, z=0.12), None, None),  # uncatalogued: only the measured check
])
def test_hold_problem(grasp, width: float, measured: Vec3 | None, catalog: Vec3 | None,  # type: ignore[no-untyped-def]
                      code: OutcomeCode | None) -> None:
    problem = grasp.hold_problem("object", width, measured, catalog)
    assert (problem[0] if problem else None) == code, problem
    if code == OutcomeCode.MISALIGNED:
        assert "reopened" in problem[1]


@pytest.mark.parametrize(("height", "catalog", "lying"), [
    (0.21, Vec3(x=0.16, y=0.07, z=0.21), False),  # a cracker box standing
    (0.19, Vec3(x=0.16, y=0.07, z=0.21), False),  # ... read 2 cm short
    (0.16, Vec3(x=0.16, y=0.07, z=0.21), True),  # on its 7 x 21 cm side (dev seed 23)
    (0.07, Vec3(x=0.16, y=0.07, z=0.21), True),  # flat on its wide side
    (0.12, CAN, False),
    (0.066, CAN, True),
    (0.08, CUP, False),  # 11 cm standing, 8 lying: too close to tell by height (the held-height rule decides)
    (0.24, Vec3(x=0.24, y=0.12, z=0.10), True),  # a tissue box on its end
    (0.12, Vec3(x=0.24, y=0.12, z=0.10), False),  # on its side it is 12 cm tall, 2 cm from standing: not told
    (0.035, HAMMER, False),  # thin: lies as it belongs
    (0.10, None, False),
])
def test_lying_by_catalog(height: float, catalog: Vec3 | None, lying: bool) -> None:
    assert lying_by_catalog(height, catalog) is lying

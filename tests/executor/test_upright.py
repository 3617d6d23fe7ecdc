"""Standing or lying, from the finger gap at the grasp and the object's catalogued extent (the colour
segmenter's catalogue, the one perception reports with every estimate)."""

from __future__ import annotations

import pytest

from services.executor.skills.manipulation import upright_by_shape, upright_by_width
from services.perception.segmenters.color import DEFAULT_OBJECTS
from shared.messages import Vec3


def catalog(name: str) -> Vec3:
    c = next(c for c in DEFAULT_OBJECTS if c.name == name)
    return Vec3(x=max(c.dims[:2]), y=min(c.dims[:2]), z=c.dims[2])


@pytest.mark.parametrize(("name", "width", "upright"), [
    ("tissue box", 0.1200, True),  # the gap the simulator's gripper reports on it standing (dev runs)
    ("tissue box", 0.0999, False),  # on its side or on its end: held across its 10 cm height
    ("cardboard box", 0.1606, True),  # 22 x 16 x 15 cm: 1 cm between standing and lying still tells
    ("cardboard box", 0.1500, False),
    ("cracker box", 0.0700, None),  # 16 x 7 x 21 cm: on its 7 x 21 cm side it is held at 7 cm too
    ("cracker box", 0.1600, False),  # on its wide side
    ("red cup", 0.0800, None),  # round: its diameter standing or lying
    ("tissue box", 0.1400, None),  # matches no extent: not a measurement of this box's pose
    ("banana", 0.0400, None),  # thin things lie flat as they belong; their gaps do not follow their boxes
    ("hammer", 0.0350, None),
])
def test_upright_by_width(name: str, width: float, upright: bool | None) -> None:
    assert upright_by_width(width, catalog(name)) is upright


def test_no_catalogue_no_verdict() -> None:
    assert upright_by_width(0.10, None) is None


@pytest.mark.parametrize(("name", "measured", "upright"), [
    ("red cup", (0.08, 0.07, 0.11), True),  # as dev localizations at 0.3-0.8 m measure standing cups
    ("red cup", (0.11, 0.06, 0.08), False),  # the toppled cup of dev localization/028
    ("red cup", (0.06, 0.02, 0.08), None),  # a partial view
    ("coke can", (0.12, 0.066, 0.066), False),
    ("green bottle", (0.07, 0.07, 0.22), True),
    ("tissue box", (0.24, 0.12, 0.10), None),  # not round: the finger gap tells for a box
    ("apple", (0.08, 0.08, 0.08), None),  # a ball is the same any way up
])
def test_upright_by_shape(name: str, measured: tuple[float, float, float], upright: bool | None) -> None:
    assert upright_by_shape(Vec3(x=measured[0], y=measured[1], z=measured[2]), catalog(name)) is upright

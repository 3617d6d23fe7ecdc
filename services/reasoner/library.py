"""The static default skill library (for `aermani vlm check` and tests) and the Skill Library prompt text.

The live loop always uses the executor's registry (`executor/skills`); this copy only mirrors the names
in shared/skills.py so that offline tools work without a running executor.
"""

from __future__ import annotations

from shared import skills as S  # noqa: N812 - reads like the paper tables
from shared.messages import SkillLibrary, SkillSpec

_DESCRIPTIONS: dict[str, tuple[str, str, str | None, bool]] = {
    S.YAW_LEFT: ("motion", "Rotate left (counter-clockwise) about the body z-axis by a fixed angle, to look around.",
                 None, False),
    S.YAW_RIGHT: ("motion", "Rotate right (clockwise) about the body z-axis by a fixed angle, to look around.",
                  None, False),
    S.FORWARD: ("motion", "Translate forward along the body x-axis by a fixed distance, to approach a target.",
                None, False),
    S.BACKWARD: ("motion", "Translate backward along the body x-axis by a fixed distance, to retreat.", None, False),
    S.LEFT: ("motion", "Translate left along the body y-axis by a fixed distance, to correct lateral misalignment.",
             None, False),
    S.RIGHT: ("motion", "Translate right along the body y-axis by a fixed distance, to correct lateral "
              "misalignment.", None, False),
    S.UP: ("motion", "Climb by a fixed height, to gain clearance or see more of the scene.", None, False),
    S.DOWN: ("motion", "Descend by a fixed height, to reach manipulation height.", None, False),
    S.OBJ_LOCALIZATION: ("perception", "Estimate the 3D pose of the queried object (open-vocabulary segmentation "
                         "fused with depth) and store it in working memory.", "object query", True),
    S.GRASP: ("manipulation", "Approach the localized object with yaw alignment, close the gripper and retreat "
              "to a safe height.", "object label (optional; defaults to the last localized object)", False),
    S.PLACEMENT_LOCALIZATION: ("perception", "Find the queried support surface and compute a collision-free "
                               "placement pose with a vertical offset.", "surface query", True),
    S.PLACE: ("manipulation", "Descend to the placement pose, open the gripper and retreat to a safe hover.",
              None, False),
    S.DONE: ("control", "Declare the task complete; the episode ends.", None, False),
    S.TAKEOFF: ("operator", "Arm and take off to the working altitude.", None, False),
    S.LAND: ("operator", "Land at the current position.", None, False),
    S.HOLD: ("operator", "Hold position.", None, False),
}


def default_library() -> SkillLibrary:
    """A SkillLibrary built from shared/skills.py names, for offline checks."""
    specs = []
    for name in (*S.POLICY_SKILLS, *S.OPERATOR_SKILLS):
        category, description, argument, required = _DESCRIPTIONS[name]
        specs.append(SkillSpec(name=name, category=category, description=description, argument=argument,
                               argument_required=required, policy_visible=name not in S.OPERATOR_SKILLS))
    return SkillLibrary(skills=tuple(specs))


def policy_skills(library: SkillLibrary) -> list[SkillSpec]:
    """Skills offered to the model, in registry order."""
    return [s for s in library.skills if s.policy_visible]


def signature(spec: SkillSpec) -> str:
    if spec.argument is None:
        return spec.name
    return f"{spec.name}(<{spec.argument}>)" if spec.argument_required else f"{spec.name}([{spec.argument}])"


def library_text(library: SkillLibrary) -> str:
    """The Skill Library part: one line per policy-visible skill with its fixed parameters."""
    lines = []
    for spec in policy_skills(library):
        params = ", ".join(f"{p.name}={p.value}{p.unit}" for p in spec.parameters)
        lines.append(f"- {signature(spec)}: {spec.description}" + (f" ({params})" if params else ""))
    return "\n".join(lines)

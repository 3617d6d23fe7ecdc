"""The Descriptive Reasoning Trace's fields: which ones each prompt variant asks for (paper Sec. III, the
ablation DRT v1-v3 and full) and what each holds. Read by the prompt, the answer schema, the parser and the rules
baseline."""

from __future__ import annotations

DRT_FIELDS: dict[str, tuple[str, ...]] = {
    "unstructured": (),
    "no_drt": (),
    "drt_v1": ("image_description",),
    "drt_v2": ("image_description", "summary"),
    "drt_v3": ("image_description", "summary", "action_predictions"),
    "full": ("image_description", "summary", "action_predictions", "reasoning"),
    "react": (),
    # The Table III baselines (baselines.py) have no reasoning trace.
    "saycan": (),
    "direct": (),
    "waypoint": (),
    "plan_once": (),
}

FIELD_HELP = {
    "image_description": "what is visible in the current image: objects, their spatial arrangement, cues",
    "summary": "a short recap of previous observations and executed skills",
    "action_predictions": "an object with one entry per available skill name, each the predicted outcome of "
                          "executing that skill now",
    "reasoning": "why the chosen skill is the right next step, from the observation, history and predictions",
}

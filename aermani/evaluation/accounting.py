"""What a run's services ran with, for run_config.json and the report: every AERMANI_* variable of the shell (a
secret only as set), which of them the run overrides, and the effective values of the settings that shape the
numbers, read by each service's own settings class from the environment the services get."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any
from unittest import mock

SECRET_WORDS = ("KEY", "TOKEN", "SECRET", "PASSWORD")
NOT_RECORDED = "(set, not recorded)"


def masked(env: Mapping[str, str]) -> dict[str, str]:
    """The AERMANI_* variables of `env`, sorted, a secret's value replaced by NOT_RECORDED."""
    return {k: NOT_RECORDED if any(w in k for w in SECRET_WORDS) else v for k, v in sorted(env.items())
            if k.startswith("AERMANI_")}


def effective_settings(env: Mapping[str, str]) -> dict[str, Any]:
    """The settings that shape the numbers as the services read them from `env` (the shell's variables overlaid
    with the run's): the simulator's realism, dynamics (the vehicle's body: kinematic or multirotor) and speed
    factor, the reasoner's step cap, T_max, backend and answer decoding, perception's segmenter. A setting the
    services would refuse is recorded as the refusal."""
    from pydantic import ValidationError

    from services.perception.settings import PerceptionSettings
    from services.reasoner.settings import ReasonerSettings
    from services.sim.settings import SimSettings

    only = {k: v for k, v in env.items() if k.startswith("AERMANI_")}
    try:
        with mock.patch.dict(os.environ, only, clear=True):
            sim, reasoner, perception = SimSettings(), ReasonerSettings(), PerceptionSettings()
    except ValidationError as exc:
        return {"error": f"the services would refuse these settings: {exc}"[:2000]}
    return {"realism": sim.realism, "dynamics": sim.dynamics, "speed_factor": sim.speed_factor,
            "step_cap": reasoner.max_steps, "t_max_s": reasoner.t_max_s, "backend": reasoner.backend,
            "output_mode": reasoner.output_mode, "segmenter": perception.segmenter}

from __future__ import annotations

import pytest
from pydantic import TypeAdapter, ValidationError

from shared import messages as m
from shared.keys import Keys, alive_pattern, parse_alive_key, vehicle_prefix
from tests.shared.samples import sample_messages


def test_every_message_type_has_a_sample_and_round_trips_json():
    samples = sample_messages()
    assert {type(s) for s in samples} == set(m.MESSAGE_TYPES)
    for s in samples:
        again = type(s).model_validate_json(s.model_dump_json())
        assert again == s
        assert s.schema_version == m.SCHEMA_VERSION


def test_models_are_frozen_and_strict():
    st = m.VehicleState()
    with pytest.raises(ValidationError):
        st.armed = True  # type: ignore[misc]
    with pytest.raises(ValidationError):
        m.VehicleState.model_validate({"kind": "vehicle_state", "bogus": 1})


def test_autopilot_command_union_discriminates():
    ta = TypeAdapter(m.AutopilotCommand)
    cmd = ta.validate_json(m.GotoCommand(position=m.Vec3(x=1), yaw=0.5).model_dump_json())
    assert isinstance(cmd, m.GotoCommand)
    with pytest.raises(ValidationError):
        ta.validate_json(b'{"kind": "self_destruct"}')


def test_task_request_rejects_control_characters_and_empty():
    with pytest.raises(ValidationError):
        m.TaskRequest(command="pick\x00up")
    with pytest.raises(ValidationError):
        m.TaskRequest(command="   ")
    with pytest.raises(ValidationError):
        m.TaskRequest(command="x" * (m.MAX_COMMAND_CHARS + 1))


def test_json_schemas_have_field_docs():
    schema = m.ReasoningStep.model_json_schema()
    assert schema["properties"]["calls"]["description"].startswith("Every model call")


def test_keys():
    k = Keys("am2")
    assert k.autopilot_state == "aermani/v1/am2/autopilot/state"
    assert k.alive("executor") == "aermani/v1/am2/alive/executor"
    assert parse_alive_key(k.alive("sim")) == ("am2", "sim")
    assert alive_pattern() == "aermani/v1/*/alive/*"
    with pytest.raises(ValueError):
        vehicle_prefix("a/b")
    with pytest.raises(ValueError):
        vehicle_prefix("**")

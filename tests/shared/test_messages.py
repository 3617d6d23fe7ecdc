from __future__ import annotations

import pytest
from pydantic import TypeAdapter, ValidationError

from shared import messages as m
from shared.keys import Keys, alive_pattern, parse_alive_key, vehicle_prefix
from tests.helpers import matched
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
    # Invisible formatting: what the operator reads is not what the reasoner would act on.
    for hidden in ("\u202e", "\u200b", "\u2066", "\ufeff", "\x85"):
        with pytest.raises(ValidationError, match=f"U\\+{ord(hidden):04X}"):
            m.TaskRequest(command=f"pick up the red{hidden} cup")
    # Half an emoji (an HTTP client's JSON `\ud83d`): refused by the string check, and by command_text itself.
    with pytest.raises(ValidationError, match="unicode"):
        m.TaskRequest(command="pick up the red\ud83d cup")
    with pytest.raises(ValueError, match="U\\+D83D"):
        m.command_text("pick up the red\ud83d cup")
    assert m.TaskRequest(command="  put the café mug in the sink\t").command == "put the café mug in the sink"
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


def test_non_finite_and_unphysical_values_are_refused():
    for bad in ('{"x": NaN}', '{"x": Infinity}', '{"z": -Infinity}', '{"x": 1e9}'):
        with pytest.raises(ValidationError):
            m.Vec3.model_validate_json(bad)
    with pytest.raises(ValidationError):
        m.VehicleState(position=m.Vec3(x=float("nan")))
    with pytest.raises(ValidationError, match="exceeds 50 m/s"):
        m.VehicleState(velocity=m.Vec3(x=120.0))
    for field, value in (("battery_remaining", 140.0), ("battery_remaining", -1.0), ("battery_voltage", 400.0),
                         ("yaw", 40.0), ("stamp_ns", -5)):
        with pytest.raises(ValidationError):
            m.VehicleState(**{field: value})
    with pytest.raises(ValidationError):
        m.GotoCommand(position=m.Vec3(x=1.0), yaw=float("nan"))
    with pytest.raises(ValidationError):
        m.GotoCommand(position=m.Vec3(x=1.0), yaw=0.0, max_speed=500.0)


def test_an_empty_or_partial_vehicle_state_is_refused_on_the_wire():
    ta = TypeAdapter(m.VehicleState)
    with pytest.raises(ValidationError, match="must carry"):
        ta.validate_json(b"{}")
    with pytest.raises(ValidationError, match="missing \\['position'"):
        ta.validate_json(b'{"kind": "vehicle_state", "stamp_ns": 1, "vehicle_id": "am1", "velocity": {}, '
                         b'"armed": true, "landed_state": "in_air", "link_ok": true}')
    good = m.VehicleState(position=m.Vec3(z=1.0), armed=True)
    assert ta.validate_json(good.model_dump_json()) == good


async def test_empty_and_nan_vehicle_states_are_dropped_at_the_bus(router):
    """Over a real router: `{}`, a NaN position and a 300 m/s state are counted as malformed and never reach
    the subscriber; the valid state behind them does."""

    from shared.bus import Bus

    a = await Bus.open(connect=[router])
    b = await Bus.open(connect=[router])
    try:
        state = Keys("t1").autopilot_state
        sub = b.subscribe(state)
        await matched(a, state)
        good = m.VehicleState(vehicle_id="t1", position=m.Vec3(z=1.2), armed=True)
        nan = good.model_dump_json().replace('"z":1.2', '"z":NaN')
        fast = good.model_dump_json().replace('"velocity":{"x":0.0', '"velocity":{"x":300.0')
        assert nan != good.model_dump_json() and fast != good.model_dump_json()
        for raw in (b"{}", nan.encode(), fast.encode(), good.model_dump_json().encode()):
            a.publish_raw(state.key, raw, "application/json;aermani.VehicleState")
        assert await sub.recv(timeout=5) == good
        assert sub.malformed == 3
    finally:
        await a.close()
        await b.close()

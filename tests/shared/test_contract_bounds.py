"""Every string and sequence of the contract is bounded (issue 32): a field added without a bound fails here, and
an oversized payload is refused with pydantic's error through the bus's own decode path."""

from __future__ import annotations

import enum
import json
import re
import sys
import types
import typing
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import annotated_types
import pytest
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from shared import keys as k
from shared import messages as m
from shared.bus import decoder
from shared.errors import DecodeError
from tests.shared.samples import sample_messages

# Values a type cannot bound, with why: each is held by the 1 MiB sample cap (shared.keys.MESSAGE_MAX_BYTES).
UNBOUNDED_VALUES_OK = {("Health", "details")}  # service-specific figures: dict[Label, Any] with a bounded count

_UNBOUNDED_QUANTIFIER = re.compile(r"(?<!\\)[*+]|\{\d*,\}")


def _bounds(metadata: list[Any]) -> tuple[bool, bool]:
    """(has max_length, has a bounding pattern) among pydantic/annotated-types metadata."""
    max_len = pattern = False
    for meta in metadata:
        if isinstance(meta, FieldInfo):
            a, b = _bounds(list(meta.metadata))
            max_len, pattern = max_len or a, pattern or b
        elif isinstance(meta, annotated_types.MaxLen):
            max_len = True
        elif isinstance(getattr(meta, "pattern", None), str):
            p = meta.pattern
            pattern = pattern or (p.startswith("^") and p.endswith("$") and not _UNBOUNDED_QUANTIFIER.search(p))
        elif getattr(meta, "max_length", None) is not None:
            max_len = True
    return max_len, pattern


def _problems(tp: Any, metadata: list[Any], where: str, seen: set[type]) -> list[str]:
    """Every unbounded str, sequence or mapping within type `tp` (nested models included)."""
    origin = get_origin(tp)
    if origin is Annotated:
        inner, *extra = get_args(tp)
        return _problems(inner, [*metadata, *extra], where, seen)
    if origin in (Union, types.UnionType):
        return [p for a in get_args(tp) if a is not type(None) for p in _problems(a, metadata, where, seen)]
    if origin is Literal or (isinstance(tp, type) and issubclass(tp, enum.Enum)):
        return []
    max_len, pattern = _bounds(metadata)
    if tp is str:
        return [] if max_len or pattern else [f"{where}: str without max_length or a bounding pattern"]
    if tp is typing.Any:
        return [f"{where}: Any"]
    if origin in (tuple, list, set, frozenset, dict):
        args = get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:  # a fixed-length tuple is bounded by its type
            out = []
        else:
            out = [] if max_len else [f"{where}: {origin.__name__} without max_length"]
            args = args[:-1] if origin is tuple else args
        for i, a in enumerate(args):
            part = ("key" if i == 0 else "value") if origin is dict else "item"
            out += _problems(a, [], f"{where}[{part}]", seen)
        return out
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        if tp in seen:
            return []
        seen.add(tp)
        out = []
        for name, field in tp.model_fields.items():
            ann = field.annotation
            if isinstance(ann, typing.ForwardRef):  # a field declared before its type (resolved by model_rebuild)
                ann = eval(ann.__forward_arg__, vars(sys.modules[tp.__module__]))  # noqa: S307
            found = _problems(ann, list(field.metadata), f"{tp.__name__}.{name}", seen)
            if (tp.__name__, name) in UNBOUNDED_VALUES_OK:
                found = [f for f in found if not f.endswith("[value]: Any")]
            out += found
        return out
    if tp in (int, float, bool, type(None)) or tp is bytes:
        return [] if tp is not bytes or max_len else [f"{where}: bytes without max_length"]
    return [f"{where}: unchecked type {tp!r}"]


def _contract_types() -> list[Any]:
    """Every message type: MESSAGE_TYPES, each declared key's types, and every model shared.messages defines."""
    found: list[Any] = list(m.MESSAGE_TYPES)
    for d in k.DECLARATIONS:
        for attr in ("type", "request", "reply"):
            t = getattr(d, attr, None)
            if t is not None and not isinstance(t, k.Protobuf | k.Json):
                found.append(t)
    found += [v for v in vars(m).values() if isinstance(v, type) and issubclass(v, BaseModel)
              and v.__module__ == m.__name__]
    return found


def test_the_walk_reaches_the_whole_contract():
    seen: set[type] = set()
    for t in _contract_types():
        _problems(t, [], "contract", seen)
    names = {t.__name__ for t in seen}
    assert {"VehicleState", "Detection", "ModelCall", "SimObjectTruth", "SkillFacts", "LocalizeAnswer"} <= names
    assert set(m.MESSAGE_TYPES) <= seen


def test_every_string_and_sequence_of_the_contract_is_bounded():
    problems: list[str] = []
    seen: set[type] = set()
    for t in _contract_types():
        problems += _problems(t, [], getattr(t, "__name__", "type"), seen)
    assert not problems, "unbounded fields (give each a max_length, a pattern or a Literal):\n" + "\n".join(problems)


def test_the_checker_catches_an_unbounded_field():
    class Loose(m.Message):
        name: str = ""
        tags: tuple[m.Label, ...] = ()
        items: tuple[Annotated[str, m.Field(max_length=3)], ...] = m.Field((), max_length=2)
        open_pattern: Annotated[str, m.Field(pattern=r"^a+$")] = "a"

    got = _problems(Loose, [], "Loose", set())
    assert got == ["Loose.name: str without max_length or a bounding pattern", "Loose.tags: tuple without max_length",
                   "Loose.open_pattern: str without max_length or a bounding pattern"]


def test_every_sample_fits_the_bounds():
    for s in sample_messages():
        assert type(s).model_validate_json(s.model_dump_json()) == s


@pytest.mark.parametrize(("model", "doc", "where"), [
    (m.TaskStatus, {"task_id": "t", "command": "c" * (m.MAX_COMMAND_CHARS + 1), "state": "running"}, "command"),
    (m.Detections, {"items": [{"label": "cup"}] * (m.MAX_DETECTIONS + 1)}, "items"),
    (m.ReasoningStep, {"task_id": "t", "step": 1, "calls": [{"raw_answer": "x" * (m.MAX_TRACE_CHARS + 1),
                                                             "valid": False}]}, "calls.0.raw_answer"),
    (m.SkillStatus, {"goal_id": "g/../../etc", "skill": "hold", "state": "running"}, "goal_id"),
    (m.Health, {"service": "s" * (m.MAX_NAME_CHARS + 1), "ok": True}, "service"),
])
def test_an_oversized_payload_is_refused_by_the_bus_decoder(model, doc, where):
    data = json.dumps(doc).encode()
    assert len(data) < k.MESSAGE_MAX_BYTES  # the contract's bound refuses it, not the byte cap
    with pytest.raises(DecodeError, match=rf"invalid {model.__name__} at {re.escape(where)}: "
                                          r"(String|Tuple|List|Dictionary) should (have at most|match pattern)"):
        decoder(model)(data)


def test_bounds_admit_what_the_services_send():
    """The largest legitimate values: a recorded answer at the parser's cap, a full library, a 200-entry memory."""
    from services.reasoner.parse import MAX_ANSWER_CHARS, recorded_answer

    answer = recorded_answer("x" * (MAX_ANSWER_CHARS + 5000))
    step = m.ReasoningStep(task_id="task-0123456789ab", step=1, calls=tuple(
        m.ModelCall(raw_answer=answer, valid=False, error=f"Unknown skill {answer!r}") for _ in range(11)))
    assert decoder(m.ReasoningStep)(step.model_dump_json().encode()) == step
    memory = m.WorkingMemory(executed=tuple(f"obj_localization({'y' * 200}): succeeded" for _ in range(200)))
    assert decoder(m.WorkingMemory)(memory.model_dump_json().encode()) == memory


def test_bounded_free_text_keeps_a_lone_surrogate_as_the_bus_writes_it():
    """pydantic-core refuses a lone surrogate in a length-bounded str: free text (a model's half emoji) is made
    well formed instead, so the step or status quoting it is not lost; an id holding one is refused."""
    st = m.TaskStatus(task_id="t", command="c", state=m.TaskState.FAILED, message="half \ud83d emoji")
    assert st.message == "half \ufffd emoji"
    call = m.ModelCall(raw_answer="\ud83d" * 3, valid=False)
    assert call.raw_answer == "\ufffd" * 3
    with pytest.raises(ValueError, match="task_id"):
        m.TaskStatus(task_id="t\ud83d", command="c", state=m.TaskState.FAILED)


def test_free_text_the_stack_builds_is_cut_to_its_bound_and_received_text_over_it_is_refused():
    """A status quoting a long exception or a model's whole answer must not be lost to its own bound: built in
    code it is cut with a note; the same text arriving off the wire is refused (a peer's payload is not edited)."""
    long = "y" * (3 * m.MAX_TEXT_CHARS)
    st = m.TaskStatus(task_id="task-1", command="pick up the red cup", state=m.TaskState.FAILED, message=long)
    assert len(st.message) == m.MAX_TEXT_CHARS and st.message.endswith(
        f"[{len(long)} characters, cut to {m.MAX_TEXT_CHARS}]")
    assert decoder(m.TaskStatus)(st.model_dump_json().encode()).message == st.message
    raw = st.model_copy(update={"message": long}).model_dump_json().encode()
    with pytest.raises(DecodeError, match="at message: String should have at most 10000 characters"):
        decoder(m.TaskStatus)(raw)
    drt = m.DescriptiveReasoningTrace(reasoning="r" * (m.MAX_TRACE_CHARS + 1))
    assert drt.reasoning is not None and len(drt.reasoning) == m.MAX_TRACE_CHARS

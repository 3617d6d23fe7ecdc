"""`aermani vlm probe`: check a model endpoint the way the reasoner will use it, and measure its RT.

With a camera frame (from a running stack's simulator, else from a simulator started for the probe, else a
generated room-like frame; the report says which) and the full-variant prompt of a first step, it checks:
the image is accepted, schema-constrained output is supported (or rejected, and free text works), answers
parse and validate against the skill library; then it makes N calls and reports the response time (RT, the
paper's measure) median and p95 and the tokens per call. Nothing moves: no skill is executed. The command and
the simulator started for its frame are the application's (aermani/probe.py): a service starts no other.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import asdict, dataclass, field

from services.reasoner.backends import make_backend
from services.reasoner.backends.base import ModelRequest
from services.reasoner.library import default_library
from services.reasoner.loop import policy_context
from services.reasoner.parse import parse_answer
from services.reasoner.prompt import History, Observation, PromptCompiler
from services.reasoner.settings import ReasonerSettings
from shared.errors import AermaniError, InvalidAnswer
from shared.messages import SkillLibrary

PROBE_COMMAND = "pick up the red cup and place it on the table"


@dataclass
class CallResult:
    """One probe call to a model endpoint: mode, whether it answered and validated, latency and tokens."""

    mode: str
    ok: bool
    """The endpoint answered (HTTP success)."""
    valid: bool
    """The answer parsed and validated against the skill library."""
    latency_s: float = 0.0
    tokens_in: int | None = None
    tokens_out: int | None = None
    tokens_cached: int | None = None
    answer: str = ""
    error: str = ""
    error_kind: str = ""
    """How the call failed (ModelError.kind): refused, schema, server or unreachable; empty when it answered."""


@dataclass
class ProbeReport:
    """Result of `aermani vlm probe`: the endpoint, what it accepted, and the calls' response times."""

    backend: str
    model: str
    base_url: str
    profile: str
    frame_source: str
    frame_bytes: int
    image_accepted: bool | None = False
    """True: a request with the image was answered; False: refused while the same request without it was
    answered; None: unknown (the server failed either way)."""
    schema_supported: bool | None = None
    """True: the server took the strict answer schema and answered under it; False: it refused it; None:
    unknown (the server failed for another reason)."""
    server_error: str = ""
    """Set when the endpoint failed whatever was asked (5xx, unreachable): not a verdict on image or schema."""
    text_mode_valid: bool | None = None
    mode_used: str = ""
    calls: list[CallResult] = field(default_factory=list)
    rt_median_s: float | None = None
    rt_p95_s: float | None = None
    valid_rate: float | None = None
    tokens_in_mean: float | None = None
    tokens_out_mean: float | None = None
    notes: list[str] = field(default_factory=list)

    def to_json(self) -> dict:
        return asdict(self)


def _p95(xs: list[float]) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, round(0.95 * (len(s) - 1)))]


async def _call(settings: ReasonerSettings, mode: str, request: ModelRequest, library: SkillLibrary,
                variant: str) -> CallResult:
    backend = make_backend(settings.model_copy(update={"output_mode": mode}))
    try:
        reply = await backend.complete(request)
    except AermaniError as exc:
        return CallResult(mode, False, False, error=str(exc)[:300], error_kind=getattr(exc, "kind", "server"))
    finally:
        await backend.aclose()
    res = CallResult(mode if reply.structured or mode == "text" else "text (schema refused)", True, False,
                     reply.latency_s, reply.tokens_in, reply.tokens_out, reply.cached_tokens, reply.text[:2000])
    try:
        parse_answer(reply.text, variant, library)
        res.valid = True
    except InvalidAnswer as exc:
        res.error = str(exc)
    return res


async def _classify(rep: ProbeReport, settings: ReasonerSettings, schema: CallResult, text: CallResult,
                    compiler: PromptCompiler, library: SkillLibrary, variant: str) -> None:
    """Image, schema and server failures told apart: a refused schema call whose free-text twin answers is the
    schema; a refused free-text call is asked again without the image (answered: the image is what the server
    refuses, and the schema is checked on that request); a 5xx or an unreachable server says nothing of either."""
    if schema.ok or text.ok:
        rep.image_accepted, rep.schema_supported = True, _schema_verdict(schema)
        if not schema.ok:
            rep.notes.append(f"schema mode: {schema.error}")
        return
    if text.error_kind != "refused":
        rep.image_accepted = rep.schema_supported = None
        rep.server_error = text.error
        rep.notes.append(f"the endpoint failed ({text.error_kind}), so image and schema support are unknown: "
                         f"{text.error}")
        return
    bare = compiler.compile(PROBE_COMMAND, History(), Observation())
    request = ModelRequest(bare, policy_context(PROBE_COMMAND, variant, library, History(), Observation()))
    plain = await _call(settings, "text", request, library, variant)
    rep.calls.append(plain)
    if not plain.ok:
        rep.image_accepted = rep.schema_supported = None
        rep.server_error = plain.error
        rep.notes.append(f"the endpoint refused the request with and without the image: {plain.error}")
        return
    rep.image_accepted = False
    rep.notes.append(f"the endpoint refuses the image (the same request without it was answered): {text.error}")
    checked = await _call(settings, "schema", request, library, variant)
    rep.calls.append(checked)
    rep.schema_supported = _schema_verdict(checked)


def _schema_verdict(call: CallResult) -> bool | None:
    """What a call made in schema mode says of schema support: answered under the schema (True), answered as free
    text or refused (False), failed for another reason (None: unknown)."""
    if call.ok:
        return call.mode == "schema"
    return False if call.error_kind in ("schema", "refused") else None


async def probe(settings: ReasonerSettings, jpeg: bytes, frame_source: str, *, calls: int = 5,
                library: SkillLibrary | None = None, variant: str = "full") -> ProbeReport:
    """Run the checks and the N timed calls against the endpoint in `settings`."""
    library = library or default_library()
    backend = make_backend(settings)  # fails early, naming the setting, on a bad backend or a missing key
    profile = getattr(backend, "profile", None)
    await backend.aclose()
    rep = ProbeReport(backend=settings.backend, model=getattr(backend, "model", settings.model),
                      base_url=settings.base_url or "(default)", profile=profile.name if profile else "-",
                      frame_source=frame_source, frame_bytes=len(jpeg))
    compiler = PromptCompiler(variant, library)
    obs = Observation(image_jpeg=jpeg, image_stamp_ns=time.time_ns())
    prompt = compiler.compile(PROBE_COMMAND, History(), obs)
    request = ModelRequest(prompt, policy_context(PROBE_COMMAND, variant, library, History(), obs))
    schema = await _call(settings, "schema", request, library, variant)
    rep.calls.append(schema)
    text = await _call(settings, "text", request, library, variant)
    rep.calls.append(text)
    rep.text_mode_valid = text.valid if text.ok else None
    await _classify(rep, settings, schema, text, compiler, library, variant)
    if not rep.image_accepted:
        return rep
    rep.mode_used = "schema" if rep.schema_supported else "text"
    timed = [await _call(settings, rep.mode_used, request, library, variant) for _ in range(calls)]
    rep.calls.extend(timed)
    good = [c for c in timed if c.ok]
    if good:
        rts = [c.latency_s for c in good]
        rep.rt_median_s, rep.rt_p95_s = statistics.median(rts), _p95(rts)
        rep.valid_rate = sum(c.valid for c in good) / len(timed)
        tin = [c.tokens_in for c in good if c.tokens_in is not None]
        tout = [c.tokens_out for c in good if c.tokens_out is not None]
        rep.tokens_in_mean = statistics.mean(tin) if tin else None
        rep.tokens_out_mean = statistics.mean(tout) if tout else None
    if len(good) < len(timed):
        rep.notes.append(f"{len(timed) - len(good)} of {len(timed)} timed calls failed: "
                         f"{next(c.error for c in timed if not c.ok)}")
    return rep


# --------------------------------------------------------------------------- the camera frame


async def frame_from_stack(connect: str, vehicle_id: str, timeout: float) -> bytes | None:
    """The newest colour frame of a running stack's camera, or None when nothing publishes one in time."""
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    from shared.cli_helpers import bus_if_up
    from shared.keys import Keys
    from shared.sensors import decode_proto

    bus = await bus_if_up(connect, timeout)
    if bus is None:
        return None
    try:
        sub = bus.subscribe(Keys(vehicle_id).camera_color, maxsize=2)
        sample = await sub.recv_sample(timeout=timeout)
        return bytes(decode_proto(CompressedImage, sample.value).data)
    except Exception:
        return None
    finally:
        await bus.close()


def generated_frame() -> bytes:
    """A room-like 640x480 JPEG (gradients, a red box on a table-coloured block, mild noise)."""
    import numpy as np

    from shared.sensors import color_message

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:480, 0:640]
    rgb = np.stack([(xx * 0.3 + 60), (yy * 0.3 + 80), (xx * 0.1 + yy * 0.1 + 100)], axis=-1)
    rgb[250:480, 100:560] = rgb[250:480, 100:560] * 0.6 + 90
    rgb[300:380, 200:260] = (215, 25, 25)
    rgb = np.clip(rgb + rng.normal(0, 3, rgb.shape), 0, 255).astype(np.uint8)
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

    from shared.sensors import decode_proto

    return bytes(decode_proto(CompressedImage, color_message(rgb, time.time_ns())).data)

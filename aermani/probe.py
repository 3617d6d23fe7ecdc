"""`aermani vlm probe`: check a model endpoint the way the reasoner will use it (services/reasoner/probe.py holds
the checks). The command lives in the application because, without a running stack, it starts the simulator
service for one camera frame: composing services is the application's part."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from aermani.launcher import Stack, available_services, loopback_mavlink_env
from services.reasoner.probe import frame_from_stack
from shared.text import plain_text, terminal_text

console = Console()


def frame_from_new_sim(timeout: float = 90.0) -> bytes | None:
    """Start the simulator service alone (free ports), take one camera frame, stop it."""
    if "sim" not in available_services():
        return None
    stack = Stack(["sim"], env=loopback_mavlink_env({"AERMANI_SIM_TARGET_OBJECT": "red cup",
                                                     "AERMANI_SIM_DESTINATION": "table"}))
    try:
        stack.start(wait=True, timeout=timeout)
        return asyncio.run(frame_from_stack(stack.endpoint, stack.procs[0].vehicle_id, 30.0))
    except Exception:
        return None
    finally:
        stack.stop()


def probe_command(
    base_url: Annotated[str | None, typer.Option(help="Endpoint base URL (e.g. http://127.0.0.1:8000/v1 for vLLM; "
                                                      "unset: the provider's).")] = None,
    model: Annotated[str, typer.Option(help="Model name (empty: the backend's default).")] = "",
    backend: Annotated[str, typer.Option(help="Backend kind (`aermani vlm backends`).")] = "openai",
    calls: Annotated[int, typer.Option(min=1, max=200, help="Timed calls for RT median/p95.")] = 5,
    api_key: Annotated[str | None, typer.Option(help="API key (default: AERMANI_REASONER_API_KEY or the "
                                                     "provider's variable).", envvar="AERMANI_REASONER_API_KEY")]
    = None,
    profile: Annotated[str, typer.Option(help="Model profile (auto: from the model name).")] = "auto",
    connect: Annotated[str, typer.Option(help="Zenoh router of a running stack to take the camera frame from.")]
    = "tcp/127.0.0.1:7447",
    vehicle: Annotated[str, typer.Option(help="Vehicle whose camera to use on --connect.")] = "am1",
    sim: Annotated[bool, typer.Option(help="Without a running stack, start the simulator for one frame.")] = True,
    timeout: Annotated[float, typer.Option(help="Request timeout per call, seconds.")] = 60.0,
    out: Annotated[Path, typer.Option(help="JSON report path.")] = Path("vlm-probe.json"),
) -> None:
    """Check an endpoint with a real camera frame: image accepted, schema mode supported, answers parse and
    validate; RT median and p95 over N calls and tokens per call. Prints a table and writes JSON."""
    from rich.table import Table

    from services.reasoner.probe import generated_frame, probe
    from services.reasoner.settings import ReasonerSettings
    from shared.errors import AermaniError

    try:
        settings = ReasonerSettings(backend=backend, base_url=base_url, model=model, api_key=api_key,
                                    profile=profile, request_timeout_s=timeout, transport_retries=1)
    except ValueError as exc:
        console.print(f"[red]bad option: {terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    jpeg, source = asyncio.run(frame_from_stack(connect, vehicle, 2.0)), f"running stack's camera ({connect})"
    if jpeg is None and sim:
        console.print("no running stack answered; starting the simulator for one camera frame...")
        jpeg, source = frame_from_new_sim(), "simulator started for the probe (camera/color)"
    if jpeg is None:
        jpeg, source = generated_frame(), "generated room-like frame (no simulator frame available)"
    console.print(f"frame: {source}, {len(jpeg) / 1024:.0f} KiB JPEG")
    try:
        rep = asyncio.run(probe(settings, jpeg, source, calls=calls))
    except AermaniError as exc:
        console.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    out.write_text(json.dumps(rep.to_json(), indent=1))

    def yes(v: bool | None) -> str:
        return "-" if v is None else "yes" if v else "NO"

    def num(v: float | None, fmt: str) -> str:
        return "-" if v is None else format(v, fmt)

    t = Table(title=terminal_text(f"{rep.backend}:{rep.model} at {rep.base_url} (profile {rep.profile})"))
    t.add_column("check")
    t.add_column("result")
    for k, v in (("server", "failed: " + terminal_text(rep.server_error[:60]) if rep.server_error else "answers"),
                 ("image accepted", yes(rep.image_accepted)), ("schema mode supported", yes(rep.schema_supported)),
                 ("free-text answer valid", yes(rep.text_mode_valid)), ("mode timed", rep.mode_used or "-"),
                 ("answers valid", "-" if rep.valid_rate is None else f"{100 * rep.valid_rate:.0f} %"),
                 (f"RT median over {calls} calls", num(rep.rt_median_s, ".3f") + " s"),
                 ("RT p95", num(rep.rt_p95_s, ".3f") + " s"),
                 ("tokens in / out per call", f"{num(rep.tokens_in_mean, '.0f')} / {num(rep.tokens_out_mean, '.0f')}"),
                 ("frame", rep.frame_source)):
        t.add_row(k, v)
    console.print(t)
    for n in rep.notes:
        console.print(f"note: {plain_text(n)}", markup=False)  # a note may quote the server's error
    console.print(f"JSON: {out}")
    raise typer.Exit(0 if rep.image_accepted and rep.valid_rate else 1)


def register(vlm: typer.Typer) -> None:
    """Add `probe` to the reasoner's `vlm` group (its `check` and `backends` commands stay the reasoner's)."""
    vlm.command("probe")(probe_command)

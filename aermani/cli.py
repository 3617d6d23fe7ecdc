"""The `aermani` command: the application's own (`up`, `health`, `router`, `certs`, and `demo`, `eval`,
`vlm probe`, which start stacks) and the sub-commands each service registers from its `cli.py`."""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import signal
import sys
import time
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from aermani import demo, fork, probe
from aermani.evaluation import cli as evaluation_cli
from aermani.launcher import OPTIONAL, SERVICE_ORDER, Stack, available_services, default_services
from shared.text import terminal_text

app = typer.Typer(help="aermani: language-driven aerial manipulation (AERMANI-VLM) on PX4.", no_args_is_help=True,
                  pretty_exceptions_enable=False)
console = Console()


@app.callback()
def _global_options(
    client_certs: Annotated[str | None, typer.Option(
        "--client-certs", help="Certificate directory (`aermani certs init`) for a `tls/...` --connect endpoint: "
        "reach a secure deployment's router (compose's ground router on :7448) from this host. Also "
        "AERMANI_ZENOH_CERTS.")] = None,
    identity: Annotated[str | None, typer.Option(
        help="Whose certificate to present with --client-certs: client (observe and abort), ground (command) "
             "or drone. Also AERMANI_ZENOH_IDENTITY; default client.")] = None,
) -> None:
    """Options for every command that connects to a router."""
    import os

    if identity is not None and identity not in ("client", "ground", "drone"):
        raise typer.BadParameter(f"{identity!r}: use client, ground or drone", param_hint="--identity")
    if client_certs is not None:
        os.environ["AERMANI_ZENOH_CERTS"] = client_certs
    if identity is not None:
        os.environ["AERMANI_ZENOH_IDENTITY"] = identity


@app.command()
def up(
    services: Annotated[str | None, typer.Option(help="Comma-separated services to start (default: all that exist; "
                                                 "the camera only when AERMANI_CAMERA_SOURCE is set).")] = None,
    without: Annotated[str, typer.Option(
        help="Comma-separated services to leave out, e.g. sim for a real drone.")] = "",
    port: Annotated[int, typer.Option(help="Port of the embedded Zenoh router on 127.0.0.1 (none with --secure: "
                                           "every listener is mutual TLS).")] = 7447,
    vehicle: Annotated[str, typer.Option(help="Vehicle id.")] = "am1",
    log_dir: Annotated[str | None, typer.Option(help="Where service logs go (default runs/<time>/logs).")] = None,
    foxglove: Annotated[bool, typer.Option(help="Also serve Foxglove's live WebSocket (needs the recorder).")]
    = False,
    secure: Annotated[bool, typer.Option(help="Ground and drone routers from shared/routers/ with mutual TLS "
                                              "and access control (certificates from `aermani certs init`).")]
    = False,
    certs: Annotated[str, typer.Option(help="Certificate directory for --secure.")] = "certs",
    tls_listen: Annotated[str, typer.Option(help="--secure: the ground router's mutual-TLS listener, the only "
                                                 "one that may leave the host, e.g. tls/0.0.0.0:7448.")]
    = "tls/127.0.0.1:7448",
) -> None:
    """Start the embedded stack: a Zenoh router on loopback and every service as a supervised process."""
    names = [s.strip() for s in services.split(",")] if services else default_services()
    skip = {s.strip() for s in without.split(",") if s.strip()}
    names = [n for n in names if n not in skip]
    unknown = [n for n in names if n not in available_services()]
    if unknown:
        console.print(f"[red]unknown services: {unknown}; available: {available_services()}[/red]")
        raise typer.Exit(2)
    if "reasoner" in names:  # a model backend without its key: said now, not as a reasoner crashing in a loop
        import os

        problem = demo.backend_problem(os.environ.get("AERMANI_REASONER_BACKEND") or "rules")
        if problem is not None:
            console.print(f"[red]{terminal_text(problem)}[/red]")
            raise typer.Exit(2)
    env = {"AERMANI_RECORDER_FOXGLOVE": "1"} if foxglove else {}
    from shared.errors import ConfigError

    try:
        stack = Stack(names, port=port, vehicle_id=vehicle, log_dir=log_dir, env=env,
                      secure=certs if secure else None, tls_listen=[tls_listen] if secure else None)
        if secure:
            from shared.security import check_cert_files, load_ca

            check_cert_files(certs, "ground")
            check_cert_files(certs, "drone")
            load_ca(certs)  # it signs each service's own certificate: said now, not as a traceback at start
    except ConfigError as exc:
        console.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    stopping = False

    def on_signal(signum: int, _frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    if secure:
        console.print(f"secure: ground router {tls_listen}, drone router {stack.drone_endpoint}, mutual TLS only "
                      f"(no plain listener); each service has its own certificate and rights; deployment "
                      f"certificates in {certs}")
    else:
        console.print(f"router on tcp/127.0.0.1:{port}")
    console.print(f"starting {', '.join(names)}; logs in {stack.log_dir}")
    if "gateway" in names:
        import os

        host = os.environ.get("AERMANI_GATEWAY_HOST", "127.0.0.1")
        console.print(f"ground-station page and API: http://{host}:{os.environ.get('AERMANI_GATEWAY_PORT', '8080')}/"
                      " (POST /api/v1/tasks)")
    stack.start(wait=False)
    shown: dict[str, bool] = {p.label: False for p in stack.procs}
    seen_events = 0
    try:
        while not stopping:
            alive = stack.alive()
            for p in stack.procs:
                now = (p.vehicle_id, p.name) in alive
                if shown[p.label] != now:
                    shown[p.label] = now
                    mark = "[green]alive[/green]" if now else "[red]dead [/red]"
                    console.print(f"  {mark}  {p.label}", highlight=False)
            for ev in stack.events[seen_events:]:
                if "exited" in ev or "restarted" in ev:
                    console.print(f"  [yellow]{terminal_text(ev)}[/yellow]")
            seen_events = len(stack.events)
            time.sleep(0.5)
    finally:
        console.print("stopping...")
        stack.stop()
        console.print("all services stopped")


@app.command()
def health(
    connect: Annotated[str, typer.Option(help="Zenoh endpoint of the router.")] = "tcp/127.0.0.1:7447",
    vehicle: Annotated[str | None, typer.Option(help="Only this vehicle id.")] = None,
    timeout: Annotated[float, typer.Option(help="Seconds to wait for answers.")] = 2.0,
) -> None:
    """List the live services (from their liveliness tokens) and what their health reports say (a stalled
    camera, a lost autopilot link...)."""
    from shared.bus import Bus, Subscription
    from shared.keys import HEALTH_TOPIC, alive_pattern, parse_alive_key
    from shared.messages import Health

    async def run() -> tuple[list[str], dict[tuple[str, str], Health]]:
        bus = await Bus.open(connect=[connect], connect_timeout_s=timeout + 1)
        try:
            topic = HEALTH_TOPIC.bind(vehicle, service="*") if vehicle else HEALTH_TOPIC.fleet(service="*")
            sub: Subscription[Health] = bus.subscribe(topic, maxsize=200)
            loop = asyncio.get_running_loop()
            deadline = loop.time() + 1.1  # health comes at about 1 Hz; listen while liveliness is asked
            keys = await bus.alive(alive_pattern(vehicle), timeout=timeout)
            reports: dict[tuple[str, str], Health] = {}
            while sub.qsize() or loop.time() < deadline:
                with contextlib.suppress(TimeoutError):
                    rec = await sub.recv_sample(timeout=max(0.01, deadline - loop.time()))
                    reports[(rec.key.split("/")[2], rec.value.service)] = rec.value
            return keys, reports
        finally:
            await bus.close()

    try:
        keys, reports = asyncio.run(asyncio.wait_for(run(), timeout + 10))
    except Exception as exc:
        console.print(f"[red]cannot reach the router at {terminal_text(connect)}: {terminal_text(exc)}[/red]")
        raise typer.Exit(1)
    table = Table("vehicle", "service", "state", "health")

    def said(vid: str, name: str) -> str:
        h = reports.get((vid, name))
        if h is None:
            return ""
        return "[green]ok[/green]" if h.ok else f"[red]{terminal_text(h.message or 'not ok')}[/red]"

    live = {parse_alive_key(k) for k in keys}
    for vid, name in sorted(live):
        table.add_row(terminal_text(vid), terminal_text(name), "[green]alive[/green]", said(vid, name))
    vehicles = {v for v, _ in live} or {vehicle or "am1"}
    for vid in sorted(vehicles):
        for name in available_services():
            if name in OPTIONAL:
                continue  # started only when configured: absence is not a fault
            if (vid, name) not in live and not any(n == name for _, n in live if name in ("recorder", "gateway")):
                table.add_row(terminal_text(vid), name, "[red]not running[/red]", said(vid, name))
    console.print(table)
    if not live:
        raise typer.Exit(1)


certs_app = typer.Typer(help="Certificates of a deployment (mutual TLS between routers).", no_args_is_help=True)
app.add_typer(certs_app, name="certs")


@certs_app.command("init")
def certs_init(
    out: Annotated[str, typer.Option(help="Directory for ca.pem/ca.key and <identity>.pem/.key.")] = "certs",
    san: Annotated[list[str] | None, typer.Option(help="Extra host name or IP address in every certificate "
                                                       "(repeatable), e.g. the ground station's address.")] = None,
    days: Annotated[int, typer.Option(help="Validity in days.")] = 825,
    force: Annotated[bool, typer.Option(help="Replace existing files.")] = False,
) -> None:
    """Make a CA and the ground, drone and client certificates (distinct common names) for a new deployment."""
    from shared.errors import ConfigError
    from shared.security import IDENTITIES, init_certs

    try:
        files = init_certs(out, sans=san or (), days=days, force=force)
    except ConfigError as exc:
        console.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    for identity, f in files.items():
        console.print(f"{identity:7s} CN={IDENTITIES[identity]:15s} {f.cert}  {f.key}")
    console.print(f"CA {out}/ca.pem (keep {out}/ca.key offline: it signs new identities). Copy ca.pem + "
                  "ground.* to the ground station, ca.pem + drone.* to the vehicle, ca.pem + client.* to observers.")


@app.command()
def router(
    role: Annotated[str, typer.Option(help="ground or drone.")],
    certs: Annotated[str, typer.Option(help="Certificate directory.")] = "/certs",
    local: Annotated[str, typer.Option(help="Plain listener for this host's services (loopback only).")]
    = "tcp/127.0.0.1:7447",
    tls_listen: Annotated[str | None, typer.Option(help="Mutual-TLS listener (default: the template's).")] = None,
    connect: Annotated[str | None, typer.Option(help="Routers to link to, comma-separated (drone: the ground "
                                                     "router, tls/<address>:7448).")] = None,
) -> None:
    """Run one secure Zenoh router from its template in shared/routers/ until SIGINT/SIGTERM."""
    import threading

    import zenoh

    from shared.bus import _init_zenoh_log
    from shared.errors import ConfigError
    from shared.security import router_config

    try:
        cfg = router_config(role, certs, local=local, tls_listen=[tls_listen] if tls_listen else None,
                            connect=[c.strip() for c in connect.split(",") if c.strip()] if connect else None)
    except ConfigError as exc:
        console.print(f"[red]{terminal_text(exc)}[/red]")
        raise typer.Exit(2)
    _init_zenoh_log()
    done = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: done.set())
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    session = zenoh.open(cfg)
    console.print(f"{role} router up: {cfg.get_json('listen/endpoints')} -> {cfg.get_json('connect/endpoints')}")
    try:
        done.wait()
    finally:
        session.close()  # type: ignore[no-untyped-call]


def _register_commands() -> None:
    """Each service may add sub-commands with `services/<name>/cli.py: register(app)` (a checkout without the
    service has none); then the application's commands that start stacks: `demo`, `eval`, and `probe` in the
    reasoner's `vlm` group."""
    for name in [*SERVICE_ORDER, "mcp"]:
        try:
            mod = importlib.import_module(f"services.{name}.cli")
        except ModuleNotFoundError as exc:
            if exc.name in (f"services.{name}", f"services.{name}.cli"):
                continue
            raise
        register = getattr(mod, "register", None)
        if register is not None:
            register(app)
    demo.register(app)
    fork.register(app)
    evaluation_cli.register(app)
    vlm = next((g.typer_instance for g in app.registered_groups if g.name == "vlm"), None)
    if vlm is not None:  # the probe checks an endpoint the way the reasoner uses it: only with the reasoner
        probe.register(vlm)


def main() -> None:
    """Run the CLI, then leave without the interpreter's finalization. Commands open Zenoh sessions in this
    process (`up`'s routers and their heartbeat watch, `demo`, `fork`, `eval`), and Zenoh's own threads call
    into Python (a late sample, a callback dropped): one that wants the GIL while the interpreter finalizes is
    ended by CPython with pthread_exit, whose forced unwind cannot cross Rust's thread entry, and the process
    aborts with "FATAL: exception not rethrown" (SIGABRT, exit -6) after every service had stopped cleanly
    (seen at the exit of `aermani up` and of a fork). Everything the CLI writes is flushed first."""
    import logging
    import os
    import traceback

    _register_commands()
    code: int = 0
    try:
        app()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if exc.code is not None and not isinstance(exc.code, int):
            print(exc.code, file=sys.stderr)
    except BrokenPipeError:
        code = 0
    except KeyboardInterrupt:
        code = 130
    except BaseException:  # noqa: BLE001 - printed as Python would, then the same exit status
        traceback.print_exc()
        code = 1
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


if __name__ == "__main__":
    main()

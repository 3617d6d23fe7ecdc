"""The MCP server: tasks, not raw flight. Every tool is a call to the gateway's HTTP API, so an agent gets
exactly what an operator gets (the same task store, the same abort, the executor's safety envelope) and
nothing more; single skills only when both this server and the gateway allow them."""

from __future__ import annotations

import hmac
import json
from typing import Any

import httpx
from mcp.server.mcpserver import MCPServer
from mcp.server.mcpserver.exceptions import ToolError
from mcp.server.mcpserver.utilities.types import Image
from mcp.server.transport_security import TransportSecuritySettings
from mcp.types import ToolAnnotations

from services.mcp.settings import McpSettings
from shared.errors import ConfigError

INSTRUCTIONS = """\
aermani flies a PX4 multirotor with a gripper (real or simulated). You give it a task in plain language, e.g.
"pick up the red cup and place it on the table"; an on-board policy (a vision-language model or the rule-based
baseline) chooses one flight-safe skill per step (move, turn, localize, grasp, place) and the executor runs it
inside a geofence with altitude and speed limits. You cannot fly the vehicle directly: start a task, follow it
with task_status, look through its camera with get_camera_frame, and abort it when needed. One task runs per
vehicle at a time. Aborting makes the vehicle hold its position."""


class GatewayError(ToolError):
    """The gateway answered with an error; the message is its own explanation."""


class Gateway:
    """A small client of the gateway's /api/v1."""

    def __init__(self, settings: McpSettings) -> None:
        headers = {"Accept": "application/json"}
        # Over HTTP without its own token this server cannot tell who calls: it must not lend the gateway's
        # rights to them, so it calls the gateway as they would (reads answer, a task start gets the 401).
        if settings.gateway_token is not None and settings.lends_gateway_token:
            headers["Authorization"] = f"Bearer {settings.gateway_token.get_secret_value()}"
        self.http = httpx.AsyncClient(base_url=settings.gateway_url.rstrip("/"), headers=headers,
                                      timeout=settings.request_timeout_s)

    async def call(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            r = await self.http.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            raise GatewayError(f"the aermani gateway at {self.http.base_url} did not answer ({exc}); is "
                               "`aermani up` (or the ground station) running?") from exc
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            raise GatewayError(f"{method} {path}: {r.status_code}: {detail}")
        return r

    async def json(self, method: str, path: str, **kwargs: Any) -> Any:
        return (await self.call(method, path, **kwargs)).json()

    async def vehicle(self, named: str | None) -> str:
        """`named`, or the only vehicle the ground station knows; with several, an agent must say which (a
        default that picks one would fly or show the wrong vehicle)."""
        if named:
            return named
        known = sorted(v["vehicle_id"] for v in (await self.json("GET", "/health"))["vehicles"])
        if len(known) == 1:
            return str(known[0])
        if not known:
            raise ToolError("no vehicle is on the ground station's bus yet; list_vehicles shows when one is")
        raise ToolError(f"{len(known)} vehicles are known ({', '.join(known)}): name one with `vehicle`")


# What each tool does to the world, for clients that ask before calling (MCP tool annotations).
READ = ToolAnnotations(read_only_hint=True, destructive_hint=False, idempotent_hint=True, open_world_hint=False)
FLIES = ToolAnnotations(read_only_hint=False, destructive_hint=True, idempotent_hint=False, open_world_hint=True)
STOPS = ToolAnnotations(read_only_hint=False, destructive_hint=False, idempotent_hint=True, open_world_hint=True)


def _step_summary(step: dict[str, Any]) -> dict[str, Any]:
    ste = step.get("ste") or {}
    drt = step.get("drt") or {}
    return {"step": step.get("step"), "skill": ste.get("skill"), "argument": ste.get("argument"),
            "skill_state": step.get("skill_state"), "skill_message": step.get("skill_message"),
            "reasoning": drt.get("reasoning"), "summary": drt.get("summary"), "valid": step.get("valid")}


def _one_scope(task_id: str | None, vehicle: str | None, fleet: bool) -> None:
    """An abort names exactly one scope: a call without one must not stop the whole fleet by default."""
    scopes = [name for name, given in (("task_id", bool(task_id)), ("vehicle", bool(vehicle)), ("fleet", fleet))
              if given]
    if len(scopes) != 1:
        raise ToolError("abort needs exactly one scope: task_id, vehicle, or fleet=true"
                        + (f" (got {', '.join(scopes)})" if scopes else ""))


def build_server(settings: McpSettings) -> MCPServer:
    """The MCP server with its tools and resources, talking to the gateway named in `settings`."""
    gw = Gateway(settings)
    server = MCPServer(name="aermani", instructions=INSTRUCTIONS, version="1")

    @server.tool(title="List vehicles", annotations=READ)
    async def list_vehicles() -> list[dict[str, Any]]:
        """The vehicles the ground station knows: which services answer, link and offboard health, battery,
        and the task each one runs now (if any)."""
        health = await gw.json("GET", "/health")
        return [{"vehicle_id": v["vehicle_id"], "services": v["services"], "link_ok": v.get("link_ok"),
                 "armed": v.get("armed"), "mode": v.get("mode"), "battery_remaining": v.get("battery_remaining"),
                 "running_task": v.get("running_task")} for v in health["vehicles"]]

    @server.tool(title="Start a task (the vehicle flies)", annotations=FLIES)
    async def start_task(command: str, vehicle: str | None = None) -> dict[str, Any]:
        """Start a task from a natural-language command (e.g. "pick up the red cup and place it on the
        table") on a vehicle (required when the ground station knows several; default: the only one). Returns
        the task id; follow it with task_status. Refused while another task runs on that vehicle."""
        body: dict[str, Any] = {"command": command, "vehicle_id": await gw.vehicle(vehicle)}
        created = await gw.json("POST", "/tasks", json=body)
        return {"task_id": created["task_id"], "vehicle_id": created["vehicle_id"], "state": created["state"]}

    @server.tool(title="Task status", annotations=READ)
    async def task_status(task_id: str, last_steps: int = 5) -> dict[str, Any]:
        """A task's state (pending, running, aborting: an abort was sent and its end has not arrived yet; then
        succeeded, failed, aborted or timeout), its explanation, and its last reasoning steps: the skill
        chosen, the model's reasoning and how the skill ended."""
        t = await gw.json("GET", f"/tasks/{task_id}")
        steps = [_step_summary(s["step"]) for s in t.get("reasoning_steps", [])]
        status = t.get("status") or {}
        return {"task_id": task_id, "vehicle_id": t.get("vehicle_id"), "command": t.get("command"),
                "state": t.get("state"), "message": status.get("message", ""), "steps": len(steps),
                "last_steps": steps[-max(0, min(last_steps, 50)):] if last_steps else []}

    @server.tool(title="Abort (the vehicle holds)", annotations=STOPS)
    async def abort(reason: str, task_id: str | None = None, vehicle: str | None = None,
                    fleet: bool = False) -> dict[str, Any]:
        """Stop now, with a reason (recorded by the vehicle): exactly one scope, a task (`task_id`), a vehicle
        (`vehicle`), or every vehicle (`fleet: true`). The vehicles hold their position. Says which vehicles
        acknowledged."""
        _one_scope(task_id, vehicle, fleet)
        body: dict[str, Any] = {"reason": reason.strip() or "abort via MCP"}
        if task_id:
            return dict(await gw.json("POST", f"/tasks/{task_id}/abort", json=body))
        if vehicle:
            body["vehicle_id"] = vehicle
        return dict(await gw.json("POST", "/abort", json=body))

    @server.tool(title="List skills", annotations=READ)
    async def list_skills(vehicle: str | None = None) -> list[dict[str, Any]]:
        """The skills the on-board policy chooses from (what a task can make the vehicle do), on `vehicle`
        (required when several are known)."""
        lib = await gw.json("GET", f"/vehicles/{await gw.vehicle(vehicle)}/skills")
        return [{"name": s["name"], "category": s["category"], "description": s["description"],
                 "argument": s.get("argument")} for s in lib["skills"] if s.get("policy_visible", True)]

    @server.tool(title="Camera frame", annotations=READ)
    async def get_camera_frame(vehicle: str | None = None) -> Image:
        """The newest colour frame of the vehicle's camera, as a JPEG image (`vehicle` required when several
        are known)."""
        r = await gw.call("GET", f"/vehicles/{await gw.vehicle(vehicle)}/camera.jpg")
        return Image(data=r.content, format="jpeg")

    @server.tool(title="Pending approvals", annotations=READ)
    async def list_approvals() -> list[dict[str, Any]]:
        """Skills the on-board policy chose that wait for an operator's approval (set per vehicle and skill
        class on the reasoner), with the policy's reasoning and when the request expires."""
        return list(await gw.json("GET", "/approvals"))

    @server.tool(title="Approve or reject a skill", annotations=FLIES)
    async def decide_approval(approval_id: str, approve: bool, reason: str = "") -> dict[str, Any]:
        """Approve (the skill runs) or reject (the policy reads your reason and chooses again) a pending
        approval."""
        return dict(await gw.json("POST", f"/approvals/{approval_id}",
                                  json={"approve": approve, "reason": reason, "operator": "mcp"}))

    if settings.allow_skills:
        @server.tool(title="Run one skill (the vehicle flies)", annotations=FLIES)
        async def run_skill(skill: str, argument: str | None = None, vehicle: str | None = None) -> dict[str, Any]:
            """Run one skill outside a task (e.g. yaw_left, obj_localization "red cup") and wait for its result.
            The executor's preconditions and safety envelope apply; the gateway must allow single skills."""
            return dict(await gw.json("POST", f"/vehicles/{await gw.vehicle(vehicle)}/skills",
                                      json={"skill": skill, "argument": argument}))

    @server.resource("aermani://tasks", mime_type="application/json")
    async def task_history() -> str:
        """The most recent tasks with their states and commands."""
        return json.dumps(await gw.json("GET", "/tasks"))

    @server.resource("aermani://vehicles/{vehicle}/detections", mime_type="application/json")
    async def current_detections(vehicle: str) -> str:
        """What perception sees now on a vehicle: labels, 3D centroids, sizes, confidence."""
        return json.dumps(await gw.json("GET", f"/vehicles/{vehicle}/detections"))

    return server


class OriginCheck:
    """ASGI middleware: a request that carries an `Origin` header (a web page's) must name one of the allowed
    origins exactly; `null` and every origin not listed get 403 before anything else is read. The SDK's own
    check allows any port of localhost, so a page on any local port could drive the vehicle."""

    def __init__(self, app: Any, allowed: list[str]) -> None:
        self.app = app
        self.allowed = {o.encode() for o in allowed}

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] == "http":
            origin = dict(scope.get("headers") or []).get(b"origin")
            if origin is not None and origin not in self.allowed:
                shown = origin.decode("latin-1")[:100].encode("unicode_escape").decode()
                body = json.dumps({"error": f"origin {shown!r} is not allowed (AERMANI_MCP_ALLOWED_ORIGINS lists "
                                            "the exact origins that may call this server)"}).encode()
                await send({"type": "http.response.start", "status": 403,
                            "headers": [(b"content-type", b"application/json")]})
                await send({"type": "http.response.body", "body": body})
                return
        await self.app(scope, receive, send)


class BearerAuth:
    """ASGI middleware: every HTTP request must carry `Authorization: Bearer <token>` (constant-time check)."""

    def __init__(self, app: Any, token: str) -> None:
        self.app = app
        self.token = token.encode()

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] == "http":
            headers = dict(scope.get("headers") or [])
            given = headers.get(b"authorization", b"")
            if not (given.startswith(b"Bearer ") and hmac.compare_digest(given[7:], self.token)):
                body = b'{"error": "missing or invalid bearer token (AERMANI_MCP_TOKEN)"}'
                await send({"type": "http.response.start", "status": 401,
                            "headers": [(b"content-type", b"application/json"), (b"www-authenticate", b"Bearer")]})
                await send({"type": "http.response.body", "body": body})
                return
        await self.app(scope, receive, send)


def http_app(settings: McpSettings) -> Any:
    """The streamable-HTTP app at /mcp: Origin checked exactly, then the bearer token (required: without
    AERMANI_MCP_TOKEN this raises ConfigError). On loopback the SDK's Host check (DNS rebinding) also runs,
    with this server's own host and port exactly."""
    settings.check_safe()
    if settings.token is None:  # check_safe refuses this for transport=http; an app is HTTP whatever it says
        raise ConfigError("the MCP server over HTTP needs AERMANI_MCP_TOKEN")
    if settings.loopback:
        hosts = [f"{h}:{settings.port}" for h in ("127.0.0.1", "localhost", "[::1]")]
        security = TransportSecuritySettings(enable_dns_rebinding_protection=True, allowed_hosts=hosts,
                                             allowed_origins=list(settings.allowed_origins))
    else:  # reached by names this server cannot know; the token (required here) is the protection
        security = TransportSecuritySettings(enable_dns_rebinding_protection=False)
    app: Any = build_server(settings).streamable_http_app(host=settings.host, transport_security=security)
    app = BearerAuth(app, settings.token.get_secret_value())
    return OriginCheck(app, settings.allowed_origins)

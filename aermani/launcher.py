"""The embedded launcher: a Zenoh router in this process, every service as its own process, supervision.

`Stack` is used by `aermani up`, `aermani demo`, the evaluation harness and the integration tests, so they
all start the system the same way: router on loopback (zenoh-python in router mode, no zenohd), services as
`python -m services.<name>` clients of it, restart with backoff when one crashes, stop with SIGTERM then
SIGKILL. Children get PR_SET_PDEATHSIG so that even a SIGKILLed launcher leaves no process behind.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from pydantic import TypeAdapter, ValidationError

from shared.bus import _init_zenoh_log, zenoh_config
from shared.keys import DEFAULT_VEHICLE_ID, alive_pattern, heartbeat_pattern, parse_alive_key
from shared.messages import Heartbeat
from shared.security import ROUTER, require_loopback, service_identity

log = logging.getLogger("aermani.launcher")

# Start order: the world and the link first, the decision makers last.
SERVICE_ORDER = ("sim", "camera", "autopilot_bridge", "perception", "executor", "reasoner", "recorder", "gateway",
                 "ros2")
# Services that exist once per vehicle (the rest serve a whole ground station).
PER_VEHICLE = ("sim", "camera", "autopilot_bridge", "perception", "executor", "reasoner", "ros2")
# Services started by default only when configured. The camera service runs when AERMANI_CAMERA_SOURCE names
# a source (not `none`); then it owns the camera keys and tf's camera/gripper frames, so a simulator in the
# same stack runs with its camera off (AERMANI_SIM_CAMERA=0) and the autopilot bridge publishes
# world->base_link (AERMANI_AUTOPILOT_BRIDGE_PUBLISH_TF=1), exactly as on a real drone. Without it the
# simulator is the camera. Explicit settings in the environment win over these defaults. The ROS 2 bridge
# runs when AERMANI_ROS2_ENABLED is true (it republishes the camera, which the router then carries twice).
OPTIONAL = ("camera", "ros2")


def camera_configured(env: dict[str, str] | os._Environ[str] | None = None) -> bool:
    """Whether a camera source is configured (AERMANI_CAMERA_SOURCE set and not `none`)."""
    source = (os.environ if env is None else env).get("AERMANI_CAMERA_SOURCE", "").strip().lower()
    return source not in ("", "none")


def default_services(env: dict[str, str] | os._Environ[str] | None = None) -> list[str]:
    """What `aermani up` starts without --services: every service in this checkout, the optional ones only
    when configured."""
    wanted = {"camera": camera_configured(env), "ros2": ros2_enabled(env)}
    return [s for s in available_services() if s not in OPTIONAL or wanted.get(s, False)]


def ros2_enabled(env: dict[str, str] | os._Environ[str] | None = None) -> bool:
    """Whether the ROS 2 bridge is asked for (AERMANI_ROS2_ENABLED true, as pydantic reads a bool)."""
    value = (os.environ if env is None else env).get("AERMANI_ROS2_ENABLED", "").strip()
    try:
        return bool(value) and TypeAdapter(bool).validate_python(value)
    except ValidationError:
        return False
# Services that run on the vehicle (behind the drone router in a --secure stack); the rest are the ground's.
DRONE_SIDE = ("sim", "camera", "autopilot_bridge", "perception", "executor")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _loopback(endpoint: str) -> str:
    """The same listener reached from this host: `tls/0.0.0.0:7448` -> `tls/127.0.0.1:7448`."""
    return endpoint.replace("0.0.0.0", "127.0.0.1").replace("[::]", "127.0.0.1")


def available_services() -> list[str]:
    """Services that exist in this checkout (have a `services/<name>/__main__.py`), in start order."""
    found = []
    root = Path(__file__).resolve().parent.parent / "services"
    names = [p.parent.name for p in root.glob("*/__main__.py")]
    for name in [*SERVICE_ORDER, *sorted(set(names) - set(SERVICE_ORDER))]:
        if name in names and importlib.util.find_spec(f"services.{name}") is not None:
            found.append(name)
    return found


def open_router(port: int, host: str = "127.0.0.1", connect: list[str] | None = None) -> zenoh.Session:
    """A Zenoh session in router mode listening on tcp/<host>:<port>, multicast scouting off, linked to the
    routers in `connect` (e.g. a vehicle host's router joining the ground's). Plain TCP without access
    control: only on loopback (`--secure` routers come from `shared.security`)."""
    require_loopback([f"tcp/{host}:{port}", *(connect or [])])
    _init_zenoh_log()
    return zenoh.open(zenoh_config(mode="router", listen=[f"tcp/{host}:{port}"], connect=list(connect or [])))


@dataclass
class ServiceProcess:
    """One service process the launcher runs: its name, vehicle, environment, log file and restart count."""

    name: str
    vehicle_id: str
    env: dict[str, str]
    log_path: Path
    proc: subprocess.Popen[bytes] | None = None
    restarts: int = 0
    started_at: float = 0.0
    next_start: float = 0.0
    exit_codes: list[int] = field(default_factory=list)

    @property
    def label(self) -> str:
        return f"{self.vehicle_id}/{self.name}" if self.name in PER_VEHICLE else self.name

    @property
    def identity(self) -> str:
        """Its own identity in a secure stack (`executor@am1`, `gateway@fleet`)."""
        return service_identity(self.name, self.vehicle_id if self.name in PER_VEHICLE else None)

    def start(self) -> None:
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        logf = open(self.log_path, "ab")  # noqa: SIM115 - handed to the child
        logf.write(f"\n--- start {time.strftime('%H:%M:%S')} ---\n".encode())
        logf.flush()
        # No preexec_fn (unsafe from a threaded parent: the supervisor restarts from its thread); the child
        # arranges to die with the launcher itself (shared.service.die_with_parent).
        env = {**self.env, "AERMANI_PARENT_PID": str(os.getpid())}
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", f"services.{self.name}"], env=env, stdout=logf, stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL, start_new_session=True,
            )
        finally:
            logf.close()
        self.started_at = time.monotonic()

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


class Stack:
    """Router + service processes. Use as a context manager or call start()/stop()."""

    def __init__(self, services: list[str] | None = None, *, port: int | None = None, vehicle_id: str =
                 DEFAULT_VEHICLE_ID, env: dict[str, str] | None = None, log_dir: str | Path | None = None,
                 supervise: bool = True, host: str = "127.0.0.1", router: bool = True,
                 secure: str | Path | None = None, tls_listen: list[str] | None = None,
                 hung_after_s: float = 4.0, link: list[str] | None = None) -> None:
        """`secure` is a certificate directory (`aermani certs init`, with the CA's key: this machine signs):
        the stack then runs a ground and a drone router from `shared/routers/` linked by mutual TLS, and no
        plain listener at all. Each service gets a certificate of its own for this run (`<service>@<vehicle>`,
        in a private directory removed at stop) and reaches its side's router over mutual TLS on loopback:
        ground services the ground router's `tls_listen` (default tls/127.0.0.1:<free port>, where outsiders
        need a deployment certificate too), vehicle services the drone router's loopback TLS listener. The
        routers' access control gives each service only its own job's rights (`shared.security`). `link`:
        routers the stack's own (plain, loopback) router connects to, so its services are reachable through
        them."""
        require_loopback([f"tcp/{host}:0"])
        self.port = port or free_port()
        self.host = host
        self.secure = Path(secure) if secure else None
        self.tls_listen = list(tls_listen) if tls_listen else [f"tls/127.0.0.1:{free_port()}"]
        # A secure stack's services use TLS on loopback: the ground ones its first TLS listener.
        self.endpoint = _loopback(self.tls_listen[0]) if secure else f"tcp/{host}:{self.port}"
        self.drone_endpoint = f"tls/127.0.0.1:{free_port()}" if secure else self.endpoint
        self.service_certs: Path | None = Path(tempfile.mkdtemp(prefix="aermani-services-")) if secure else None
        self.drone_router: zenoh.Session | None = None
        self.log_dir = Path(log_dir) if log_dir else Path("runs") / time.strftime("%Y%m%d-%H%M%S") / "logs"
        self.supervise = supervise
        self.with_router = router
        self.link = list(link or [])
        self.router: zenoh.Session | None = None
        self.procs: list[ServiceProcess] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.hung_after_s = hung_after_s
        self._beats: dict[tuple[str, str], tuple[float, int]] = {}
        self.events: list[str] = []
        if services is None:
            services = available_services()
        self.add_vehicle(vehicle_id, services, env or {})

    # ---- composition

    def add_vehicle(self, vehicle_id: str, services: list[str], env: dict[str, str] | None = None) -> None:
        """Add services for one vehicle id; ground-station services (recorder, gateway) are added once."""
        have = {(p.name, p.vehicle_id) for p in self.procs}
        env = dict(env or {})
        if "camera" in services and camera_configured({**os.environ, **env}):
            # One camera per vehicle: the camera service's frames, not the simulator's (see OPTIONAL).
            for var, value in (("AERMANI_SIM_CAMERA", "false"), ("AERMANI_AUTOPILOT_BRIDGE_PUBLISH_TF", "true")):
                if var not in env and var not in os.environ:
                    env[var] = value
        for name in services:
            if name not in PER_VEHICLE and any(p.name == name for p in self.procs):
                continue
            if (name, vehicle_id) in have:
                continue
            endpoint = self.drone_endpoint if name in DRONE_SIDE else self.endpoint
            child_env = {**os.environ, "AERMANI_ZENOH_CONNECT": endpoint, "AERMANI_VEHICLE_ID": vehicle_id,
                         "PYTHONUNBUFFERED": "1", **env}
            suffix = f"-{vehicle_id}" if name in PER_VEHICLE else ""
            proc = ServiceProcess(name, vehicle_id, child_env, self.log_dir / f"{name}{suffix}.log")
            if self.service_certs is not None:
                if self.router is not None:
                    raise RuntimeError("a secure stack's services are added before it starts: the routers' "
                                       "access control names each of them")
                child_env["AERMANI_ZENOH_CERTS"] = str(self.service_certs)
                child_env["AERMANI_ZENOH_IDENTITY"] = proc.identity
            self.procs.append(proc)

    def find(self, name: str, vehicle_id: str | None = None) -> ServiceProcess:
        for p in self.procs:
            if p.name == name and (vehicle_id is None or p.vehicle_id == vehicle_id):
                return p
        raise KeyError(f"no service {name!r} (vehicle {vehicle_id}) in this stack")

    # ---- lifecycle

    def start(self, wait: bool = True, timeout: float = 90.0) -> Stack:
        if self.with_router and self.router is None:
            if self.secure is None:
                self.router = open_router(self.port, self.host, connect=self.link)
            else:
                self._open_secure_routers()
        for p in self.procs:
            p.start()
            self._event(f"started {p.label} (pid {p.proc.pid if p.proc else '?'})")
        if self.supervise:
            self._thread = threading.Thread(target=self._supervise, name="aermani-supervisor", daemon=True)
            self._thread.start()
        if wait:
            self.wait_alive(timeout=timeout)
        return self

    def _open_secure_routers(self) -> None:
        from shared.security import cert_files, issue_service_certs, router_config

        _init_zenoh_log()
        assert self.secure is not None and self.service_certs is not None
        ground = sorted({p.identity for p in self.procs if p.name not in DRONE_SIDE})
        drone = sorted({p.identity for p in self.procs if p.name in DRONE_SIDE})
        # One vehicle behind the drone router: that router gets a certificate bound to its vehicle id, so it
        # speaks for that vehicle only. Several simulated vehicles share one drone router here, which then
        # keeps the deployment's drone certificate (every vehicle's rights), as compose's drone router does.
        vehicles = sorted({p.vehicle_id for p in self.procs if p.name in DRONE_SIDE})
        bound = [service_identity(ROUTER, vehicles[0])] if len(vehicles) == 1 else []
        issue_service_certs(self.secure, self.service_certs, ground + drone + bound)
        ros2 = {p.identity: int(p.env.get("AERMANI_ROS2_DOMAIN_ID", "0") or 0) for p in self.procs if p.name == "ros2"}
        self.router = zenoh.open(router_config("ground", self.secure, tls_listen=self.tls_listen, services=ground,
                                               ros2_domains=ros2, vehicles=vehicles if bound else None))
        if drone:
            try:
                self.drone_router = zenoh.open(router_config(
                    "drone", self.secure, local=self.drone_endpoint, connect=[self.endpoint], services=drone,
                    own=cert_files(self.service_certs, bound[0]) if bound else None))
            except BaseException:
                self.router.close()  # type: ignore[no-untyped-call]
                self.router = None
                raise

    def wait_alive(self, names: list[str] | None = None, timeout: float = 90.0) -> None:
        """Block until every (or the named) service has declared its liveliness token."""
        want = {(p.vehicle_id, p.name) for p in self.procs if names is None or p.name in names}
        deadline = time.monotonic() + timeout
        while True:
            alive = self.alive()
            if want <= alive:
                return
            for p in self.procs:
                if not self.supervise and p.proc is not None and p.proc.poll() is not None:
                    raise RuntimeError(f"{p.label} exited with {p.proc.returncode}:\n{p.tail()}")
            if time.monotonic() > deadline:
                missing = sorted(f"{v}/{n}" for v, n in want - alive)
                tails = "\n".join(f"--- {p.label}:\n{p.tail()}" for p in self.procs
                                  if (p.vehicle_id, p.name) in want - alive)
                raise TimeoutError(f"services not alive after {timeout:.0f} s: {missing}\n{tails}")
            time.sleep(0.2)

    def alive(self) -> set[tuple[str, str]]:
        """(vehicle_id, service) pairs whose liveliness token is present now."""
        if self.router is None:
            return set()
        out = set()
        with contextlib.suppress(Exception):
            for reply in self.router.liveliness().get(alive_pattern(), timeout=2.0):
                if reply.ok is not None:
                    with contextlib.suppress(ValueError):
                        out.add(parse_alive_key(str(reply.ok.key_expr)))
        return out

    def kill(self, name: str, sig: int = signal.SIGKILL, vehicle_id: str | None = None) -> None:
        p = self.find(name, vehicle_id)
        if p.proc is not None and p.proc.poll() is None:
            p.proc.send_signal(sig)

    def _supervise(self) -> None:
        self._watch_heartbeats()
        while not self._stop.wait(0.2):
            now = time.monotonic()
            for p in self.procs:
                try:
                    self._supervise_one(p, now)
                except Exception as exc:  # one service's trouble never ends the supervision of the others
                    self._event(f"supervising {p.label} failed: {exc}")

    def _supervise_one(self, p: ServiceProcess, now: float) -> None:
        if p.proc is None:  # never started, or a restart failed: try again when due
            if p.next_start and now >= p.next_start and not self._stop.is_set():
                self._restart(p, now)
            return
        if p.proc.poll() is None:
            self._check_hung(p, now)
            return
        if p.next_start == 0.0:
            code = p.proc.returncode
            p.exit_codes.append(code)
            delay = self._backoff(p, now)
            self._event(f"{p.label} exited with {code}; restarting in {delay:.1f} s")
        elif now >= p.next_start and not self._stop.is_set():
            self._restart(p, now)

    def _backoff(self, p: ServiceProcess, now: float) -> float:
        """Schedule the next start: the delay doubles per crash (0.5 s .. 30 s); a long healthy run resets it."""
        if now - p.started_at > 60:
            p.restarts = 0
        delay: float = min(30.0, 0.5 * 2.0 ** p.restarts)
        p.next_start = now + delay
        return delay

    def _restart(self, p: ServiceProcess, now: float) -> None:
        p.restarts += 1
        p.next_start = 0.0
        try:
            p.start()
        except Exception as exc:  # fork failure, EMFILE, a log directory gone: keep supervising, retry later
            p.proc = None
            delay = self._backoff(p, now)
            self._event(f"restarting {p.label} failed ({exc}); trying again in {delay:.1f} s")
            return
        self._event(f"restarted {p.label} (pid {p.proc.pid if p.proc else '?'}, restart #{p.restarts})")

    def _watch_heartbeats(self) -> None:
        """Note every service's heartbeat (published from its event loop) on the routers this stack runs."""
        for router in (self.router, self.drone_router):
            if router is not None:
                self._watch_heartbeats_on(router)

    def _watch_heartbeats_on(self, router: zenoh.Session) -> None:
        def on_beat(sample: zenoh.Sample) -> None:
            with contextlib.suppress(Exception):
                parts = str(sample.key_expr).split("/")
                beat = Heartbeat.model_validate_json(sample.payload.to_bytes())
                self._beats[(parts[2], parts[4])] = (time.monotonic(), beat.pid)

        with contextlib.suppress(Exception):
            router.declare_subscriber(heartbeat_pattern(), on_beat)

    def restart_router(self, down_s: float = 0.0, timeout: float = 30.0) -> None:
        """Close the stack's router and open it again on the same endpoint after `down_s` seconds (a router
        restart, for fault injection). The services are Zenoh clients that reconnect by themselves. Their
        heartbeats could not reach the supervisor meanwhile: it forgets them, so none is taken for hung."""
        if self.secure is not None or self.router is None:
            raise RuntimeError("restart_router: only the plain router of a started stack")
        router, self.router = self.router, None
        self._beats.clear()
        with contextlib.suppress(Exception):
            router.close()  # type: ignore[no-untyped-call]
        self._event(f"router {self.endpoint} closed")
        time.sleep(down_s)
        deadline = time.monotonic() + timeout
        while True:
            try:
                opened = open_router(self.port, self.host, connect=self.link)
                break
            except Exception as exc:  # the port may linger a moment after the close
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the router did not reopen on {self.endpoint}: {exc}") from exc
                time.sleep(0.2)
        self._beats.clear()
        if self.supervise:
            self._watch_heartbeats_on(opened)
        self.router = opened
        self._event(f"router {self.endpoint} reopened")

    def _check_hung(self, p: ServiceProcess, now: float) -> None:
        """A live process whose heartbeat stopped is hung (a blocked loop, SIGSTOP): kill it, and the next
        round restarts it like a crash."""
        assert p.proc is not None
        seen = self._beats.get((p.vehicle_id, p.name))
        if seen is None or seen[1] != p.proc.pid:  # not beating yet since this start
            return
        quiet = now - seen[0]
        if quiet > self.hung_after_s:
            self._event(f"{p.label} (pid {p.proc.pid}) is hung: no heartbeat for {quiet:.1f} s; killing it")
            self._beats.pop((p.vehicle_id, p.name), None)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.proc.pid, signal.SIGKILL)

    def _event(self, text: str) -> None:
        self.events.append(text)
        log.info("%s", text)

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM every service (reverse start order), wait, SIGKILL stragglers, close the router."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for p in reversed(self.procs):
            if p.running and p.proc is not None:
                with contextlib.suppress(ProcessLookupError):
                    p.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for p in reversed(self.procs):
            if p.proc is None:
                continue
            try:
                p.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._event(f"{p.label} did not stop in {timeout:.0f} s; killing")
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.proc.pid, signal.SIGKILL)
                p.proc.wait(timeout=5)
        if self.drone_router is not None:
            with contextlib.suppress(Exception):
                self.drone_router.close()  # type: ignore[no-untyped-call]
            self.drone_router = None
        if self.router is not None:
            with contextlib.suppress(Exception):
                self.router.close()  # type: ignore[no-untyped-call]
            self.router = None
        if self.service_certs is not None:
            shutil.rmtree(self.service_certs, ignore_errors=True)

    def __enter__(self) -> Stack:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def status(self) -> list[dict[str, Any]]:
        alive = self.alive()
        return [{"service": p.label, "pid": p.proc.pid if p.proc else None, "running": p.running,
                 "alive": (p.vehicle_id, p.name) in alive, "restarts": p.restarts, "log": str(p.log_path)}
                for p in self.procs]

    def status_json(self) -> str:
        return json.dumps(self.status())


def loopback_mavlink_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """Free loopback UDP ports for the simulator/bridge MAVLink pair (and the simulator's ground-station link), so
    a stack never collides with another one on the machine; `extra` settings win."""
    api = free_udp_port()
    return {"AERMANI_SIM_API_PORT": str(api), "AERMANI_SIM_API_LOCAL_PORT": str(free_udp_port()),
            "AERMANI_SIM_GCS_PORT": str(free_udp_port()), "AERMANI_SIM_GCS_LOCAL_PORT": str(free_udp_port()),
            "AERMANI_AUTOPILOT_BRIDGE_CONNECTION": f"udpin:127.0.0.1:{api}", **(extra or {})}

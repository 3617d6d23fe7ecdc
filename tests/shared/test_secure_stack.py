"""`aermani up --secure` attacked from outside and used from inside (issue 32).

The launcher's secure stack as a user runs it: a ground and a drone router from shared/routers/, linked by
mutual TLS, every service a real process with a certificate of its own for this run and only its job's rights.
The outsider test finds every socket the stack listens on (from the kernel's socket table, not from what the
launcher says it opened) and tries each door: a plain Zenoh session, TLS without a certificate, a certificate
of another CA, then the deployment's read-only and drone certificates and one service's leaked certificate on
the listeners that take them. None may command the vehicle, fake its state or fake a service's presence; the
ground identity and the executor's own certificate, tried the same way, can (so a refusal is the ACL's, not a
broken stack's). The task test runs a whole pick-and-place with an operator's approval over HTTP under
--secure: every service's messages (approvals and heartbeats included) pass their routers."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import time
from pathlib import Path

import httpx
import psutil
import pytest
import zenoh

from aermani.launcher import Stack, free_port, loopback_mavlink_env
from shared.bus import Bus, zenoh_config
from shared.errors import BusError, NoResponder
from shared.keys import Keys
from shared.messages import Scenario
from shared.security import client_config, init_certs
from tests.gateway.conftest import TOKEN, wait_task
from tests.gateway.test_fullstack import wait_grounded
from tests.helpers import arun

pytestmark = pytest.mark.integration
K = Keys("am1")
OTHER = Keys("am2")
HOLD = {"kind": "hold"}


def listeners(stack: Stack, before: set[int] = frozenset()) -> tuple[set[int], set[tuple[str, int]]]:
    """TCP ports the stack listens on, and every UDP address it bound: its service processes' (and their
    children's) sockets and this process's (the routers run in it; `before`: ports this process held
    before the stack started, not the stack's), from the kernel's tables."""
    procs = [psutil.Process(os.getpid())]
    for p in stack.procs:
        if p.proc is not None and p.proc.poll() is None:
            with contextlib.suppress(psutil.NoSuchProcess):
                parent = psutil.Process(p.proc.pid)
                procs += [parent, *parent.children(recursive=True)]
    tcp: set[int] = set()
    udp: set[tuple[str, int]] = set()
    for proc in procs:
        with contextlib.suppress(psutil.NoSuchProcess, psutil.AccessDenied):
            for c in proc.net_connections(kind="inet"):
                if proc.pid == os.getpid() and c.laddr.port in before:
                    continue
                if c.type == 1 and c.status == psutil.CONN_LISTEN:  # SOCK_STREAM
                    assert c.laddr.ip in ("127.0.0.1", "::1"), f"{proc.name()} listens beyond loopback: {c.laddr}"
                    tcp.add(c.laddr.port)
                elif c.type == 2 and not c.raddr:  # SOCK_DGRAM, bound
                    udp.add((c.laddr.ip, c.laddr.port))
    return tcp, udp


async def _reset(config: zenoh.Config, scenario: Scenario) -> None:
    async with await Bus.open(config=config) as bus:
        res = await bus.query(K.sim_reset, scenario, timeout=30)
        assert res.ok, res.message


def _own_ports() -> set[int]:
    return {c.laddr.port for c in psutil.Process(os.getpid()).net_connections(kind="inet")}


async def _opens(config: zenoh.Config) -> Bus | None:
    try:
        return await Bus.open(config=config)
    except BusError:
        return None


def _no_cert(endpoint: str, ca: Path) -> zenoh.Config:
    """TLS that trusts the deployment's CA but shows no certificate of its own."""
    cfg = zenoh_config(connect=[endpoint], connect_timeout_s=3)
    cfg.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ca)))
    cfg.insert_json5("transport/link/tls/verify_name_on_connect", "false")
    return cfg


COMMANDS = {"autopilot/command": HOLD, "executor/run_skill": {"skill": "land"},
            "reasoner/start_task": {"command": "land"}, "sim/fault": {"unit": "camera", "type": "off"}}


async def _commands(bus: Bus, names: list[str]) -> list[str]:
    """The command keys among `names` this session got an answer on (none, for anyone the ACL refuses)."""
    answered = []
    for name in names:
        with contextlib.suppress(NoResponder, BusError):
            await bus.query(K.key(name), COMMANDS[name], timeout=1.5)
            answered.append(name)
    return answered


@pytest.mark.timeout(600)
async def test_an_outsider_gets_no_reply_and_fakes_nothing_on_any_door_of_a_secure_stack(tmp_path):
    init_certs(tmp_path / "certs")
    init_certs(tmp_path / "other-ca")  # a CA of another deployment, certificates with the right names
    env = loopback_mavlink_env({"AERMANI_GATEWAY_PORT": str(free_port()), "AERMANI_GATEWAY_TOKEN": TOKEN,
                                "AERMANI_GATEWAY_DB_PATH": str(tmp_path / "gw.sqlite3")})
    stack = Stack(["sim", "autopilot_bridge", "perception", "executor", "gateway"], env=env,
                  log_dir=tmp_path / "logs", supervise=False, secure=tmp_path / "certs")
    certs, svc = tmp_path / "certs", stack.service_certs
    assert svc is not None
    faked: list[tuple[str, str]] = []
    before = _own_ports()
    with stack:
        tcp, udp = listeners(stack, before)
        zenoh_doors = {stack.endpoint, stack.drone_endpoint}
        assert {int(e.rsplit(":", 1)[1]) for e in zenoh_doors} <= tcp
        assert all(ip in ("127.0.0.1", "::1") for ip, _ in udp), udp  # MAVLink stays on loopback
        for p in stack.procs:  # no plain listener: every service reaches its router over TLS
            assert p.env["AERMANI_ZENOH_CONNECT"].startswith("tls/127.0.0.1:"), (p.label, p.env)
        watch = stack.router.declare_subscriber("aermani/v1/**", lambda s: faked.append(
            (str(s.key_expr), s.payload.to_bytes().decode(errors="replace"))))

        # 1. Nobody without a deployment identity gets a session on any TCP port of the stack.
        attempts: list[tuple[str, zenoh.Config]] = []
        for port in sorted(tcp):
            plain, tls = f"tcp/127.0.0.1:{port}", f"tls/127.0.0.1:{port}"
            attempts += [(plain, zenoh_config(connect=[plain], connect_timeout_s=3)),
                         (tls, _no_cert(tls, certs / "ca.pem"))]
            attempts += [(tls, client_config(tmp_path / "other-ca", ident, [tls], connect_timeout_s=3))
                         for ident in ("ground", "drone")]
        opened = await asyncio.gather(*(_opens(c) for _, c in attempts))
        leaked = [door for (door, _), b in zip(attempts, opened, strict=True) if b is not None]
        for b in opened:
            if b is not None:
                await b.close()
        assert not leaked, f"sessions opened without a deployment identity on {leaked}"

        # 2. Identities of the deployment without these rights, on every listener that takes them: no command
        # answered, no forged sample delivered, no fake presence. (identity, its files, listener, commands it
        # may not give, vehicles whose state it may not publish.)
        everything, both = list(COMMANDS), [K, OTHER]
        tries = [(ident, certs, ep, everything, both) for ident in ("client", "drone") for ep in sorted(zenoh_doors)]
        tries += [(ident, svc, stack.drone_endpoint, everything, both) for ident in ("perception@am1", "sim@am1")]
        # The gateway starts tasks and runs skills by hand: its job, not the autopilot's or the simulator's.
        tries += [("gateway@fleet", svc, stack.endpoint, ["autopilot/command", "sim/fault"], both)]
        # The vehicle's own router speaks for am1, never for another vehicle.
        tries += [("router@am1", svc, stack.endpoint, ["autopilot/command", "sim/fault"], [OTHER])]
        for ident, d, ep, forbidden, victims in tries:
            bus = await _opens(client_config(d, ident, [ep], connect_timeout_s=5))
            if bus is None:  # a router that does not take this identity at all
                continue
            try:
                answered = await _commands(bus, forbidden)
                assert not answered, f"{ident} on {ep} got answers on {answered}"
                mark = b'{"forged": "' + ident.encode() + b'"}'
                for victim in victims:
                    bus.session.put(victim.autopilot_state.key, mark)
                    bus.session.put(victim.key("executor/skill_status"), mark)
                tokens = [bus.session.liveliness().declare_token(v.alive(f"intruder_{ident.split('@')[0]}"))
                          for v in victims]
                await asyncio.sleep(1.0)
                alive = {name for _, name in stack.alive()}
                for token in tokens:
                    token.undeclare()
                assert not any(n.startswith("intruder") for n in alive), (ident, ep, alive)
            finally:
                await bus.close()
        await asyncio.sleep(0.5)
        forged = [(k, v) for k, v in faked if "forged" in v]
        assert any(k == K.autopilot_state.key for k, _ in faked), "the watch saw not even the real state"
        assert not forged, f"forged samples reached the ground router: {forged}"

        # 3. The same tries with the rights to command succeed: the ground identity over the ground's TLS
        # listener, the executor's own certificate on the drone router.
        for ident, d, ep in (("ground", certs, stack.endpoint), ("executor@am1", svc, stack.drone_endpoint)):
            async with await Bus.open(config=client_config(d, ident, [ep], connect_timeout_s=5)) as bus:
                reply = json.loads(await bus.query(K.autopilot_command.key, HOLD, timeout=5.0))
                assert reply["kind"] == "autopilot_result" and reply["command"] == "hold", (ident, reply)
        watch.undeclare()
    assert not svc.exists(), "the services' certificates outlive the stack"


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_a_task_with_operator_approval_runs_under_secure(tmp_path):
    """Every service on its own certificate and rights, the operator over HTTP: the grasp waits for an
    approval the reasoner publishes on the bus, the gateway lists it, the operator approves, the cup is
    placed and the task succeeds."""
    init_certs(tmp_path / "certs")
    port = free_port()
    env = loopback_mavlink_env({
        "AERMANI_SIM_SPEED_FACTOR": "4", "AERMANI_SIM_FPS": "5", "AERMANI_REASONER_BACKEND": "rules",
        # The task must succeed, so the world is the ideal one (the realistic one's gusts and drift leave the
        # grasp to chance: tests/reasoner/test_demo.py).
        "AERMANI_SIM_REALISM": "ideal",
        # The reasoner's default step cap: in this layout the rules policy's search for the table after the
        # grasp took 24 steps in one run and had not found it at step 40 in another (issue 33's search).
        "AERMANI_REASONER_T_MAX_S": "240", "AERMANI_REASONER_MAX_STEPS": "80",
        "AERMANI_REASONER_APPROVAL": '["grasp"]', "AERMANI_REASONER_APPROVAL_TIMEOUT_S": "120",
        "AERMANI_GATEWAY_PORT": str(port), "AERMANI_GATEWAY_TOKEN": TOKEN,
        "AERMANI_GATEWAY_DB_PATH": str(tmp_path / "gw.sqlite3"), "AERMANI_RECORDER_DIR": str(tmp_path / "rec")})
    stack = Stack(["sim", "autopilot_bridge", "perception", "executor", "reasoner", "recorder", "gateway"],
                  env=env, log_dir=tmp_path / "logs", supervise=False, secure=tmp_path / "certs")
    try:
        with stack, httpx.Client(base_url=f"http://127.0.0.1:{port}/api/v1", timeout=30,
                                 headers={"Authorization": f"Bearer {TOKEN}"}) as c:
            deadline = time.monotonic() + 120
            while True:  # the gateway hears every service's heartbeat-backed health across the routers
                with contextlib.suppress(httpx.HTTPError):
                    v = next(v for v in c.get("/health").json()["vehicles"] if v["vehicle_id"] == "am1")
                    if all(v["services"].get(s) for s in ("reasoner", "executor", "perception", "autopilot_bridge")) \
                            and v.get("state") and v["state"]["link_ok"]:
                        break
                assert time.monotonic() < deadline, "the gateway never saw the vehicle's services and state"
                time.sleep(0.5)
            # The evaluation's way to lay out a scenario: the ground identity over the TLS listener.
            ground = client_config(tmp_path / "certs", "ground", [stack.endpoint], connect_timeout_s=10)
            arun(_reset(ground, Scenario(seed=1, target_object="red cup", destination="table")), 60)
            wait_grounded(c)
            created = c.post("/tasks", json={"command": "Pick up the red cup and place it on the table."})
            assert created.status_code == 202, created.text
            task_id = created.json()["task_id"]
            deadline = time.monotonic() + 300
            while True:
                pending = c.get("/approvals").json()
                if pending:
                    break
                state = c.get(f"/tasks/{task_id}").json()["state"]
                assert state in ("pending", "running"), f"task ended {state} before any approval was asked"
                assert time.monotonic() < deadline, "no approval request reached the gateway"
                time.sleep(0.3)
            assert pending[0]["skill"] == "grasp" and pending[0]["task_id"] == task_id, pending
            decided = c.post(f"/approvals/{pending[0]['approval_id']}", json={"approve": True, "operator": "test"})
            assert decided.status_code == 200, decided.text
            done = wait_task(c, task_id, {"succeeded", "failed", "aborted", "timeout"}, timeout=400)
            assert done["state"] == "succeeded", done
            steps = [s["step"] for s in done["reasoning_steps"]]
            grasps = [s for s in steps if (s.get("ste") or {}).get("skill") == "grasp"]
            assert grasps and grasps[-1]["skill_state"] == "succeeded", grasps
    except BaseException:
        for p in stack.procs:
            print(f"--- log of {p.label} ---\n{p.tail(40)}")
        raise

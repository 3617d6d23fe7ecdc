"""Mutual TLS and access control on real routers over loopback, with certificates from `aermani certs init`.

Topology as in the field: a ground router (plain loopback listener for the ground station's services, mutual
TLS listener for everything else) and a drone router (loopback listener for the vehicle's services) linked
to it over mutual TLS with the drone's certificate. Stand-ins for the reasoner (start_task) and the bridge
(autopilot/command) are real Zenoh sessions on their side's loopback listener; outsiders connect to the
ground router's TLS listener with one certificate each."""

from __future__ import annotations

import asyncio
import contextlib
import json
import stat

import pytest
import zenoh

from aermani.launcher import free_port, open_router
from shared.bus import Bus
from shared.errors import ConfigError, NoResponder
from shared.keys import Keys
from shared.security import (
    IDENTITIES,
    ROUTERS_DIR,
    client_config,
    common_name,
    init_certs,
    require_loopback,
    router_config,
)
from tests.helpers import first_answer, matched

K = Keys("am1")


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    d = tmp_path_factory.mktemp("certs")
    init_certs(d)
    return d


@pytest.fixture(scope="module")
def routers(certs):
    ground_local, tls, drone_local = free_port(), free_port(), free_port()
    ground = zenoh.open(router_config("ground", certs, local=f"tcp/127.0.0.1:{ground_local}",
                                      tls_listen=[f"tls/127.0.0.1:{tls}"]))
    drone = zenoh.open(router_config("drone", certs, local=f"tcp/127.0.0.1:{drone_local}",
                                     connect=[f"tls/127.0.0.1:{tls}"]))
    yield {"ground": f"tcp/127.0.0.1:{ground_local}", "tls": f"tls/127.0.0.1:{tls}",
           "drone": f"tcp/127.0.0.1:{drone_local}", "certs": certs}
    drone.close()
    ground.close()


class Deployment:
    """The stand-in services on both sides and what they received."""

    def __init__(self, routers: dict) -> None:
        self.r = routers
        self.calls: dict[str, list] = {"start_task": [], "autopilot_command": [], "run_skill": []}

    async def __aenter__(self) -> Deployment:
        self.reasoner = await Bus.open(connect=[self.r["ground"]], connect_timeout_s=5)
        self.bridge = await Bus.open(connect=[self.r["drone"]], connect_timeout_s=5)

        def recorder(name: str):
            async def handler(req):
                self.calls[name].append(req)
                return {"accepted": True}
            return handler

        self.reasoner.serve(K.start_task.key, recorder("start_task"))
        self.bridge.serve(K.autopilot_command.key, recorder("autopilot_command"))
        self.bridge.serve(K.run_skill.key, recorder("run_skill"))
        self.abort_at_drone = self.bridge.subscribe(K.abort.key)
        self.abort_at_ground = self.reasoner.subscribe(K.abort.key)
        self.state_at_ground = self.reasoner.subscribe(K.autopilot_state.key)
        self.state_at_drone = self.bridge.subscribe(K.autopilot_state.key)
        # Declarations cross the TLS link between the routers: wait until the ground side reaches the bridge.
        probe = await Bus.open(connect=[self.r["ground"]], connect_timeout_s=5)
        try:
            async def reachable() -> bool:
                with contextlib.suppress(NoResponder):
                    await probe.query(K.run_skill.key, {"probe": True}, timeout=1.0)
                    return True
                return False

            for _ in range(50):
                if await reachable():
                    break
                await asyncio.sleep(0.1)
            else:
                raise TimeoutError("the drone router's queryables never reached the ground router")
        finally:
            await probe.close()
        self.calls["run_skill"].clear()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.reasoner.close()
        await self.bridge.close()

    async def outsider(self, identity: str) -> Bus:
        return await Bus.open(config=client_config(self.r["certs"], identity, [self.r["tls"]], connect_timeout_s=5))


async def _refused(bus: Bus, key: str) -> None:
    with pytest.raises(NoResponder):
        await bus.query(key, {"kind": "goto", "x": 0.0, "y": 0.0, "z": 10.0}, timeout=2.0)


def test_certs_have_distinct_common_names_and_private_keys(certs):
    names = {identity: common_name(certs / f"{identity}.pem") for identity in IDENTITIES}
    assert names == IDENTITIES and len(set(names.values())) == len(names)
    for key in certs.glob("*.key"):
        assert stat.S_IMODE(key.stat().st_mode) == 0o600, key
    with pytest.raises(ConfigError, match="--force"):
        init_certs(certs)


def test_templates_turn_rest_off_and_deny_by_default(certs):
    for role in ("ground", "drone"):
        cfg = router_config(role, certs, local="tcp/127.0.0.1:1")
        assert json.loads(cfg.get_json("plugins")) == {}, "the REST plugin must be off"
        acl = json.loads(cfg.get_json("access_control"))
        assert acl["enabled"] is True and acl["default_permission"] == "deny"
        assert all(r["permission"] == "allow" for r in acl["rules"])
        assert json.loads(cfg.get_json("transport/link/tls/enable_mtls")) is True
        listen = json.loads(cfg.get_json("listen/endpoints"))
        assert all(e.startswith("tls/") or e.startswith("tcp/127.0.0.1:") for e in listen), listen
    assert (ROUTERS_DIR / "ground.json5").is_file() and (ROUTERS_DIR / "drone.json5").is_file()


def test_plain_listeners_beyond_loopback_are_refused(certs):
    with pytest.raises(ConfigError, match="loopback"):
        open_router(free_port(), host="0.0.0.0")
    with pytest.raises(ConfigError, match="loopback"):
        router_config("ground", certs, local="tcp/0.0.0.0:7447")
    with pytest.raises(ConfigError, match="tls"):
        router_config("drone", certs, connect=["tcp/192.0.2.1:7447"])
    require_loopback(["tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tcp/localhost:1"])


def test_a_session_without_a_certificate_cannot_connect(routers, tmp_path):
    plain = zenoh.Config()
    plain.insert_json5("mode", '"client"')
    plain.insert_json5("connect/endpoints", json.dumps([routers["tls"]]))
    plain.insert_json5("connect/timeout_ms", "2000")
    plain.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(routers["certs"] / "ca.pem")))
    with pytest.raises(zenoh.ZError):
        zenoh.open(plain)
    # A certificate from another CA (someone else's `certs init`) is no better.
    init_certs(tmp_path)
    foreign = client_config(tmp_path, "ground", [routers["tls"]], connect_timeout_s=2)
    foreign.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(routers["certs"] / "ca.pem")))
    with pytest.raises(zenoh.ZError):
        zenoh.open(foreign)


async def test_drone_certificate_cannot_start_tasks_or_command_the_autopilot(routers):
    async def main():
        async with Deployment(routers) as dep:
            for identity in ("drone", "client"):
                outsider = await dep.outsider(identity)
                try:
                    await _refused(outsider, K.start_task)
                    await _refused(outsider, K.autopilot_command)
                    await _refused(outsider, K.run_skill)
                    await _refused(outsider, "aermani/**")  # a wildcard query finds no allow rule either
                finally:
                    await outsider.close()
            assert dep.calls == {"start_task": [], "autopilot_command": [], "run_skill": []}

    await main()


async def test_ground_certificate_starts_tasks_and_commands_the_autopilot(routers):
    async def main():
        async with Deployment(routers) as dep:
            ground = await dep.outsider("ground")
            try:
                assert await ground.query(K.start_task.key, {"text": "pick up the cup"}, timeout=3.0)
                assert await ground.query(K.autopilot_command.key, {"kind": "hold"}, timeout=3.0)
            finally:
                await ground.close()
            # The ground station's own services (loopback listener) reach the drone through the TLS link.
            local = await Bus.open(connect=[routers["ground"]], connect_timeout_s=5)
            try:
                assert await local.query(K.run_skill.key, {"skill": "takeoff"}, timeout=3.0)
            finally:
                await local.close()
            assert len(dep.calls["start_task"]) == 1 and len(dep.calls["autopilot_command"]) == 1
            assert len(dep.calls["run_skill"]) == 1

    await main()


async def test_abort_works_from_every_identity_and_state_only_from_the_drone(routers):
    async def main():
        async with Deployment(routers) as dep:
            for identity in ("ground", "drone", "client"):
                outsider = await dep.outsider(identity)
                try:
                    await matched(outsider, K.abort)  # a fixed pause raced the new session's routes under load
                    outsider.publish(K.abort.key, {"source": identity})
                    got_drone = await dep.abort_at_drone.recv(timeout=5.0)
                    got_ground = await dep.abort_at_ground.recv(timeout=5.0)
                    assert json.loads(got_drone) == json.loads(got_ground) == {"source": identity}
                    outsider.publish(K.autopilot_state.key, {"z": 50.0, "from": identity})
                finally:
                    await outsider.close()
            # The vehicle's own bridge publishes state through the drone router: it reaches the ground.
            dep.bridge.publish(K.autopilot_state.key, {"z": 1.0, "from": "bridge"})
            at_ground: list[str] = []
            while "bridge" not in at_ground:
                at_ground.append(json.loads(await dep.state_at_ground.recv(timeout=5.0))["from"])
            at_drone: list[str] = []
            while "bridge" not in at_drone:
                at_drone.append(json.loads(await dep.state_at_drone.recv(timeout=5.0))["from"])
            # At the ground router a drone certificate may publish vehicle state (it is the vehicle router's
            # identity); the ground station and observers may not. The drone router takes vehicle state from
            # nobody beyond its host: what the ground router relays arrives from the ground's identity.
            assert sorted(at_ground) == ["bridge", "drone"], at_ground
            assert at_drone == ["bridge"], at_drone

    await main()


async def test_depth_crosses_to_the_ground_once_a_second_and_segmentation_passes_the_acl(routers):
    """The drone router thins depth on its TLS link to the ground (1 Hz) while the vehicle's own subscribers get
    every frame; the oracle's segmentation key (a verbatim chunk, which `**` rules do not match) is allowed."""
    async def main():
        async with Deployment(routers) as dep:
            camera = await Bus.open(connect=[dep.r["drone"]], connect_timeout_s=5)
            try:
                depth_ground = dep.reasoner.subscribe(K.camera_depth.key, maxsize=1000)
                seg_ground = dep.reasoner.subscribe(K.camera_segmentation.key, maxsize=1000)
                depth_drone = dep.bridge.subscribe(K.camera_depth.key, maxsize=1000)
                got = None
                for _ in range(100):  # until the ground's subscriptions have reached the drone router
                    camera.publish(K.camera_segmentation.key, b"seg", reliable=True)
                    with contextlib.suppress(TimeoutError):
                        got = await seg_ground.recv_sample(timeout=0.1)
                        break
                assert got is not None and got.payload == b"seg"
                loop = asyncio.get_running_loop()
                t0, sent = loop.time(), 45
                for i in range(sent):  # 3 s at 15 fps
                    camera.publish(K.camera_depth.key, b"d%d" % i, reliable=True)
                    await asyncio.sleep(max(0.0, t0 + (i + 1) / 15 - loop.time()))
                elapsed = loop.time() - t0
                at_drone = [await depth_drone.recv_sample(timeout=10) for _ in range(sent)]
                await asyncio.sleep(0.5)
                at_ground = []
                while (rec := depth_ground.recv_nowait()) is not None:
                    at_ground.append(rec)
                assert len(at_drone) == sent
                assert 1 <= len(at_ground) <= elapsed + 2, (len(at_ground), elapsed)
            finally:
                await camera.close()

    await main()


@pytest.mark.integration
async def test_secure_stack_real_bridge_obeys_the_ground_only(tmp_path):
    """`aermani up --secure` in miniature: the launcher's two routers, the real simulator and bridge as
    processes on the drone side; an outsider with the drone certificate cannot command, the ground can."""
    from aermani.launcher import Stack, free_udp_port

    init_certs(tmp_path / "certs")
    api = free_udp_port()
    env = {"AERMANI_SIM_API_PORT": str(api), "AERMANI_SIM_API_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_SIM_GCS_PORT": str(free_udp_port()), "AERMANI_SIM_GCS_LOCAL_PORT": str(free_udp_port()),
           "AERMANI_AUTOPILOT_BRIDGE_CONNECTION": f"udpin:127.0.0.1:{api}"}
    stack = Stack(["sim", "autopilot_bridge"], env=env, log_dir=tmp_path / "logs", supervise=False,
                  secure=tmp_path / "certs")
    assert stack.find("autopilot_bridge").env["AERMANI_ZENOH_CONNECT"] == stack.drone_endpoint != stack.endpoint

    async def main():
        for identity, allowed in (("drone", False), ("client", False), ("ground", True)):
            bus = await Bus.open(config=client_config(tmp_path / "certs", identity, stack.tls_listen,
                                                      connect_timeout_s=5))
            try:
                if allowed:
                    reply = json.loads(await bus.query(K.autopilot_command.key, {"kind": "hold"}, timeout=5.0))
                    assert reply["kind"] == "autopilot_result" and reply["command"] == "hold", reply
                else:
                    await _refused(bus, K.autopilot_command)
            finally:
                await bus.close()

    with stack:
        assert {("am1", "sim"), ("am1", "autopilot_bridge")} <= stack.alive()  # tokens cross the TLS link
        await main()


async def test_queries_carry_the_senders_name_and_session_id():
    """What the bridge logs as a command's sender: the querier's Bus.name and Zenoh session id (claimed in
    the query's attachment; sanitised for the log)."""
    from shared.bus import Caller

    port = free_port()
    router = open_router(port)

    async def main():
        server = await Bus.open(connect=[f"tcp/127.0.0.1:{port}"])
        client = await Bus.open(connect=[f"tcp/127.0.0.1:{port}"])
        client.name = "executor"
        seen: list[Caller] = []

        async def handler(req, caller):
            seen.append(caller)
            return {"ok": True}

        try:
            server.serve("test/caller", handler, with_caller=True)
            await first_answer(client, "test/caller", {"x": 1})
            assert seen == [Caller("executor", str(client.session.zid()))]
        finally:
            await client.close()
            await server.close()

    try:
        await main()
    finally:
        router.close()
    assert str(Caller.from_attachment(b'{"sender": "a\\nINFO forged line", "zid": "z"}')) == "aINFO forged line (zid z)"
    assert Caller.from_attachment(None).sender.startswith("unknown")


@pytest.mark.integration
async def test_router_command_used_by_compose(tmp_path, certs):
    """`aermani router --role ground|drone` (the compose routers) as real processes: the drone router links
    to the ground router over mutual TLS, the ground identity reaches the vehicle, a drone certificate does
    not, and SIGTERM stops both cleanly."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    ground_local, tls, drone_local = free_port(), free_port(), free_port()
    env = {**os.environ, "PYTHONPATH": str(root)}
    cmd = [sys.executable, "-m", "aermani.cli", "router", "--certs", str(certs)]
    procs = [subprocess.Popen([*cmd, "--role", "ground", "--local", f"tcp/127.0.0.1:{ground_local}",
                               "--tls-listen", f"tls/127.0.0.1:{tls}"], env=env, cwd=root,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True),
             subprocess.Popen([*cmd, "--role", "drone", "--local", f"tcp/127.0.0.1:{drone_local}",
                               "--connect", f"tls/127.0.0.1:{tls}"], env=env, cwd=root,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)]

    async def main():
        bridge = await Bus.open(connect=[f"tcp/127.0.0.1:{drone_local}"], connect_timeout_s=20)
        calls = []

        async def handler(req):
            calls.append(req)
            return {"ok": True}

        try:
            bridge.serve(K.autopilot_command.key, handler)
            ground = await Bus.open(config=client_config(certs, "ground", [f"tls/127.0.0.1:{tls}"],
                                                         connect_timeout_s=20))
            drone = await Bus.open(config=client_config(certs, "drone", [f"tls/127.0.0.1:{tls}"],
                                                        connect_timeout_s=20))
            try:
                for _ in range(100):  # until the drone router's queryable has crossed the link
                    with contextlib.suppress(NoResponder):
                        await ground.query(K.autopilot_command.key, {"kind": "hold"}, timeout=1.0)
                        break
                    await asyncio.sleep(0.1)
                assert calls, "the ground identity never reached the vehicle through the router processes"
                await _refused(drone, K.autopilot_command)
                assert len(calls) == 1
            finally:
                await ground.close()
                await drone.close()
        finally:
            await bridge.close()

    seen = ["", ""]

    def wait_up(i: int, role: str) -> None:
        """Until the router process says it is up (its start is seconds of interpreter start on a busy
        machine: a fixed connect timeout raced it)."""
        for line in procs[i].stdout:
            seen[i] += line
            if f"{role} router up" in line:
                return
        raise AssertionError(f"the {role} router exited before it was up: {seen[i]}")

    try:
        await asyncio.to_thread(wait_up, 0, "ground")
        await asyncio.to_thread(wait_up, 1, "drone")
        await main()
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
        outs = [seen[i] + procs[i].communicate(timeout=20)[0] for i in range(2)]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert "ground router up" in outs[0] and "drone router up" in outs[1]


@pytest.mark.parametrize("role", ["ground", "drone"])
def test_the_templates_let_each_side_serve_every_query_its_services_declare(certs, role):
    """A queryable the other router does not let through is unreachable across the link (the reasoner on the
    ground, the executor on the drone): cancel_skill and the action protocol's result queryables were left out
    once. Every query a drone service declares must pass `drone-serve`, every query of a ground service
    `ground-serve`."""
    from shared.keys import declared_by

    acl = json.loads(router_config(role, certs, local="tcp/127.0.0.1:1").get_json("access_control"))
    rules = {r["id"]: r for r in acl["rules"]}
    sides = {"drone-serve": ("executor", "perception", "autopilot_bridge", "sim"), "ground-serve": ("reasoner",)}
    for rule, services in sides.items():
        allowed = [zenoh.KeyExpr(k) for k in rules[rule]["key_exprs"]]
        assert set(rules[rule]["messages"]) >= {"declare_queryable", "reply"}
        for service in services:
            for q in declared_by(service)[1]:
                key = zenoh.KeyExpr(q.bind("am7").key)
                assert any(a.includes(key) for a in allowed), f"{role}.json5 {rule} does not let {key} through"

"""The gateway's browser-attack guard against the real server (uvicorn on loopback, a stand-in vehicle on a
real router): cross-site and DNS-rebinding requests are refused and change nothing, the token covers every
endpoint but /live, bodies are capped, security headers are set, /docs needs no CDN, and TLS works."""

from __future__ import annotations

import json
import os
import signal
import ssl
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from aermani.launcher import free_port, open_router
from shared.security import init_certs
from tests.gateway.conftest import TOKEN
from tests.gateway.fakes import Harness

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def open_gw(tmp_path_factory) -> Iterator[Harness]:
    """Loopback, no token: the mode a web page the operator visits could attack."""
    h = Harness(tmp_path_factory.mktemp("guard"), gateway_settings={"abort_ack_timeout_s": 0.2}).start()
    try:
        deadline = time.monotonic() + 30
        while not httpx.get(h.base_url + "/api/v1/health", timeout=5).json()["vehicles"]:
            assert time.monotonic() < deadline, "the stand-in vehicle never showed up"
            time.sleep(0.1)
        yield h
    finally:
        h.stop()


@pytest.fixture(scope="module")
def token_gw(tmp_path_factory) -> Iterator[Harness]:
    h = Harness(tmp_path_factory.mktemp("guard-token"), gateway_settings={"token": TOKEN}).start()
    try:
        yield h
    finally:
        h.stop()


def _aborts(h: Harness) -> int:
    return len(h.fake.aborts)


CROSS_SITE = [
    # A form post from another site: text/plain or form-encoded, the only types a form can send.
    ("form post", {"Content-Type": "application/x-www-form-urlencoded", "Origin": "http://evil.example"}, b"a=1"),
    ("no-cors fetch", {"Content-Type": "text/plain", "Origin": "http://evil.example",
                       "Sec-Fetch-Site": "cross-site"}, b"{}"),
    ("json from another origin", {"Content-Type": "application/json", "Origin": "http://evil.example"}, b"{}"),
    ("json from another local port", {"Content-Type": "application/json", "Origin": "http://127.0.0.1:1"}, b"{}"),
    ("sandboxed page", {"Content-Type": "application/json", "Origin": "null"}, b"{}"),
    ("cross-site without Origin", {"Content-Type": "application/json", "Sec-Fetch-Site": "cross-site"}, b"{}"),
    ("no content type", {}, b""),
]


@pytest.mark.parametrize(("name", "headers", "body"), CROSS_SITE, ids=[c[0] for c in CROSS_SITE])
def test_cross_site_state_changes_are_refused(open_gw, name, headers, body) -> None:
    before = _aborts(open_gw)
    for path in ("/api/v1/abort", "/api/v1/tasks"):
        r = httpx.post(open_gw.base_url + path, content=body, headers=headers, timeout=10)
        assert r.status_code in (403, 415), (name, path, r.status_code, r.text)
        err = r.json()
        assert err["status"] == r.status_code and err["detail"]
    time.sleep(0.3)
    assert _aborts(open_gw) == before, f"{name}: an abort got through"


def test_same_origin_json_still_works(open_gw) -> None:
    before = _aborts(open_gw)
    r = httpx.post(open_gw.base_url + "/api/v1/abort", json={"reason": "same-origin page"}, timeout=10,
                   headers={"Origin": open_gw.base_url, "Sec-Fetch-Site": "same-origin"})
    assert r.status_code == 202, r.text
    r = httpx.post(open_gw.base_url + "/api/v1/abort", json={"reason": "curl"}, timeout=10)  # no Origin: not a browser
    assert r.status_code == 202, r.text
    deadline = time.monotonic() + 10
    while _aborts(open_gw) < before + 2:
        assert time.monotonic() < deadline, "the accepted aborts never reached the vehicle"
        time.sleep(0.05)


@pytest.mark.parametrize("host", ["evil.example", f"evil.example:{80}", "rebind.attacker.test:8080", "10.0.0.5:8080",
                                  "127.0.0.1.nip.io:8080"])
def test_dns_rebinding_is_refused(open_gw, host) -> None:
    """A page on evil.example whose name now resolves to 127.0.0.1 sends Host: evil.example."""
    for method, path in (("GET", "/api/v1/health"), ("GET", "/api/v1/tasks"), ("GET", "/"),
                         ("POST", "/api/v1/abort")):
        r = httpx.request(method, open_gw.base_url + path, headers={"Host": host, "Content-Type": "application/json"},
                          content=b"{}" if method == "POST" else None, timeout=10)
        assert r.status_code == 403 and "DNS rebinding" in r.json()["detail"], (method, path, r.text)
    for host_ok in (f"127.0.0.1:{open_gw.http_port}", f"localhost:{open_gw.http_port}"):
        assert httpx.get(open_gw.base_url + "/api/v1/health", headers={"Host": host_ok}, timeout=10).status_code == 200


def test_body_size_is_capped(open_gw) -> None:
    big = json.dumps({"command": "x" * 200_000}).encode()
    r = httpx.post(open_gw.base_url + "/api/v1/tasks", content=big, headers={"Content-Type": "application/json"},
                   timeout=10)
    assert r.status_code == 413 and r.json()["error"] == "too_large"

    def chunks():  # no Content-Length: the cap counts what arrives
        for _ in range(40):
            yield b"x" * 4096

    r = httpx.post(open_gw.base_url + "/api/v1/tasks", content=chunks(), headers={"Content-Type": "application/json"},
                   timeout=10)
    assert r.status_code == 413, r.text


def test_security_headers_and_docs_without_cdn(open_gw) -> None:
    for path in ("/", "/api/v1/health", "/docs", "/api/v1/nope"):
        r = httpx.get(open_gw.base_url + path, timeout=10)
        assert r.headers["x-content-type-options"] == "nosniff", path
        assert r.headers["x-frame-options"] == "DENY"
        assert "frame-ancestors 'none'" in r.headers["content-security-policy"]
        assert r.headers["referrer-policy"] == "no-referrer"
    docs = httpx.get(open_gw.base_url + "/docs", timeout=10)
    assert docs.status_code == 200 and "POST /api/v1/tasks" in docs.text and "/api/v1/openapi.json" in docs.text
    assert "<script" not in docs.text and "cdn" not in docs.text.lower() and "http" not in docs.text.split("<body")[1]


def test_token_covers_every_endpoint_but_liveness(token_gw) -> None:
    base = token_gw.base_url + "/api/v1"
    assert httpx.get(base + "/live", timeout=10).json() == {"ok": True}
    for path in ("/health", "/tasks", "/tasks/task-x", "/tasks/task-x/events", "/vehicles/am1/camera.jpg"):
        r = httpx.get(base + path, timeout=10)
        assert r.status_code == 401, (path, r.status_code)
        assert TOKEN not in r.text
    ok = httpx.get(base + "/health", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10)
    assert ok.status_code == 200
    # With a token, a browser on another origin is still refused even if it somehow had the token.
    r = httpx.post(base + "/abort", json={}, timeout=10,
                   headers={"Authorization": f"Bearer {TOKEN}", "Origin": "http://evil.example"})
    assert r.status_code == 403


def test_gateway_process_serves_https_with_the_deployment_ca(tmp_path) -> None:
    """The real service process with AERMANI_GATEWAY_TLS_*: https with certificates from `aermani certs init`."""
    init_certs(tmp_path / "certs")
    router_port, port = free_port(), free_port()
    router = open_router(router_port)
    env = {k: v for k, v in os.environ.items() if not k.startswith("AERMANI_")}
    env.update(AERMANI_GATEWAY_PORT=str(port), AERMANI_GATEWAY_TOKEN=TOKEN, PYTHONPATH=str(ROOT),
               AERMANI_GATEWAY_DB_PATH=str(tmp_path / "gw.sqlite3"),
               AERMANI_ZENOH_CONNECT=f"tcp/127.0.0.1:{router_port}",
               AERMANI_GATEWAY_TLS_CERTFILE=str(tmp_path / "certs" / "ground.pem"),
               AERMANI_GATEWAY_TLS_KEYFILE=str(tmp_path / "certs" / "ground.key"))
    log = tmp_path / "gateway.log"
    with open(log, "wb") as logf:
        proc = subprocess.Popen([sys.executable, "-m", "services.gateway"], env=env, cwd=ROOT, stdout=logf,
                                stderr=subprocess.STDOUT)
    try:
        ca = ssl.create_default_context(cafile=str(tmp_path / "certs" / "ca.pem"))
        deadline = time.monotonic() + 60
        while True:
            assert proc.poll() is None, log.read_text()
            try:
                r = httpx.get(f"https://127.0.0.1:{port}/api/v1/live", verify=ca, timeout=5)
                break
            except httpx.HTTPError:
                assert time.monotonic() < deadline, log.read_text()
                time.sleep(0.2)
        assert r.status_code == 200 and r.headers["strict-transport-security"].startswith("max-age=")
        with pytest.raises(httpx.HTTPError):
            httpx.get(f"http://127.0.0.1:{port}/api/v1/live", timeout=5)  # plain HTTP is not served
        r = httpx.get(f"https://127.0.0.1:{port}/api/v1/health", verify=ca, timeout=5,
                      headers={"Authorization": f"Bearer {TOKEN}"})
        assert r.status_code == 200
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        router.close()
    assert "gateway on https://127.0.0.1" in log.read_text()

"""Browser attacks on the loopback no-token gateway, in headless Chromium against the real server: a page on
another origin tries a cross-site abort (fetch and form post), a page on a DNS-rebound name (Chromium's host
resolver maps it to 127.0.0.1) tries to read and abort. Both are refused and nothing reaches the vehicle;
the gateway's own page, same-origin, still aborts."""

from __future__ import annotations

import http.server
import threading
import time
from collections.abc import Iterator

import pytest

from tests.gateway.fakes import Harness
from tests.gateway.test_browser import ARGS, CHROMIUM
from tests.helpers import free_port

pytestmark = [pytest.mark.integration, pytest.mark.browser,
              pytest.mark.skipif(not __import__("os").path.exists(CHROMIUM),
                                 reason=f"{CHROMIUM} is absent: apt-get install chromium to run the browser test")]

EVIL_PAGE = """<!doctype html><html><body>
<form id="f" method="POST" action="{gw}/api/v1/abort" enctype="text/plain">
<input name='{{"reason":"form","x":"' value='"}}'></form>
<script>
window.results = {{}};
(async () => {{
  try {{
    await fetch("{gw}/api/v1/abort", {{method: "POST", mode: "no-cors", headers: {{"Content-Type": "text/plain"}},
                                       body: JSON.stringify({{reason: "no-cors fetch"}})}});
    window.results.nocors = "sent";
  }} catch (e) {{ window.results.nocors = "error"; }}
  try {{
    const r = await fetch("{gw}/api/v1/abort", {{method: "POST", headers: {{"Content-Type": "application/json"}},
                                               body: JSON.stringify({{reason: "cors fetch"}})}});
    window.results.cors = r.status;
  }} catch (e) {{ window.results.cors = "blocked"; }}
  try {{
    const r = await fetch("{gw}/api/v1/health");
    window.results.read = r.status;
  }} catch (e) {{ window.results.read = "blocked"; }}
  window.results.done = true;
}})();
</script></body></html>"""

REBOUND_SCRIPT = """async () => {
  const out = {};
  const h = await fetch("/api/v1/health");
  out.read = h.status;
  const a = await fetch("/api/v1/abort", {method: "POST", headers: {"Content-Type": "application/json"},
                                         body: JSON.stringify({reason: "rebinding"})});
  out.abort = a.status;
  out.detail = (await a.json()).detail;
  return out;
}"""


@pytest.fixture(scope="module")
def open_gw(tmp_path_factory) -> Iterator[Harness]:
    h = Harness(tmp_path_factory.mktemp("attacks"), gateway_settings={"abort_ack_timeout_s": 0.2}).start()
    try:
        yield h
    finally:
        h.stop()


@pytest.fixture(scope="module")
def evil_site(open_gw) -> Iterator[str]:
    page = EVIL_PAGE.format(gw=open_gw.base_url).encode()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server's naming
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.end_headers()
            self.wfile.write(page)

        def log_message(self, *args) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", free_port()), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()


def _browser(pw, *extra: str):
    return pw.chromium.launch(executable_path=CHROMIUM, args=[*ARGS, *extra], headless=True)


def test_cross_site_page_cannot_abort(open_gw, evil_site, caplog) -> None:
    caplog.set_level("WARNING", logger="aermani.gateway.guard")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    before = len(open_gw.fake.aborts)
    with sync_api.sync_playwright() as pw:
        browser = _browser(pw)
        try:
            page = browser.new_page()
            page.goto(evil_site)
            page.wait_for_function("window.results && window.results.done", timeout=30_000)
            results = page.evaluate("window.results")
            # The no-cors POST left the browser (the guard refused it; Chromium's opaque-response blocking may
            # turn the refusal into a fetch error); the JSON one died in the CORS preflight; the read was
            # refused or unreadable.
            assert results["nocors"] in ("sent", "error") and results["cors"] == "blocked", results
            assert results["read"] == "blocked", results
            with page.expect_navigation():
                page.evaluate("document.getElementById('f').submit()")
            assert '"status": 403' in page.content() or '"status":403' in page.content()
        finally:
            browser.close()
    time.sleep(0.5)
    assert len(open_gw.fake.aborts) == before, [a.reason for a in open_gw.fake.aborts]
    # Both cross-site POSTs reached the gateway and were refused there (not merely dropped by the browser).
    refused = [r.getMessage() for r in caplog.records if r.name == "aermani.gateway.guard"]
    assert sum("POST /api/v1/abort" in m and "cross-origin" in m for m in refused) >= 2, refused


def test_dns_rebinding_page_cannot_read_or_abort(open_gw) -> None:
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    before = len(open_gw.fake.aborts)
    port = open_gw.http_port
    with sync_api.sync_playwright() as pw:
        # The attacker's name resolves to the gateway's loopback address, as after a DNS rebinding.
        browser = _browser(pw, "--host-resolver-rules=MAP rebind.attacker.test 127.0.0.1")
        try:
            page = browser.new_page()
            resp = page.goto(f"http://rebind.attacker.test:{port}/")
            assert resp is not None and resp.status == 403
            out = page.evaluate(REBOUND_SCRIPT)
            assert out["read"] == 403 and out["abort"] == 403 and "DNS rebinding" in out["detail"], out
        finally:
            browser.close()
    time.sleep(0.5)
    assert len(open_gw.fake.aborts) == before


def test_the_gateway_page_itself_still_aborts_without_a_token(open_gw) -> None:
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    expect = sync_api.expect
    with sync_api.sync_playwright() as pw:
        browser = _browser(pw)
        try:
            page = browser.new_page()
            page.goto(open_gw.base_url + "/")
            expect(page.locator("#vehicle option")).to_have_count(1, timeout=30_000)
            page.click("#abort")
            expect(page.locator("#message")).to_contain_text("abort sent to am1", timeout=30_000)
        finally:
            browser.close()
    assert open_gw.fake.aborts and open_gw.fake.aborts[-1].reason == "abort button"

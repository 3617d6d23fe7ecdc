"""The ground-station page in headless Chromium: submit a command, see steps and camera frames, abort."""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from tests.gateway.conftest import TOKEN
from tests.gateway.fakes import Harness

CHROMIUM = "/usr/bin/chromium"
pytestmark = [pytest.mark.integration, pytest.mark.browser,
              pytest.mark.skipif(not os.path.exists(CHROMIUM),
                                 reason=f"{CHROMIUM} is absent: apt-get install chromium to run the browser test")]
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]


@contextlib.contextmanager
def opened_page(url: str, on_dialog: Callable[[Any], None] | None = None) -> Iterator[tuple[Any, list[str], Any]]:
    """The page at `url` in headless Chromium, as (page, errors, playwright's expect): `errors` collects page
    errors and Content-Security-Policy violations; the browser closes afterwards."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        try:
            page = browser.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            # The gateway's Content-Security-Policy must not block anything the page itself does.
            page.on("console", lambda m: errors.append(m.text) if "Content Security Policy" in m.text else None)
            if on_dialog is not None:
                page.on("dialog", on_dialog)
            page.goto(url)
            yield page, errors, sync_api.expect
        finally:
            browser.close()


@pytest.fixture(scope="module")
def page_url(tmp_path_factory) -> Iterator[tuple[str, Harness]]:
    h = Harness(tmp_path_factory.mktemp("browser"), gateway_settings={"token": TOKEN}, step_delay_s=0.3).start()
    try:
        yield h.base_url + "/", h
    finally:
        h.stop()


def test_page_runs_a_task_and_aborts(page_url) -> None:
    url, h = page_url
    with opened_page(url) as (page, errors, expect):
        # Fleet health needs the token too (it carries the vehicle's position): type it first.
        page.fill("#token", TOKEN)
        assert page.evaluate("sessionStorage.getItem('aermani.token')") == TOKEN
        expect(page.locator("#vehicle option")).to_have_count(1, timeout=30_000)

        # The camera updates: two different frame stamps over time.
        # Locator assertions, not wait_for_function: the page's Content-Security-Policy (no eval) stays on.
        expect(page.locator("#camera")).to_have_attribute("data-stamp", re.compile(r"\d+"), timeout=30_000)
        first = page.get_attribute("#camera", "data-stamp")
        expect(page.locator("#camera")).not_to_have_attribute("data-stamp", first, timeout=30_000)
        assert page.evaluate("document.getElementById('camera').naturalWidth") == 64

        page.fill("#command", "search the room until abort")
        page.click("#send")
        # At least two steps (the task keeps stepping every 0.3 s: an exact count races a loaded machine).
        expect(page.locator("#timeline li.step").nth(1)).to_be_visible(timeout=30_000)
        expect(page.locator("#timeline li.step").first).to_contain_text("a red cup on a table")
        expect(page.locator("#timeline li.step").first).to_contain_text("#1 takeoff")
        expect(page.locator("#task-state")).to_have_text("running")
        expect(page.locator("#current-skill")).not_to_have_text("–")
        expect(page.locator("#pose")).to_contain_text("OFFBOARD")

        page.click("#abort")
        expect(page.locator("#task-state")).to_have_text("aborted", timeout=30_000)
        expect(page.locator("#message")).to_contain_text(re.compile("acknowledged by am1|aborted: abort button"))
        assert h.fake.aborts and h.fake.aborts[-1].reason == "abort button"
        # ABORT ALL VEHICLES: one fleet-wide publication, acknowledged by the vehicle.
        page.click("#abort-all")
        expect(page.locator("#message")).to_contain_text("fleet abort sent (1 vehicles); acknowledged by am1",
                                                         timeout=10_000)
        assert h.fake.aborts[-1].reason == "abort-all button" and h.fake.aborts[-1].task_id is None
        assert errors == []


@pytest.fixture()
def approval_page(tmp_path) -> Iterator[tuple[str, Harness]]:
    h = Harness(tmp_path, gateway_settings={"token": TOKEN}, steps=5, step_delay_s=0.2).start()
    try:
        yield h.base_url + "/", h
    finally:
        h.stop()


def test_page_approves_and_rejects_a_waiting_skill(approval_page) -> None:
    """Operator approval through the real page: a grasp waits; Reject (with a reason) makes the policy ask
    again; Approve lets it run and the task completes."""
    url, h = approval_page
    with opened_page(url, on_dialog=lambda d: d.accept("that is the wrong cup")) as (page, errors, expect):
        page.fill("#token", TOKEN)  # every API route needs it, the vehicle list too
        expect(page.locator("#vehicle option")).to_have_count(1, timeout=30_000)
        page.fill("#command", "pick up the red cup with approval")
        page.click("#send")
        item = page.locator("#approval-list li.approval")
        expect(item).to_have_count(1, timeout=30_000)
        expect(item.first).to_contain_text("grasp")
        expect(item.first).to_contain_text("is the next step of the plan")
        first_id = item.first.get_attribute("data-id")
        item.first.locator("button.reject").click()
        expect(page.locator("#message")).to_contain_text("rejected", timeout=10_000)
        # The policy asks again: a new request appears; approve it.
        expect(page.locator(f"#approval-list li.approval:not([data-id='{first_id}'])")).to_have_count(
            1, timeout=30_000)
        page.locator("#approval-list li.approval button.approve").first.click()
        expect(page.locator("#task-state")).to_have_text("succeeded", timeout=30_000)
        expect(page.locator("#approvals")).to_be_hidden()
        assert [d.approved for d in h.fake.decisions] == [False, True]
        assert h.fake.decisions[0].reason == "that is the wrong cup"
        assert h.fake.decisions[0].operator == "web page"
        assert not errors, errors

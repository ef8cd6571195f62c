"""Headless Chromium (Debian's, driven by playwright) for the dashboard and API docs tests.

Skips where Chromium is missing (a developer's laptop without root); fails instead with CI=true.
``page`` runs offline, as an edge computer without internet does: a request to any host but
127.0.0.1 is refused and recorded, and the test fails if the page made one or raised a
JavaScript error.
"""
from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from tests.support.api_fixtures import in_ci

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]
LOCAL_HOSTS = {"127.0.0.1", "localhost"}


def chromium_path() -> Path | None:
    if CHROMIUM.exists():
        return CHROMIUM
    found = shutil.which("chromium")
    return Path(found) if found else None


@pytest.fixture(scope="module")
def browser():
    path = chromium_path()
    if path is None:
        message = "headless Chromium not installed (scripts/ensure-test-deps.sh installs it)"
        if in_ci():
            pytest.fail(message)
        pytest.skip(message)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(path), args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()


class OfflinePage:
    """What the offline page saw: requests it was refused (to other hosts) and JavaScript errors."""

    def __init__(self) -> None:
        self.outside_requests: list[str] = []
        self.errors: list[str] = []


def offline_context(browser, **context_options):
    """A browser context that reaches 127.0.0.1 only; returns (context, OfflinePage)."""
    seen = OfflinePage()
    context = browser.new_context(**context_options)

    def only_local(route) -> None:
        url = route.request.url
        if urlsplit(url).scheme in ("http", "https", "ws", "wss") and urlsplit(url).hostname not in LOCAL_HOSTS:
            seen.outside_requests.append(url)
            route.abort("internetdisconnected")
        else:
            route.continue_()

    context.route("**/*", only_local)
    return context, seen


@pytest.fixture
def page(browser) -> Iterator:
    context, seen = offline_context(browser)
    page = context.new_page()
    page.on("pageerror", lambda error: seen.errors.append(str(error)))
    page.seen = seen  # type: ignore[attr-defined]
    yield page
    context.close()
    assert not seen.errors, f"JavaScript errors on the page: {seen.errors}"
    assert not seen.outside_requests, f"the page reached beyond 127.0.0.1: {seen.outside_requests}"

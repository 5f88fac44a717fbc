"""The browser tests' Chromium: one headless browser per module, Debian's (never a downloaded
one). Browser tests are few smoke tests of real flows; the logic behind them is tested in-process,
and ``polling.wait`` waits for the app's state, which changes on other threads."""

from __future__ import annotations

import shutil

import pytest

from app.screenshots import ARGS, CHROMIUM


@pytest.fixture(scope="module")
def browser():
    if shutil.which(CHROMIUM) is None:
        pytest.fail(
            f"{CHROMIUM} is missing: `make test` installs Debian's chromium (apt-get install chromium)"
        )
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=ARGS)
        yield browser
        browser.close()

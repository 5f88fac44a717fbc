"""The walkthrough's clock in the page: a key's effect timed from its input event to the text that
shows it, on a plain page (the walkthrough itself is a benchmark, not a test)."""

from __future__ import annotations

import pytest

from app.walkthrough import PAGE_CLOCK, Shows, shows_text

pytestmark = pytest.mark.browser

PAGE = """
<body><div id="version">(version 1)</div><div id="label">Label #3: box</div><script>
window.addEventListener('keydown', (event) => {
  if (event.key !== 'n') return;
  setTimeout(() => { document.getElementById('version').textContent = '(version 2)'; }, 60);
  setTimeout(() => { document.getElementById('label').textContent = 'Label #4: cone'; }, 150);
});
</script></body>
"""


def _timed_in_page(browser, shows) -> tuple[float, float]:
    """Press N on a fresh ``PAGE``, wait for ``shows`` (polled) and return its times in the page."""
    page = browser.new_page()
    try:
        page.set_content(PAGE)
        page.add_script_tag(content=PAGE_CLOCK)  # (the walkthrough's page: an init script)
        shown = shows(page)
        shown.watch()
        page.keyboard.press("n")
        shown()
        return shown.in_page()
    finally:
        page.close()


def test_the_page_times_a_key_until_the_text_that_shows_its_effect(browser):
    # Known before the key: the edit's new version, which shows 60 ms after it.
    seen, painted = _timed_in_page(browser, lambda page: shows_text(page, "(version 2)"))
    assert 60.0 <= seen < 150.0 and painted > seen
    # Known only after it: a label number other than those shown before (Label #3, in the page
    # already when the watch starts, does not count).
    seen, painted = _timed_in_page(
        browser, lambda page: Shows(page, "Label #4:", r"Label #(\d+):", exclude=[3])
    )
    assert 150.0 <= seen and painted > seen


def test_a_pattern_the_page_shows_before_the_key_or_never_is_an_error_not_a_time(browser):
    from playwright.sync_api import Error

    # "Label #3:" is in the page before the key: any later change would have resolved the watch.
    with pytest.raises(Error, match="before the key"):
        _timed_in_page(browser, lambda page: shows_text(page, "Label #3:"))
    # A polled text the pattern does not match: the page's wait ends, with an error.
    page = browser.new_page()
    try:
        page.set_content(PAGE)
        page.add_script_tag(content=PAGE_CLOCK)
        shown = Shows(page, "(version 2)", r"\(version 7\)")
        shown.watch()
        page.keyboard.press("n")
        shown()
        with pytest.raises(Error, match="never matched"):
            shown.in_page(timeout_ms=300.0)
    finally:
        page.close()

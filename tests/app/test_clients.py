"""``ClientView``'s own logic that needs no browser: a coalesced block's redraws."""

from __future__ import annotations

import contextlib
import threading
import types

import pytest

from app.clients import ClientView


def _bare_view() -> ClientView:
    """A ClientView with what ``coalesced``, ``redraw``'s guard and ``refresh`` touch, and no
    browser: ``redraw`` itself is replaced by a counter (the real one would draw)."""
    view = object.__new__(ClientView)
    view.closed = False
    view.client = types.SimpleNamespace(atomic=contextlib.nullcontext)
    view.panels = []
    view.follow_object = lambda: None
    view._draw_highlights = lambda: None
    for name in ("_coalesce_lock", "_refresh_lock", "_batch_lock"):
        setattr(view, name, threading.Lock())
    view._wanted, view._num_refreshes, view._open_batches = {}, 0, 0
    view.sent_at = 0.0
    view.redraws = 0

    def redraw() -> None:
        view.redraws += 1

    view.redraw = redraw
    return view


def test_a_coalesced_block_redraws_and_refreshes_once_at_its_end():
    view = _bare_view()
    with view.coalesced():
        for _ in range(3):
            ClientView.redraw(view)  # deferred: it returns before reading any state
            view.refresh()
        with view.coalesced():  # nested: the outer block's end does it
            view.refresh()
        assert view.redraws == 0 and view._num_refreshes == 0 and view.sending
    assert view.redraws == 1 and view._num_refreshes == 1 and not view.sending
    # Nothing asked for: nothing done.
    with view.coalesced():
        pass
    assert view.redraws == 1 and view._num_refreshes == 1
    # Outside a block, each call is done at once.
    view.refresh()
    assert view._num_refreshes == 2


def test_a_coalesced_redraw_that_refreshed_is_not_followed_by_another_refresh():
    view = _bare_view()

    def redraw_that_refreshes() -> None:
        view.redraws += 1
        view.refresh()

    view.redraw = redraw_that_refreshes
    with view.coalesced():
        ClientView.redraw(view)
        view.refresh()
    assert view.redraws == 1 and view._num_refreshes == 1


def test_only_the_blocks_own_thread_waits_for_its_end():
    view = _bare_view()
    with view.coalesced():
        other = threading.Thread(target=view.refresh)
        other.start()
        other.join(5)
        assert view._num_refreshes == 1  # another browser event's refresh is not held back
    assert view._num_refreshes == 1  # and the block asked for none


def test_a_failing_block_still_brings_the_browser_up_to_date():
    view = _bare_view()
    with pytest.raises(RuntimeError), view.coalesced():
        view.refresh()
        raise RuntimeError("an edit failed")
    assert view._num_refreshes == 1 and view._wanted == {}


def test_two_blocks_at_once_each_bring_the_browser_up_to_date():
    # viser runs each key on its own pool thread: a second key's block starting while the first's
    # runs must not take away what the first asked for.
    view = _bare_view()
    first_asked, second_done = threading.Event(), threading.Event()

    def first() -> None:
        with view.coalesced():
            ClientView.redraw(view)  # (a frame change)
            first_asked.set()
            second_done.wait(5)

    def second() -> None:
        first_asked.wait(5)
        with view.coalesced():
            view.refresh()  # (a camera key)
        second_done.set()

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(5)
    assert view.redraws == 1 and view._num_refreshes == 1 and view._wanted == {}

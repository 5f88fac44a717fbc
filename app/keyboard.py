"""Keys pressed on a closed drop-down are hotkeys, not a search.

viser's drop-downs are searchable Mantine selects, and the hotkeys (Mantine's ``useHotkeys``)
ignore keys whose target is an input. A drop-down keeps the focus after an option is picked, so
without this the next ``B`` or ``3`` would be typed into its search box (filtering it to nothing)
instead of giving a verdict or choosing a class. While a drop-down is open its keys still search
its options; once it is closed, a letter, digit or one of the hotkeys' named keys gives the focus
back to the page and reaches the hotkeys, as if the drop-down had never been used.

viser 1.1.1 has no public call to run a script in one browser; its ``RunJavascriptMessage`` (the
message it loads Plotly with) does, sent on the browser's own connection.
"""

from __future__ import annotations

import viser
from viser import _messages

ROUTE_KEYS_JS = r"""
(() => {
  if (window.__factorydetRouteKeys) return;
  window.__factorydetRouteKeys = true;
  const named = new Set(["Delete", "Enter", "Escape", "PageUp", "PageDown"]);
  // Mantine marks an open drop-down's input aria-expanded (and its root data-expanded).
  const isClosedDropdown = (el) =>
    el instanceof HTMLInputElement &&
    el.getAttribute("aria-haspopup") === "listbox" &&
    el.getAttribute("aria-expanded") !== "true" &&
    el.closest("[data-expanded]") === null;
  // By the physical key as well: on macOS, Option+I types a symbol, not "i".
  const isHotkey = (event) =>
    /^[a-z0-9]$/i.test(event.key) || /^(Key[A-Z]|Digit[0-9])$/.test(event.code) || named.has(event.key);
  window.addEventListener(
    "keydown",
    (event) => {
      const input = event.target;
      if (!isClosedDropdown(input) || event.ctrlKey || event.metaKey || event.isComposing) return;
      if (!isHotkey(event)) return;
      event.preventDefault();
      event.stopImmediatePropagation();
      input.blur();
      document.body.dispatchEvent(
        new KeyboardEvent("keydown", {
          key: event.key,
          code: event.code,
          shiftKey: event.shiftKey,
          altKey: event.altKey,
          bubbles: true,
          cancelable: true,
        })
      );
    },
    true
  );
})();
"""
"""Installed once per page: a capture-phase listener that sees every key before the input does."""


def route_dropdown_keys_to_hotkeys(client: viser.ClientHandle) -> None:
    """Make keys pressed on a closed drop-down of this browser reach the hotkeys (module docstring)."""
    client._websock_connection.queue_message(_messages.RunJavascriptMessage(source=ROUTE_KEYS_JS))

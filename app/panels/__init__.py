"""One module per GUI panel; each builds its widgets and wires them to the state."""

from ..naming import short_name

__all__ = ["from_user", "short_name"]


def from_user(event) -> bool:
    """True for a change a browser made; False for the echo of the app setting a widget's value
    (viser calls ``on_update`` synchronously for both), which must not write back into the state."""
    return event.client is not None

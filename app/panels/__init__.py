"""One module per GUI panel; each builds its widgets and wires them to the state."""


def short_name(name: str, parts: int = 2) -> str:
    """A model's name as a panel shows it: a checkpoint path shortened to its last ``parts`` parts
    (``…/models/default.pt``), so that a long path does not overflow the sidebar."""
    pieces = name.replace("\\", "/").split("/")
    return name if len(pieces) <= parts else "…/" + "/".join(pieces[-parts:])


def from_user(event) -> bool:
    """True for a change a browser made; False for the echo of the app setting a widget's value
    (viser calls ``on_update`` synchronously for both), which must not write back into the state."""
    return event.client is not None

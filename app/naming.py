"""How the app names things in its panels (no GUI of its own: the trainer and the panels share it)."""


def short_name(name: str, parts: int = 2) -> str:
    """A model's name as a panel shows it: a checkpoint path shortened to its last ``parts`` parts
    (``…/models/default.pt``), so that a long path does not overflow the sidebar."""
    pieces = name.replace("\\", "/").split("/")
    return name if len(pieces) <= parts else "…/" + "/".join(pieces[-parts:])

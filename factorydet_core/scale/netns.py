"""Run a command in a network namespace of its own with only the loopback interface up, so that
a Ray it starts listens on 127.0.0.1 alone (Ray otherwise binds its ports on every interface of
the machine). The tests and benchmarks that start Ray run through it:

    python -m factorydet_core.scale.netns -- python -m pytest -m ray

It needs ``unshare`` (util-linux) and root, or unprivileged user namespaces (``--map-root-user``).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import socket
import struct
import sys

_SIOCGIFFLAGS = 0x8913
_SIOCSIFFLAGS = 0x8914
_IFF_UP = 0x1
_INSIDE = "--inside"


def loopback_only() -> bool:
    """Whether this process's network namespace has no interface but ``lo``."""
    # socket.if_nameindex asks the kernel about this namespace; /sys/class/net shows the
    # namespace sysfs was mounted in.
    try:
        return [name for _, name in socket.if_nameindex()] == ["lo"]
    except OSError:
        return False


def bring_loopback_up() -> None:
    """Set ``lo`` up (a new namespace starts with it down) without iproute2."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        request = struct.pack("16sH", b"lo", 0)
        flags = struct.unpack("16sH", fcntl.ioctl(sock, _SIOCGIFFLAGS, request)[:18])[1]
        fcntl.ioctl(sock, _SIOCSIFFLAGS, struct.pack("16sH", b"lo", flags | _IFF_UP))


def main(argv: list[str]) -> int:
    inside = bool(argv) and argv[0] == _INSIDE
    args = argv[1:] if inside else argv
    if args and args[0] == "--":
        args = args[1:]
    if not args:
        print("usage: python -m factorydet_core.scale.netns -- COMMAND [ARG ...]", file=sys.stderr)
        return 2
    if inside:
        bring_loopback_up()
        os.execvp(args[0], args)
    unshare = shutil.which("unshare")
    if unshare is None:
        print("unshare (util-linux) is missing: install util-linux", file=sys.stderr)
        return 2
    user_namespace = [] if os.geteuid() == 0 else ["--map-root-user"]
    os.execv(
        unshare,
        [unshare, "--net", *user_namespace, sys.executable, "-m", __spec__.name, _INSIDE, "--", *args],
    )
    return 0  # not reached


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""Run inside the shipped sowgate.service sandbox (only ExecStart replaced): what it may touch.

Each attempt's outcome, "ok" or the errno's name, goes to stdout (the journal) as one JSON line:
the sandbox makes /out read-only too.
"""

from __future__ import annotations

import errno
import json
import os
import socket


def attempt(action) -> str:  # type: ignore[no-untyped-def]
    try:
        action()
    except OSError as exc:
        return errno.errorcode.get(exc.errno or 0, str(exc))
    return "ok"


def open_dev(path: str) -> None:
    os.close(os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK))


def write_in(folder: str) -> None:
    path = os.path.join(folder, "probe-was-here")
    with open(path, "w") as f:
        f.write("x")
    os.unlink(path)


state = os.environ.get("STATE_DIRECTORY", "/var/lib/sowgate")
results = {
    "open /dev/ttyS2 (configured)": attempt(lambda: open_dev("/dev/ttyS2")),
    "open /dev/ttyS0 (console, not configured)": attempt(lambda: open_dev("/dev/ttyS0")),
    "open /dev/net/tun (mode 0666)": attempt(lambda: open_dev("/dev/net/tun")),
    "open /dev/fuse (mode 0666)": attempt(lambda: open_dev("/dev/fuse")),
    "open /dev/vda (disk)": attempt(lambda: open_dev("/dev/vda")),
    "write /var/lib/sowgate": attempt(lambda: write_in(state)),
    "write /etc/sowgate": attempt(lambda: write_in("/etc/sowgate")),
    "write /opt/sowgate": attempt(lambda: write_in("/opt/sowgate")),
    "write /usr/bin": attempt(lambda: write_in("/usr/bin")),
    "socket AF_PACKET": attempt(lambda: socket.socket(socket.AF_PACKET, socket.SOCK_RAW).close()),
}
print("probe " + json.dumps(results), flush=True)

"""Who the dashboard answers: the names it may be reached under, the pages that may command it,
and how fast a password may be guessed.

The trust model (README, "Dashboard"):

- **Host.** Every request, the WebSocket included, must name an allowed host
  (``[dashboard] allowed_hosts``; by default the listen address, localhost, 127.0.0.1, ::1, and
  when listening beyond loopback this machine's host name and NAME.local). Anything else gets a
  400 naming the key. This is what stops DNS rebinding: a page at ``evil.example`` that points
  its own name at the cab box makes the browser send ``Host: evil.example``, and same-origin
  alone cannot tell that from the real page. When listening beyond loopback an IP address is
  always accepted: a browser sends one only when the user typed it, so it is never a rebound
  name.
- **Origin.** A POST or a WebSocket upgrade that carries ``Origin`` must come from the page
  itself (same scheme-less ``host:port`` as ``Host``, and an allowed host): 403 otherwise, and
  for ``Origin: null`` (a sandboxed frame or a file). A browser always sends ``Origin`` on a
  POST and on a WebSocket, so a request without one is not from a browser (curl, a farm
  script): it is taken, still subject to the host list and the password, as a script on the
  network could send anything a page can.
- **Password.** Wrong passwords are slowed per client address (0.25 s after the first, doubling
  to 10 s), and while an address waits its further attempts get 429 without being checked, so
  parallel connections guess no faster. All addresses together may fail about once every 2 s
  once a burst of 20 is spent (a network full of addresses guesses no faster either); the
  price is that during such an attack the farmer may also see 429 for a few seconds. Every
  failure is logged with the client (at most 10 lines a minute; the rest are counted in the
  next line). A request without credentials is not a failure: it is how a browser asks.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import ipaddress
import logging
import math
import secrets
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable, Iterable, Mapping, MutableMapping
from typing import Any
from urllib.parse import urlsplit

from starlette.responses import Response

log = logging.getLogger(__name__)

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


def header_map(scope: Scope) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}


def hostname_of(host: str) -> str | None:
    """The name in a ``Host`` header (``name:port``, ``[v6]:port``), lower case; None when the
    header is not one."""
    try:
        parts = urlsplit("//" + host.strip())
        name = parts.hostname
        _ = parts.port  # raises on a port that is not a number
    except ValueError:
        return None
    if not name or parts.path or parts.query or parts.username is not None:
        return None
    return name


def is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


class TrustedHosts:
    """The host names the dashboard answers to (see the module's docstring)."""

    def __init__(self, names: Iterable[str], *, any_ip: bool) -> None:
        self.names = frozenset(n.lower() for n in names)
        self.any_ip = any_ip
        self.refused = 0  # requests RequestGuard turned away (a foreign host or origin)

    def allows(self, name: str | None) -> bool:
        if name is None:
            return False
        if name in self.names or (self.any_ip and is_ip(name)):
            return True
        return any(p.startswith("*.") and name.endswith(p[1:]) for p in self.names)

    def described(self) -> str:
        shown = ", ".join(sorted(self.names))
        return shown + (", or any IP address" if self.any_ip else "")


def foreign_origin(headers: Mapping[str, str], hosts: TrustedHosts) -> str | None:
    """Why the ``Origin`` of a request is not the page's own, or None when it is (or absent)."""
    origin = headers.get("origin")
    if origin is None:
        return None  # not a browser: see the module's docstring
    parts = urlsplit(origin.strip())
    if origin.strip() == "null" or parts.scheme not in ("http", "https"):
        return f"Origin {origin!r} is not a web page of this dashboard"
    if parts.netloc.lower() != headers.get("host", "").strip().lower():
        return f"Origin {origin!r} is another site than this page ({headers.get('host')!r})"
    if not hosts.allows(parts.hostname):
        return f"Origin {origin!r} is not an allowed host"
    return None


# GETs whose Origin is checked too: the fleet view's database queries (a page of another
# site cannot read their answers without CORS, but it must not make the database work either)
ORIGIN_CHECKED_PREFIXES = ("/api/history/",)


class RequestGuard:
    """ASGI middleware: the host list on every request, the Origin on POSTs, WebSockets and
    the fleet view's GETs."""

    def __init__(self, app: ASGIApp, hosts: TrustedHosts) -> None:
        self.app = app
        self.hosts = hosts
        self._log = LogLimiter()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = header_map(scope)
        host = headers.get("host", "")
        if not self.hosts.allows(hostname_of(host)):
            await self._refuse(
                scope, receive, send, 400,
                f"host {host!r} is not one this dashboard answers to ({self.hosts.described()})"
                "; add it to [dashboard] allowed_hosts if it is this machine's name",
            )
            return
        if kind == "websocket" or scope.get("method") == "POST" or \
                str(scope.get("path", "")).startswith(ORIGIN_CHECKED_PREFIXES):
            why = foreign_origin(headers, self.hosts)
            if why is not None:
                await self._refuse(scope, receive, send, 403, f"cross-origin request refused: "
                                                            f"{why}")
                return
        await self.app(scope, receive, send)

    async def _refuse(self, scope: Scope, receive: Receive, send: Send, status: int,
                      reason: str) -> None:
        self.hosts.refused += 1
        self._log.warning("dashboard: refused %s %s from %s: %s", scope.get("method", "WS"),
                          scope.get("path"), client_of(scope), reason)
        await Response(reason + "\n", status_code=status, media_type="text/plain")(
            scope, receive, send)


def client_of(scope: Scope) -> str:
    client = scope.get("client")
    return str(client[0]) if client else "unknown"


class LogLimiter:
    """At most ``per_minute`` warnings a minute; the next one says how many were left out."""

    def __init__(self, per_minute: int = 10, clock: Callable[[], float] = time.monotonic,
                 logger: logging.Logger = log) -> None:
        self.logger = logger
        self.per_minute = per_minute
        self.clock = clock
        self._window_start = -math.inf
        self._in_window = 0
        self.suppressed = 0

    def warning(self, fmt: str, *args: object) -> bool:
        now = self.clock()
        if now - self._window_start >= 60.0:
            self._window_start, self._in_window = now, 0
        if self._in_window >= self.per_minute:
            self.suppressed += 1
            return False
        self._in_window += 1
        if self.suppressed:
            fmt += " (%d similar lines left out)"
            args = (*args, self.suppressed)
            self.suppressed = 0
        self.logger.warning(fmt, *args)
        return True


class LoginThrottle:
    """Failed passwords: a growing wait per client address, and a cap over all of them."""

    FIRST_DELAY_S = 0.25
    MAX_DELAY_S = 10.0
    FORGET_AFTER_S = 900.0  # an address without a failure for 15 min starts again
    TRACKED = 4096  # addresses remembered (the oldest go first)
    GLOBAL_INTERVAL_S = 2.0  # all addresses together: one failure per 2 s ...
    GLOBAL_BURST = 20  # ... after a burst of 20

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        # address -> (failures, time of the last, earliest next attempt)
        self._clients: OrderedDict[str, tuple[int, float, float]] = OrderedDict()
        self._global_t = -math.inf  # GCRA: the theoretical arrival time of the next failure
        self.failures = 0

    def wait_s(self, client: str) -> float:
        """Seconds before ``client`` may have a password checked (0: now)."""
        now = self.clock()
        wait = self._global_t - self.GLOBAL_BURST * self.GLOBAL_INTERVAL_S - now
        entry = self._clients.get(client)
        if entry is not None:
            wait = max(wait, entry[2] - now)
        return max(0.0, wait)

    def failed(self, client: str) -> tuple[int, float]:
        """Count one wrong password: (failures of this client in a row, seconds it waits)."""
        now = self.clock()
        self.failures += 1
        count, last, _ = self._clients.pop(client, (0, now, now))
        if now - last > self.FORGET_AFTER_S:
            count = 0
        count += 1
        delay = min(self.FIRST_DELAY_S * 2 ** min(count - 1, 16), self.MAX_DELAY_S)
        self._clients[client] = (count, now, now + delay)
        while len(self._clients) > self.TRACKED:
            self._clients.popitem(last=False)
        self._global_t = max(self._global_t, now) + self.GLOBAL_INTERVAL_S
        return count, delay

    def succeeded(self, client: str) -> None:
        self._clients.pop(client, None)


class BasicAuth:
    """ASGI middleware: every HTTP request and WebSocket needs the password (HTTP basic, any
    user name), and wrong ones are slowed and logged (see the module's docstring)."""

    REALM = 'Basic realm="sowgate dashboard", charset="UTF-8"'

    def __init__(self, app: ASGIApp, password: str,
                 throttle: LoginThrottle | None = None) -> None:
        self.app = app
        self.password = password
        self.throttle = throttle or LoginThrottle()
        self._log = LogLimiter()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        given = header_map(scope).get("authorization")
        client = client_of(scope)
        if given is None:  # how a browser asks for the login box: no failure
            await self._deny(scope, receive, send, 401, "password needed")
            return
        wait = self.throttle.wait_s(client)
        if wait > 0:  # not even checked: parallel guesses go no faster than serial ones
            await self._deny(scope, receive, send, 429,
                             f"too many wrong passwords: try again in {math.ceil(wait)} s",
                             {"Retry-After": str(math.ceil(wait))})
            return
        if check_password(given, self.password):
            self.throttle.succeeded(client)
            await self.app(scope, receive, send)
            return
        count, delay = self.throttle.failed(client)
        self._log.warning("dashboard: wrong password from %s (%d in a row; it waits %.2f s)",
                          client, count, delay)
        await asyncio.sleep(delay)
        await self._deny(scope, receive, send, 401, "wrong password")

    async def _deny(self, scope: Scope, receive: Receive, send: Send, status: int, text: str,
                    headers: dict[str, str] | None = None) -> None:
        await Response(text + "\n", status_code=status, media_type="text/plain",
                       headers={"WWW-Authenticate": self.REALM, **(headers or {})})(
            scope, receive, send)


def check_password(header: str | None, password: str) -> bool:
    """Whether an ``Authorization`` header carries ``password`` (HTTP basic, any user)."""
    if not header or not header.startswith("Basic "):
        return False
    try:
        decoded = base64.b64decode(header[6:].strip(), validate=True).decode("utf-8")
    except (binascii.Error, UnicodeDecodeError):
        return False
    _, sep, given = decoded.partition(":")
    return bool(sep) and secrets.compare_digest(given.encode(), password.encode())

"""The dashboard's web side: one page, its vendored assets, a WebSocket of live updates, and
the commands the page sends (Starlette, served by uvicorn).

A page that connects gets ``Fleet.snapshot()`` (every machine, every seed kept), then the
changes ``Fleet.drain_updates()`` collects, pushed every ``PUSH_PERIOD_S``: 2 000 seeds a second
become 4 messages a second. A page that cannot keep up (a slow tablet on a weak Wi-Fi) is not
allowed to hold memory: its queue is dropped and it gets a fresh snapshot instead.

With ``[dashboard] password_file`` every request, the WebSocket included, needs HTTP basic
auth with that password (any user name): required when the page offers commands and listens
beyond localhost (``sowgate dashboard`` refuses to start otherwise).
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextlib
import logging
import math
import secrets
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping, MutableMapping
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import orjson
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from gateway.config import Settings
from gateway.config.farm import DASHBOARD_COMMANDS
from gateway.dashboard.model import Fleet, encode
from gateway.dashboard.subscriber import CommandRefused, DashboardSubscriber

log = logging.getLogger(__name__)

STATIC = Path(__file__).parent / "static"
PUSH_PERIOD_S = 0.25
CLIENT_QUEUE = 64  # messages a page may lag behind before it is resynchronised
# the commands the page can send, of those [commands] enabled allows
PAGE_COMMANDS = DASHBOARD_COMMANDS
REALM = 'Basic realm="sowgate dashboard", charset="UTF-8"'

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


def page_config(settings: Settings) -> dict[str, Any]:
    enabled = set(settings.commands.enabled)
    return {
        "commands": [c for c in PAGE_COMMANDS if c in enabled],
        "tile_url": settings.dashboard.tile_url,
        "units": {"speed": "km/h", "rate": "kg/ha", "duty": "%", "tilt": "°",
                  "area": "ha", "mass": "kg", "distance": "m"},
        "machine_id": settings.machine.id,
        # the rate form offers these, each with its rate range: a crop typed by hand came
        # back as "unknown crop" from the machine
        "crops": {name: [m.rate_min_kg_ha, m.rate_max_kg_ha]
                  for name, m in sorted(settings.control.crops.items())},
    }


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


class BasicAuth:
    """ASGI middleware: every HTTP request and WebSocket needs the password."""

    def __init__(self, app: ASGIApp, password: str) -> None:
        self.app = app
        self.password = password

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1")
                   for k, v in scope.get("headers", [])}
        if check_password(headers.get("authorization"), self.password):
            await self.app(scope, receive, send)
            return
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008})
            return
        response = Response("password needed", status_code=401,
                            headers={"WWW-Authenticate": REALM})
        await response(scope, receive, send)


def same_origin(headers: Mapping[str, str]) -> bool:
    """No ``Origin`` (not a browser), or one naming the host the request was sent to."""
    origin = headers.get("origin")
    if origin is None:
        return True
    host = headers.get("host", "")
    return urlsplit(origin).netloc == host


class Hub:
    """The open pages and what is pushed to them."""

    def __init__(self, fleet: Fleet) -> None:
        self.fleet = fleet
        self.clients: set[asyncio.Queue[str]] = set()
        self.wake = asyncio.Event()

    def changed(self) -> None:
        self.wake.set()

    async def run(self) -> None:
        while True:
            await self.wake.wait()
            self.wake.clear()
            self.push()
            await asyncio.sleep(PUSH_PERIOD_S)  # coalesce: at most 4 pushes a second

    def push(self) -> None:
        messages = [encode(m) for m in self.fleet.drain_updates()]
        if not messages:
            return
        for queue in self.clients:
            if queue.qsize() + len(messages) > CLIENT_QUEUE:
                self.resync(queue)
                continue
            for text in messages:
                queue.put_nowait(text)

    def join(self) -> tuple[asyncio.Queue[str], str]:
        """A new page's queue and its snapshot, in one step (no await): what is pending goes
        to the other pages first, so the snapshot and the updates after it neither miss nor
        repeat a seed."""
        self.push()
        snapshot = encode(self.fleet.snapshot())
        queue: asyncio.Queue[str] = asyncio.Queue()
        self.clients.add(queue)
        return queue, snapshot

    def resync(self, queue: asyncio.Queue[str]) -> None:
        while not queue.empty():
            queue.get_nowait()
        queue.put_nowait(encode(self.fleet.snapshot()))


def create_app(
    settings: Settings,
    *,
    fleet: Fleet | None = None,
    password: str | None = None,
    run_subscriber: bool = True,
) -> Starlette:
    own_id, own_target = settings.machine.id, settings.positioning.target_spacing_m
    fleet = fleet or Fleet(
        settings.mqtt.topic_prefix,
        max_seeds=settings.dashboard.max_seeds,
        # the config's target spacing is this machine's; others are rated against a median
        target_spacing=lambda mid: own_target if mid == own_id else None,
    )
    hub = Hub(fleet)
    subscriber = DashboardSubscriber(settings, fleet, on_change=hub.changed)
    config = page_config(settings)

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        tasks = [asyncio.create_task(hub.run(), name="dashboard-push")]
        if run_subscriber:
            tasks.append(asyncio.create_task(subscriber.run(), name="dashboard-mqtt"))
        try:
            yield
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def index(request: Request) -> Response:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    async def live(websocket: WebSocket) -> None:
        if not same_origin(websocket.headers):
            await websocket.close(code=1008)
            return
        await websocket.accept()
        queue, snapshot = hub.join()
        await websocket.send_text(encode({"type": "config", **config}))
        await websocket.send_text(snapshot)

        async def sender() -> None:
            while True:
                await websocket.send_text(await queue.get())

        task = asyncio.create_task(sender(), name="dashboard-ws-send")
        try:
            while True:  # the page sends nothing; this sees it go
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    break
        except WebSocketDisconnect:
            pass
        finally:
            hub.clients.discard(queue)
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    async def command(request: Request) -> Response:
        # a JSON content type forces a browser's CORS preflight (which is never answered), and
        # the origin must be this page's: another web site cannot move the machine through a
        # browser that has the password cached
        if not request.headers.get("content-type", "").startswith("application/json"):
            return JSONResponse({"ok": False, "error": "send application/json"}, 415)
        if not same_origin(request.headers):
            return JSONResponse({"ok": False, "error": "cross-origin request refused"}, 403)
        try:
            body = orjson.loads(await request.body())
        except (orjson.JSONDecodeError, RecursionError):
            return JSONResponse({"ok": False, "error": "request is not JSON"}, status_code=400)
        if not isinstance(body, dict):
            return JSONResponse({"ok": False, "error": "request must be an object"}, 400)
        name = body.get("command")
        machine_id = body.get("machine_id")
        payload = body.get("payload") or {}
        if not isinstance(name, str) or name not in config["commands"]:
            return JSONResponse(
                {"ok": False, "error": f"command {name!r} is not offered on this page"}, 403
            )
        if not isinstance(machine_id, str) or not isinstance(payload, dict):
            return JSONResponse({"ok": False, "error": "machine_id and payload needed"}, 400)
        if any(isinstance(v, float) and not math.isfinite(v) for v in payload.values()):
            return JSONResponse({"ok": False, "error": "numbers must be finite"}, 400)
        try:
            request_id = await subscriber.send_command(machine_id, name, payload)
        except CommandRefused as exc:
            return JSONResponse({"ok": False, "error": str(exc)}, status_code=409)
        except Exception as exc:  # the broker went away mid-publish
            return JSONResponse({"ok": False, "error": f"not sent: {exc}"}, status_code=503)
        return JSONResponse({"ok": True, "request_id": request_id})

    async def health(request: Request) -> Response:
        return JSONResponse({
            "broker_connected": fleet.broker_connected,
            "machines": {mid: v.seed_count for mid, v in fleet.machines.items()},
        })

    app = Starlette(
        routes=[
            Route("/", index),
            Route("/api/command", command, methods=["POST"]),
            Route("/api/health", health),
            WebSocketRoute("/ws", live),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ],
        lifespan=lifespan,
    )
    app.state.fleet = fleet
    app.state.hub = hub
    app.state.subscriber = subscriber
    if password is not None:
        app.add_middleware(BasicAuth, password=password)
    return app


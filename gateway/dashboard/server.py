"""The dashboard's web side: one page, its vendored assets, a WebSocket of live updates, and
the commands the page sends (Starlette, served by uvicorn).

A page that connects gets ``Fleet.snapshot()`` (every machine, every seed kept), then the
changes ``Fleet.drain_updates()`` collects, pushed every ``PUSH_PERIOD_S``: 2 000 seeds a second
become 4 messages a second. A page that cannot keep up (a slow tablet on a weak Wi-Fi) is not
allowed to hold memory: its queue is dropped and it gets a fresh snapshot instead.

With ``[dashboard] password_file`` every request, the WebSocket included, needs HTTP basic
auth with that password (any user name): required when the page offers commands and listens
beyond localhost (``sowgate dashboard`` refuses to start otherwise). Every request must name an
allowed host, and POSTs and WebSockets come from the page itself (``guard``: the trust model).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import orjson
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from gateway.config import Settings
from gateway.config.farm import DASHBOARD_COMMANDS
from gateway.dashboard.guard import BasicAuth, RequestGuard, TrustedHosts, check_password
from gateway.dashboard.model import Fleet, encode
from gateway.dashboard.subscriber import CommandRefused, DashboardSubscriber

log = logging.getLogger(__name__)

__all__ = ["Hub", "check_password", "create_app", "page_config"]

STATIC = Path(__file__).parent / "static"
PUSH_PERIOD_S = 0.25
CLIENT_QUEUE = 64  # messages a page may lag behind before it is resynchronised
# the commands the page can send, of those [commands] enabled allows
PAGE_COMMANDS = DASHBOARD_COMMANDS


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


class Hub:
    """The open pages and what is pushed to them."""

    def __init__(self, fleet: Fleet) -> None:
        self.fleet = fleet
        self.clients: set[asyncio.Queue[str]] = set()
        self.refused = 0  # pages turned away by [dashboard] max_clients
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
    database_url: str | None = None,
) -> Starlette:
    own_id, own_target = settings.machine.id, settings.positioning.target_spacing_m
    fleet = fleet or Fleet(
        settings.mqtt.topic_prefix,
        max_seeds=settings.dashboard.max_seeds,
        max_machines=settings.dashboard.max_machines,
        # the config's target spacing is this machine's; others are rated against a median
        target_spacing=lambda mid: own_target if mid == own_id else None,
    )
    hub = Hub(fleet)
    d = settings.dashboard
    trusted = TrustedHosts(d.trusted_hosts(), any_ip=not d.local_only)
    subscriber = DashboardSubscriber(settings, fleet, on_change=hub.changed)
    config = page_config(settings)
    # the fleet view (gateway/dashboard/history.py): the farm server's PostgreSQL, if any
    url = database_url or settings.farm_server.database_url
    history = None
    if url:
        from gateway.dashboard.history import History

        history = History(url, {} if own_target is None else {own_id: own_target})
    config["history"] = history is not None

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
        # the host and the Origin were checked by RequestGuard before this runs
        if len(hub.clients) >= settings.dashboard.max_clients:
            hub.refused += 1
            log.warning("dashboard: page from %s refused: %d pages open ([dashboard] "
                        "max_clients)", websocket.client and websocket.client.host,
                        len(hub.clients))
            await websocket.close(code=1013, reason="too many pages open")
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
        # RequestGuard took only this page's origin under an allowed host: another web site
        # cannot move the machine through a browser that has the password cached
        if not request.headers.get("content-type", "").startswith("application/json"):
            return JSONResponse({"ok": False, "error": "send application/json"}, 415)
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
            # topics of machine ids beyond [dashboard] max_machines, dropped
            "machines_refused": fleet.machines_refused,
            "pages": len(hub.clients),
            "pages_refused": hub.refused,
            "requests_refused": trusted.refused,
        })

    async def history_request(request: Request) -> Response:
        """The fleet view's GETs (``/api/history/<what>``): a bad parameter is a 400 naming it,
        a database that cannot answer a 503; the queries run in a worker thread."""
        from gateway.dashboard.history import (
            BadRequest,
            check_params,
            parse_day,
            parse_machines,
        )

        if history is None:
            return JSONResponse({"error": "no farm database: set [farm_server] database_url "
                                 "or start sowgate dashboard with --database URL"}, 404)
        what = request.path_params["what"]
        items = request.query_params.multi_items()
        params = dict(items)
        try:
            if len(params) != len(items):
                raise BadRequest("each parameter once")
            if what == "days":
                check_params(params, set())
                result: Any = {"days": await asyncio.to_thread(history.days)}
            elif what == "field":
                check_params(params, {"day", "machine", "preview"})
                window, machines = parse_day(params), parse_machines(params)
                preview = params.get("preview", "0")
                if preview not in ("0", "1"):
                    raise BadRequest(f"preview: 0 or 1 (got {preview[:20]!r})")
                result = await asyncio.to_thread(history.field, window, machines,
                                                 preview == "1")
            elif what == "quality":
                check_params(params, {"day", "machine"})
                window, machines = parse_day(params), parse_machines(params, required=True)
                assert machines is not None
                result = await asyncio.to_thread(history.quality, window, machines[0])
            elif what == "alarms":
                check_params(params, {"day", "machine"})
                window, machines = parse_day(params), parse_machines(params)
                result = await asyncio.to_thread(history.alarms, window, machines)
            else:
                return JSONResponse({"error": f"no such history request: {what[:40]!r} (days, "
                                     "field, quality, alarms)"}, 404)
        except BadRequest as exc:
            return JSONResponse({"error": str(exc)}, 400)
        except Exception as exc:  # psycopg's: the database is away or refuses
            log.warning("dashboard: farm database request %s failed: %s", what, exc)
            return JSONResponse({"error": f"farm database: {str(exc).strip()[:300]}"}, 503)
        return Response(orjson.dumps(result), media_type="application/json",
                        headers={"Cache-Control": "no-store"})

    app = Starlette(
        routes=[
            Route("/", index),
            Route("/api/history/{what}", history_request),
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
    # outermost: a stranger's request is refused before it can even try a password
    app.add_middleware(RequestGuard, hosts=trusted)
    return app


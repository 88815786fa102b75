"""The live web view's server (aiohttp): the page, its static files and a WebSocket of updates.

Routes (all GET; nothing else is answered: the view is read-only, no command reaches a box from here):

- ``/``: the page (``static/index.html``); ``/static/…``: its script and style sheet, from the package
  (nothing is fetched from the internet);
- ``/ws``: a WebSocket; the server sends JSON text messages: first a ``snapshot`` (every box's rings, state
  and events), then an ``update`` every `PUBLISH_PERIOD_S` (the rows published since, decimated, the state,
  new events) with a ``seq`` one higher each time; what the browser sends is ignored;
- ``/api/snapshot``: the same snapshot as JSON (for scripts and tests).

A browser that does not keep up (more than `MAX_QUEUED` updates waiting) has its queue replaced by a fresh
snapshot: the server's memory per browser stays bounded. The updates are made once (one JSON text for every
browser).

Why aiohttp: one maintained library for asyncio with both the WebSocket server and a WebSocket client (the
tests drive Chromium's DevTools protocol and measure the updates with it), no framework around it.
"""
from __future__ import annotations

import asyncio
import json
import sys
import time
from importlib import resources
from typing import Callable

from aiohttp import WSMsgType, web

from .fleet import Fleet

#: how often the browsers get an update (s): 4 Hz
PUBLISH_PERIOD_S = 0.25
#: updates waiting for one browser before it is sent a fresh snapshot instead
MAX_QUEUED = 16

STATIC = resources.files("ground.web") / "static"
_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml"}
#: the page may only load what this server serves (no inline scripts, nothing from elsewhere)
_CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
        "connect-src 'self'; frame-ancestors 'none'")


def _dumps(obj) -> str:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


def _static(name: str) -> web.Response:
    path = STATIC / name
    suffix = "." + name.rsplit(".", 1)[-1]
    if "/" in name or name.startswith(".") or suffix not in _TYPES or not path.is_file():
        raise web.HTTPNotFound()
    return web.Response(body=path.read_bytes(), content_type=_TYPES[suffix], charset="utf-8",
                        headers={"Content-Security-Policy": _CSP, "Cache-Control": "no-cache",
                                 "X-Content-Type-Options": "nosniff"})


class WebView:
    """The server's state: the fleet, the browsers connected, the publishing task."""

    def __init__(self, fleet: Fleet, *, clock: Callable[[], float] = time.time,
                 publish_period_s: float = PUBLISH_PERIOD_S) -> None:
        self.fleet = fleet
        self.clock = clock
        self.publish_period_s = publish_period_s
        self.clients: dict[web.WebSocketResponse, asyncio.Queue] = {}
        self.updates_sent = 0
        self.publish_failures = 0
        self._task: asyncio.Task | None = None

    def app(self) -> web.Application:
        app = web.Application()
        app.router.add_get("/", self.index)
        app.router.add_get("/static/{name}", self.static)
        app.router.add_get("/ws", self.websocket)
        app.router.add_get("/api/snapshot", self.api_snapshot)
        app.on_startup.append(self._start)
        app.on_shutdown.append(self._stop)
        return app

    async def index(self, request: web.Request) -> web.Response:
        return _static("index.html")

    async def static(self, request: web.Request) -> web.Response:
        return _static(request.match_info["name"])

    async def api_snapshot(self, request: web.Request) -> web.Response:
        return web.Response(text=_dumps(self.fleet.snapshot(self.clock())), content_type="application/json")

    async def websocket(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(heartbeat=20.0)
        await ws.prepare(request)
        queue: asyncio.Queue = asyncio.Queue()
        queue.put_nowait(_dumps(self.fleet.snapshot(self.clock())))  # no await between this and the next line:
        self.clients[ws] = queue                                      # no update is missed or sent before it
        sender = asyncio.create_task(self._send(ws, queue))
        try:
            async for msg in ws:  # read-only: what the page sends is dropped
                if msg.type == WSMsgType.ERROR:
                    break
        finally:
            self.clients.pop(ws, None)
            sender.cancel()
        return ws

    async def _send(self, ws: web.WebSocketResponse, queue: asyncio.Queue) -> None:
        try:
            while not ws.closed:
                await ws.send_str(await queue.get())
        except (ConnectionError, RuntimeError):
            pass

    def publish(self) -> str:
        """Make the next update and queue it for every browser."""
        text = _dumps(self.fleet.update(self.clock()))
        for queue in self.clients.values():
            if queue.qsize() >= MAX_QUEUED:
                while not queue.empty():
                    queue.get_nowait()
                queue.put_nowait(_dumps(self.fleet.snapshot(self.clock())))
            else:
                queue.put_nowait(text)
        self.updates_sent += 1
        return text

    async def _publisher(self) -> None:
        loop = asyncio.get_running_loop()
        next_s = loop.time()
        said = False
        while True:
            next_s += self.publish_period_s
            await asyncio.sleep(max(0.0, next_s - loop.time()))
            try:
                self.publish()
            except Exception as e:  # noqa: BLE001 - the publications go on (and the failure is said once)
                self.publish_failures += 1
                if not said:
                    print(f"ground.station: an update could not be made ({type(e).__name__}: {e}); counted",
                          file=sys.stderr, flush=True)
                    said = True

    async def _start(self, app) -> None:
        self._task = asyncio.create_task(self._publisher())

    async def _stop(self, app) -> None:
        if self._task is not None:
            self._task.cancel()
        for ws in list(self.clients):
            await ws.close()

"""The page's HTTP server: a Starlette app run by uvicorn in a thread of the daemon.

`WebServer.bind` runs before the agent starts anything: it reads the token and binds the port,
so a bad token file or a port in use ends `run` with status 78 and a message naming the key.
Read-only: every route is a GET. With a token, every request needs it: `Authorization: Bearer
<token>`, or the `silo_agent_token` cookie a first visit with `?token=<token>` sets (the page is
then reloaded without the token in its address); otherwise 401.

Scans are found only among the ids the audit cache lists (`Archive`), so a URL never reaches a
file outside it: an unknown id, a `..` or an encoded slash is a 404. Pictures are drawn one at
a time in one low-priority worker thread and kept per scan, so an open page costs a scan
little: the browser's refreshes are JSON of what changed (server-sent events).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import hmac
import json
import os
import re
import socket
import tempfile
import threading
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar
from urllib.parse import parse_qsl, urlencode

import structlog
import uvicorn
from starlette.applications import Starlette
from starlette.background import BackgroundTask
from starlette.requests import Request
from starlette.responses import (
    FileResponse,
    JSONResponse,
    PlainTextResponse,
    RedirectResponse,
    Response,
    StreamingResponse,
)
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send

from silo_agent.config import Config, ConfigError, WebConfig, read_token
from silo_agent.telemetry.heightmap_codec import HeightMapFormatError, decode_live_heightmap
from silo_agent.web.archive import HISTORY_RANGES, Archive, ScanNotFound, published_volume
from silo_agent.web.pictures import MapLayout, history_svg, legend, map_png

if TYPE_CHECKING:
    from silo_agent.service.daemon import Agent

log = structlog.get_logger(__name__)

COOKIE = "silo_agent_token"
EVENT_POLL_S = 0.5  # how often an open page's event stream looks for a change
PREPARE_POLL_S = 1.0  # how often the server looks for a new scan to draw before it is asked
KEPT_PICTURES = 8
SCANS_PER_PAGE = 50  # api/scans without `limit`
MAX_SCANS_PER_PAGE = 500  # a page stays cheap to build and to draw: a year of scans is 100,000
RENDER_NICENESS = 10  # the picture thread yields the CPU to a running scan
ASSETS = {
    "index.html": "text/html; charset=utf-8",
    "app.js": "text/javascript; charset=utf-8",
    "style.css": "text/css; charset=utf-8",
}
T = TypeVar("T")


class LiveFeed:
    """The latest live map (`P/heightmap/live` payload) a session published, for the page."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._payload: bytes | None = None
        self.count = 0

    def put(self, payload: bytes) -> None:
        with self._lock:
            self._payload = payload
            self.count += 1

    def latest(self) -> tuple[int, bytes | None]:
        with self._lock:
            return self.count, self._payload


@dataclass
class Sources:
    """What the page reads from the running agent, each call cheap and thread-safe."""

    archive: Archive
    config: Callable[[], Config]
    status: Callable[[], dict[str, Any]]  # cameras, alarm states, recent alarm events
    live: LiveFeed


def _nice_thread() -> None:
    """Lower this worker thread's CPU priority (Linux schedules threads one by one)."""
    with contextlib.suppress(AttributeError, OSError):  # not Linux, or not allowed
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), RENDER_NICENESS)


def _warm_up() -> None:
    """Import what drawing needs and load its fonts, in the picture thread, before the first
    page asks (about a second on a gateway core)."""
    history_svg([], None, "all")


class _Token:
    """ASGI middleware: 401 without the token; `?token=` sets the cookie and redirects."""

    def __init__(self, app: ASGIApp, token: str) -> None:
        self.app = app
        self.token = token.encode()

    def _matches(self, value: str | None) -> bool:
        return value is not None and hmac.compare_digest(value.encode(), self.token)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request = Request(scope)
        header = request.headers.get("authorization", "")
        bearer = header[7:].strip() if header.lower().startswith("bearer ") else None
        if self._matches(bearer) or self._matches(request.cookies.get(COOKIE)):
            await self.app(scope, receive, send)
            return
        query = parse_qsl(scope.get("query_string", b"").decode("latin-1"), keep_blank_values=True)
        given = [v for k, v in query if k == "token"]
        if given and self._matches(given[-1]):
            rest = urlencode([(k, v) for k, v in query if k != "token"])
            # the page itself, relative (behind a proxy's prefix too), as "./name": a bare last
            # segment such as "https:evil.example" reads as an absolute URL (an open redirect)
            name = "./" + request.url.path.rsplit("/", 1)[-1]
            response: Response = RedirectResponse(name + (f"?{rest}" if rest else ""), 303)
            response.set_cookie(COOKIE, self.token.decode(), httponly=True, samesite="strict")
        else:
            response = PlainTextResponse(
                "401 Unauthorized: this page needs the agent's web token "
                "(Authorization: Bearer <token>, or ?token=<token> once in a browser)\n",
                401,
                headers={"WWW-Authenticate": 'Bearer realm="silo-agent"'},
            )
        await response(scope, receive, send)


class Pages:
    """The routes; every picture is drawn in `pool` and kept per scan."""

    def __init__(self, sources: Sources) -> None:
        self.sources = sources
        self.pool = ThreadPoolExecutor(1, "web-render", initializer=_nice_thread)
        self._lock = threading.Lock()
        self._pictures: OrderedDict[tuple[str, ...], tuple[bytes, MapLayout | None]] = OrderedDict()
        self._assets = {
            name: resources.files("silo_agent.web").joinpath("static", name).read_bytes()
            for name in ASSETS
        }

    async def _off_loop(self, work: Callable[[], T]) -> T:
        return await asyncio.get_running_loop().run_in_executor(self.pool, work)

    def _kept(
        self, key: tuple[str, ...], draw: Callable[[], tuple[bytes, MapLayout | None]]
    ) -> tuple[bytes, MapLayout | None]:
        with self._lock:
            if key in self._pictures:
                self._pictures.move_to_end(key)
                return self._pictures[key]
        picture = draw()
        with self._lock:
            self._pictures[key] = picture
            while len(self._pictures) > KEPT_PICTURES:
                self._pictures.popitem(last=False)
        return picture

    # ------------------------------------------------------------ routes

    async def asset(self, request: Request) -> Response:
        name = request.path_params.get("name", "index.html")
        if name not in ASSETS:
            return PlainTextResponse("404 Not Found\n", 404)
        return Response(
            self._assets[name], media_type=ASSETS[name], headers={"Cache-Control": "no-cache"}
        )

    def state(self) -> dict[str, Any]:
        """The latest scan as `P/volume` says it, and what the agent knows now."""
        archive = self.sources.archive
        latest = archive.latest()
        config = self.sources.config()
        out: dict[str, Any] = {
            "silo_id": config.silo.id,
            "scans": len(archive.records()),
            "latest": None,
            **self.sources.status(),
        }
        live_count, payload = self.sources.live.latest()
        out["live"] = {"count": live_count, **(_live_meta(payload) if payload else {})}
        if latest is not None:
            try:
                summary = archive.summary(latest.scan_id)
            except ScanNotFound:
                return out
            try:
                published = published_volume(summary)
            except (KeyError, ValueError, TypeError):
                return out
            out["latest"] = {
                "published": published,
                "details": _details(summary),
            }
        return out

    async def api_state(self, _request: Request) -> Response:
        return JSONResponse(await self._off_loop(self.state))

    async def api_scans(self, request: Request) -> Response:
        """One page of the scan list, newest first: `limit` scans from the newest, or from
        the scan just older than `before` (a scan id), and whether older ones remain."""
        limit = request.query_params.get("limit", str(SCANS_PER_PAGE))
        # digits only, and few: int() takes "+5", " 5", "٥" and chokes on 5,000 digits
        if not (re.fullmatch("[0-9]{1,3}", limit) and 1 <= int(limit) <= MAX_SCANS_PER_PAGE):
            return _bad_request("limit", f"a whole number from 1 to {MAX_SCANS_PER_PAGE}")
        before = request.query_params.get("before")
        try:
            records, more = await self._off_loop(
                lambda: self.sources.archive.page(int(limit), before)
            )
        except ScanNotFound:
            return _bad_request("before", f"no scan {before!r} in the list (removed since?)")
        return JSONResponse({"scans": [r.to_json() for r in records], "more": more})

    def scan_map(self, scan_id: str) -> tuple[bytes, MapLayout | None]:
        """One scan's map picture and layout, drawn once and kept (call in `pool`)."""

        def draw() -> tuple[bytes, MapLayout | None]:
            view = self.sources.archive.view(scan_id)
            if view.heightmap is None:
                raise ScanNotFound(f"{scan_id} has no height map")
            return map_png(
                view.heightmap,
                view.floor_z,
                view.region,
                piles=view.summary.get("piles") or [],
                cameras=view.cameras,
            )

        return self._kept(("map", scan_id), draw)

    def prepare(self, scan_id: str) -> None:
        """Draw a scan's map before anyone asks (call in `pool`): the first visit after a scan
        finds its picture drawn."""
        try:
            self.scan_map(scan_id)
        except ScanNotFound:
            pass  # a result without a height map: nothing to draw
        except Exception:  # the page must never take the agent down; a request will retry
            log.exception("cannot draw the latest scan's map", scan_id=scan_id)

    async def api_map(self, request: Request) -> Response:
        scan_id, kind = request.path_params["scan_id"], request.path_params["kind"]
        if kind not in ("png", "json"):
            raise ScanNotFound(f"{scan_id}.{kind}")
        png, layout = await self._off_loop(lambda: self.scan_map(scan_id))
        if kind == "png":
            return Response(png, media_type="image/png", headers={"Cache-Control": "max-age=3600"})
        assert layout is not None
        view = await self._off_loop(lambda: self.sources.archive.view(scan_id))
        cameras = [
            {
                "serial": c.serial,
                "position": c.position,
                "points": c.points,
                "coverage": c.coverage,
                "gravity_deg": c.gravity_deg,
            }
            for c in view.cameras
        ]
        return JSONResponse(
            {"scan_id": scan_id, **layout.to_json(), "legend": legend(layout), "cameras": cameras}
        )

    async def api_live(self, _request: Request) -> Response:
        count, payload = self.sources.live.latest()
        if payload is None:
            return PlainTextResponse("404 Not Found: no live map yet\n", 404)

        def draw() -> tuple[bytes, MapLayout | None]:
            live = decode_live_heightmap(payload)
            config = self.sources.config()
            png, layout = map_png(
                live.heightmap,
                config.silo.floor_z,
                _region(config),
                robots=live.meta.get("robots") or [],
                scale_band=True,  # no legend beside it: the page fetches only the picture
            )
            return png, layout

        try:
            png, _layout = await self._off_loop(lambda: self._kept(("live", str(count)), draw))
        except HeightMapFormatError:
            return PlainTextResponse("404 Not Found: unreadable live map\n", 404)
        return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})

    async def api_history(self, request: Request) -> Response:
        span = request.query_params.get("range", "week")
        if span not in HISTORY_RANGES:
            return PlainTextResponse(
                f"400 Bad Request: range is one of {list(HISTORY_RANGES)}\n", 400
            )

        def draw() -> str:
            records = self.sources.archive.history(span)
            return history_svg(records, self.sources.config().silo.bulk_density_t_m3, span)

        svg = await self._off_loop(draw)
        return Response(svg, media_type="image/svg+xml", headers={"Cache-Control": "no-store"})

    async def report(self, request: Request) -> Response:
        from silo_agent.web.report import report_html

        scan_id = request.path_params["scan_id"]
        view = await self._off_loop(lambda: self.sources.archive.view(scan_id))
        html = await self._off_loop(lambda: report_html(view))
        return Response(html, media_type="text/html; charset=utf-8")

    async def export(self, request: Request) -> Response:
        scan_id = request.path_params["scan_id"]
        archive = self.sources.archive
        archive.directory(scan_id)  # ScanNotFound before any file is made
        handle, name = tempfile.mkstemp(prefix="silo-agent-export-", suffix=".tar.gz")
        os.close(handle)
        path = Path(name)
        try:
            await self._off_loop(lambda: archive.cache.export(scan_id, path))
        except BaseException:
            path.unlink(missing_ok=True)
            raise
        return FileResponse(
            path,
            media_type="application/gzip",
            filename=f"{scan_id}.tar.gz",
            background=BackgroundTask(path.unlink, missing_ok=True),
        )

    async def events(self, request: Request) -> Response:
        """Server-sent events: `state` whenever it changes (a scan, an alarm, a camera, a new
        live map)."""

        async def stream() -> AsyncIterator[str]:
            last_state = ""
            while not await request.is_disconnected():
                state = json.dumps(await self._off_loop(self.state), sort_keys=True)
                if state != last_state:
                    last_state = state
                    yield f"event: state\ndata: {state}\n\n"
                await asyncio.sleep(EVENT_POLL_S)

        return StreamingResponse(
            stream(),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
        )


def _bad_request(parameter: str, problem: str) -> Response:
    """A 400 whose one-line JSON names the query parameter at fault."""
    return JSONResponse({"error": f"{parameter}: {problem}"}, 400)


def _region(config: Config) -> Any:
    return config.silo.region_polygon()  # `region`, or a bin's wall


def _live_meta(payload: bytes) -> dict[str, Any]:
    try:
        live = decode_live_heightmap(payload)
    except HeightMapFormatError:
        return {}
    return {"session_id": live.session_id, "sequence": live.sequence, **live.meta}


DETAIL_KEYS = (
    "method",
    "grid_step_m",
    "invalid_reason",
    "fill_ratio",
    "headspace_m",
    "capacity_m3",
    "registration_residual_m",
    "cameras",
    "piles",
    "surface",
)


def _details(summary: dict[str, Any]) -> dict[str, Any]:
    """What the page shows beside `P/volume`'s figures, each only if the result has it."""
    return {k: summary[k] for k in DETAIL_KEYS if k in summary}


def app_for(sources: Sources, token: str | None) -> tuple[ASGIApp, Pages]:
    pages = Pages(sources)

    async def not_found(_request: Request, exc: Exception) -> Response:
        return PlainTextResponse(f"404 Not Found: {exc}\n", 404)

    async def failed(_request: Request, exc: Exception) -> Response:
        log.error("web request failed", error=repr(exc))
        return PlainTextResponse("500 Internal Server Error\n", 500)

    routes = [
        Route("/", pages.asset),
        Route("/static/{name}", pages.asset),
        Route("/api/state", pages.api_state),
        Route("/api/scans", pages.api_scans),
        Route("/api/map/{scan_id}.{kind}", pages.api_map),
        Route("/api/live.png", pages.api_live),
        Route("/api/history.svg", pages.api_history),
        Route("/api/events", pages.events),
        Route("/scans/{scan_id}/report.html", pages.report),
        Route("/scans/{scan_id}/export.tar.gz", pages.export),
    ]
    app: ASGIApp = Starlette(
        routes=routes,
        exception_handlers={ScanNotFound: not_found, Exception: failed},
    )
    if token is not None:
        app = _Token(app, token)
    return app, pages


class WebServer:
    """`bind` at start (errors: ConfigError), `start` once the agent is up, `stop` at the end;
    the agent's supervision restarts its thread if it dies (`alive`, `restart`)."""

    name = "web"

    def __init__(self, cfg: WebConfig, token: str | None, sock: socket.socket) -> None:
        self.cfg = cfg
        self.token = token
        self.sock = sock
        self._server: uvicorn.Server | None = None
        self._thread: threading.Thread | None = None
        self._pages: Pages | None = None
        self._app: ASGIApp | None = None
        self._stopping = threading.Event()
        self._watcher: threading.Thread | None = None

    @classmethod
    def bind(cls, cfg: WebConfig) -> WebServer:
        token = None
        if cfg.token_file is not None:
            try:
                token = read_token(cfg.token_file)
            except (OSError, ValueError) as exc:
                raise ConfigError(f"web.token_file: {exc}") from None
            if not token:
                raise ConfigError(f"web.token_file: {cfg.token_file} is empty")
        try:
            sock = _listen(cfg)
        except OSError as exc:
            raise ConfigError(
                f"web: cannot listen on {cfg.host}:{cfg.port}: {exc.strerror or exc}"
                + ("; choose another web.port" if exc.errno == errno.EADDRINUSE else "")
            ) from None
        return cls(cfg, token, sock)

    @property
    def port(self) -> int:
        return int(self.sock.getsockname()[1])

    def start(self, agent: Agent) -> None:
        """Serve `agent`'s page: its audit cache, config, node state and live maps."""
        feed = LiveFeed()
        agent.telemetry.watch_live(feed.put)
        self.serve(
            Sources(Archive(agent.cache), lambda: agent.config, agent.telemetry.snapshot, feed)
        )

    def serve(self, sources: Sources) -> None:
        self._app, self._pages = app_for(sources, self.token)
        self._run()
        self._pages.pool.submit(_warm_up)  # matplotlib's import (~1 s) off the first request
        self._watcher = threading.Thread(
            target=self._prepare_new_scans, args=(self._pages,), name="web-prepare", daemon=True
        )
        self._watcher.start()
        log.info(
            "web page serving",
            url=f"http://{self.cfg.host}:{self.port}/",
            token=self.token is not None,
        )

    def _prepare_new_scans(self, pages: Pages) -> None:
        """Each new latest scan's map drawn in the picture thread once it is listed (a
        directory listing a second, as an open page's event stream does); ends with the
        server."""
        drawn: str | None = None
        while True:
            try:
                latest = pages.sources.archive.latest()
                if latest is not None and latest.scan_id != drawn:
                    pages.pool.submit(pages.prepare, latest.scan_id)
                    drawn = latest.scan_id
            except RuntimeError:  # the pool was shut down: the server is stopping
                return
            except Exception:
                log.exception("cannot list the audit cache for the page")
            if self._stopping.wait(PREPARE_POLL_S):
                return

    def _run(self) -> None:
        assert self._app is not None
        config = uvicorn.Config(
            self._app,
            log_config=None,
            access_log=False,
            lifespan="off",
            timeout_graceful_shutdown=1,
        )
        self._server = uvicorn.Server(config)
        self._thread = threading.Thread(
            target=self._server.run, kwargs={"sockets": [self.sock]}, name="web", daemon=True
        )
        self._thread.start()

    def alive(self) -> bool:
        """The server's thread runs (or it was never started)."""
        return self._thread is None or self._thread.is_alive()

    def restart(self) -> None:
        """A new server after its thread died, on the port again if the dying one closed it.
        If another process took the port meanwhile the page stays down (logged): the scans
        go on, the page is not worth stopping the agent for."""
        if self.sock.fileno() == -1:
            try:
                self.sock = _listen(self.cfg)
            except OSError as exc:
                log.error(
                    "web page down: cannot listen again",
                    address=f"{self.cfg.host}:{self.cfg.port}",
                    error=exc.strerror or str(exc),
                )
                self._thread = None
                return
        self._run()

    def stop(self) -> None:
        self._stopping.set()
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(5)
        if self._pages is not None:
            self._pages.pool.shutdown(wait=False, cancel_futures=True)
        self.sock.close()


def _listen(cfg: WebConfig) -> socket.socket:
    family = socket.AF_INET6 if ":" in cfg.host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((cfg.host, cfg.port))
        sock.listen(64)
    except OSError:
        sock.close()
        raise
    return sock

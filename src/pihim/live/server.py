"""The ground-station web server of ``pihim live``: a page, a WebSocket of frames, a capture endpoint.

Built on Starlette and served by uvicorn (optional extra ``pihim[live]``).

Routes
------
``GET /``, ``/app.js``, ``/app.css``
    The page (fixed files shipped with pihim; no path from the request is
    ever looked up on disk).
``WS /ws``
    Binary messages: one frame packet each (:func:`pihim.live.engine.pack_packet`),
    newest only -- a slow browser skips frames instead of queueing them; text
    messages: ``{"type": "status", ...}`` once a second and on every error
    change, so an error shows while no frame arrives.
``POST /api/capture``
    ``Content-Type: application/json``, body ``{}`` or ``{"label": "..."}``
    (1-48 letters, digits, ``_``, ``-``): writes the newest raw frame and its
    JSON record (:func:`pihim.live.engine.write_capture`) and answers with the
    record.
``GET /api/status``
    :meth:`pihim.live.engine.LiveEngine.status`.

Security
--------
* Bound to the loopback address by default. Any other address needs a
  token (:func:`check_bind`); every request must then carry it: ``?token=``
  in the URL (the page passes it on), an ``Authorization: Bearer`` header, or
  the ``pihim_live_token`` cookie. Tokens are compared in constant time.
* Without a token only ``Host: localhost``, ``127.0.0.1`` or ``[::1]`` is
  served, which defeats DNS rebinding; WebSocket and POST requests from a
  page of another origin (``Origin`` not matching ``Host``) are refused, so a
  web site open in the operator's browser cannot drive the server.
* Captures are named by the server; the only client text that reaches a
  file name is the label, checked against a strict pattern.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import hmac
import ipaddress
import json
import signal
import socket
import threading
import time
from collections.abc import AsyncIterator, Callable
from importlib import resources
from typing import Any
from urllib.parse import parse_qs, urlsplit

from pihim.errors import PihimInputError
from pihim.live.engine import LABEL_RE, LiveEngine

__all__ = ["MIN_TOKEN_LENGTH", "bind_socket", "build_app", "check_bind", "is_loopback", "serve"]

#: Shortest token accepted for a server reachable from other machines.
MIN_TOKEN_LENGTH = 16
_LOCAL_HOSTS = {"localhost", "127.0.0.1", "::1"}
_COOKIE = "pihim_live_token"
_STATIC = {"/": ("index.html", "text/html; charset=utf-8"),
           "/app.js": ("app.js", "text/javascript; charset=utf-8"),
           "/app.css": ("app.css", "text/css; charset=utf-8")}
_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY",
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob:; connect-src 'self' ws: wss:; "
                               "frame-ancestors 'none'",
}


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback name or address (``localhost``, 127.0.0.0/8, ``::1``)."""
    h = host.strip().strip("[]").lower()
    if h == "localhost":
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False


def check_bind(host: str, token: str | None) -> None:
    """Refuse to serve beyond this machine without a token (PihimInputError)."""
    if token is not None and len(token) < MIN_TOKEN_LENGTH:
        raise PihimInputError(f"--token must be at least {MIN_TOKEN_LENGTH} characters (e.g. --token auto, or "
                              f"python -c 'import secrets; print(secrets.token_urlsafe())')")
    if token is not None and not token.isprintable():
        raise PihimInputError("--token must be printable text")
    if not is_loopback(host):
        try:  # an unresolvable --host is the error to report, not the missing token
            socket.getaddrinfo(host.strip("[]"), None, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
        except (socket.gaierror, UnicodeError) as exc:
            raise PihimInputError(f"--host {host}: cannot resolve the address ({exc})") from None
    if not is_loopback(host) and token is None:
        raise PihimInputError(f"--host {host} makes the live view reachable from other machines: give a "
                              f"--token (or --token auto), or keep the default --host 127.0.0.1")


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port``; one-line PihimInputError when that is impossible."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise PihimInputError(f"--port must be an integer in 0..65535, got {port!r}")
    try:
        infos = socket.getaddrinfo(host.strip("[]"), port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        raise PihimInputError(f"--host {host}: cannot resolve the address ({exc})") from None
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if family == socket.AF_INET6:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
        sock.bind(addr)
        sock.listen(64)
    except OSError as exc:
        sock.close()
        if exc.errno == errno.EADDRINUSE:
            raise PihimInputError(f"--port {port}: {host}:{port} is already in use (another pihim live?); "
                                  f"choose another --port") from None
        if exc.errno == errno.EADDRNOTAVAIL:
            raise PihimInputError(f"--host {host}: not an address of this machine") from None
        if exc.errno == errno.EACCES:
            raise PihimInputError(f"--port {port}: permission denied (ports below 1024 need privileges)") from None
        raise PihimInputError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    sock.setblocking(False)
    return sock


def _static(name: str) -> bytes:
    return resources.files("pihim.live").joinpath("static", name).read_bytes()


def _host_name(host_header: str) -> str:
    """Host name of a ``Host`` header value (port and IPv6 brackets removed), lower case."""
    h = host_header.strip().lower()
    if h.startswith("["):
        return h[1:h.find("]")] if "]" in h else h
    return h.rsplit(":", 1)[0] if h.count(":") == 1 else h


class _Hub:
    """Wakes the WebSocket senders (in the event loop) when the engine (in its thread) has news."""

    def __init__(self) -> None:
        self.loop: asyncio.AbstractEventLoop | None = None
        self.events: set[asyncio.Event] = set()

    def poke(self) -> None:
        loop = self.loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # loop closing
                loop.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        for ev in self.events:
            ev.set()


def build_app(engine: LiveEngine, *, token: str | None = None, start_engine: bool = True) -> Any:
    """The Starlette application serving ``engine`` (see the module notes).

    Parameters
    ----------
    engine : LiveEngine
    token : str, optional
        Required on every request when given.
    start_engine : bool
        Start the engine at application start-up and stop it at shutdown.
    """
    from starlette.applications import Starlette
    from starlette.responses import JSONResponse, Response
    from starlette.routing import Route, WebSocketRoute
    from starlette.websockets import WebSocket, WebSocketDisconnect

    hub = _Hub()
    engine.on_packet = hub.poke
    pages = {path: (_static(name), mime) for path, (name, mime) in _STATIC.items()}

    def token_ok(scope_headers: dict[str, str], query: str) -> bool:
        if token is None:
            return True
        given = parse_qs(query).get("token", [None])[0]
        if given is None:
            auth = scope_headers.get("authorization", "")
            if auth.lower().startswith("bearer "):
                given = auth[7:].strip()
        if given is None:
            for part in scope_headers.get("cookie", "").split(";"):
                k, _, v = part.strip().partition("=")
                if k == _COOKIE:
                    given = v
        return given is not None and hmac.compare_digest(given.encode("utf-8", "replace"), token.encode("utf-8"))

    def refusal(headers: dict[str, str], query: str, *, cross_origin_matters: bool) -> tuple[int, str] | None:
        if not token_ok(headers, query):
            return 401, "a valid token is required (open the page as http://HOST:PORT/?token=...)"
        host = headers.get("host", "")
        if token is None and _host_name(host) not in _LOCAL_HOSTS:
            return 403, "unknown Host header (without a token only localhost is served)"
        origin = headers.get("origin")
        if cross_origin_matters and origin is not None and urlsplit(origin).netloc.lower() != host.lower():
            return 403, "cross-origin request refused"
        return None

    class Guard:
        """ASGI middleware enforcing token, Host and Origin rules on HTTP and WebSocket requests."""

        def __init__(self, app: Any) -> None:
            self.app = app

        async def __call__(self, scope: dict, receive: Callable, send: Callable) -> None:
            if scope["type"] not in ("http", "websocket"):
                await self.app(scope, receive, send)
                return
            headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
            query = scope.get("query_string", b"").decode("latin-1")
            cross = scope["type"] == "websocket" or scope.get("method", "GET") not in ("GET", "HEAD")
            why = refusal(headers, query, cross_origin_matters=cross)
            if why is None:
                await self.app(scope, receive, send)
                return
            code, text = why
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008, "reason": text[:100]})
                return
            body = json.dumps({"error": text}).encode()
            await send({"type": "http.response.start", "status": code,
                        "headers": [(b"content-type", b"application/json"),
                                    (b"content-length", str(len(body)).encode())]})
            await send({"type": "http.response.body", "body": body})

    async def page(request: Any) -> Response:
        body, mime = pages[request.url.path]
        resp = Response(body, media_type=mime.split(";")[0], headers=_HEADERS)
        if token is not None and request.url.path == "/":
            resp.set_cookie(_COOKIE, token, httponly=True, samesite="strict")
        return resp

    async def status(request: Any) -> JSONResponse:  # noqa: ARG001
        return JSONResponse(engine.status(), headers=_HEADERS)

    async def capture(request: Any) -> JSONResponse:
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return JSONResponse({"error": "send JSON (Content-Type: application/json)"}, 415)
        body = await request.body()
        if len(body) > 4096:
            return JSONResponse({"error": "request too large"}, 413)
        try:
            data = json.loads(body or b"{}")
        except (ValueError, RecursionError):
            return JSONResponse({"error": "body is not JSON"}, 400)
        if not isinstance(data, dict) or set(data) - {"label"}:
            return JSONResponse({"error": "body must be {} or {\"label\": \"...\"}"}, 400)
        label = data.get("label")
        if label in ("", None):
            label = None
        elif not isinstance(label, str) or not LABEL_RE.match(label):
            return JSONResponse({"error": "label must be 1-48 letters, digits, '_' or '-', starting with a letter "
                                          "or digit"}, 400)
        try:
            record = await asyncio.to_thread(engine.capture, label)
        except LookupError:
            return JSONResponse({"error": "no frame yet"}, 503)
        except PihimInputError as exc:
            return JSONResponse({"error": str(exc)}, 400)
        except OSError as exc:
            return JSONResponse({"error": f"cannot write the capture: {exc.strerror or exc}"}, 500)
        return JSONResponse(record, headers=_HEADERS)

    async def frames(websocket: WebSocket) -> None:
        await websocket.accept()
        ev = asyncio.Event()
        ev.set()
        hub.events.add(ev)

        async def drain() -> None:
            with contextlib.suppress(WebSocketDisconnect, RuntimeError):
                while True:
                    msg = await websocket.receive()
                    if msg["type"] == "websocket.disconnect":
                        return

        receiver = asyncio.create_task(drain())
        last_seq, last_status, last_beat = 0, -1, 0.0
        try:
            while not receiver.done():
                waiter = asyncio.create_task(ev.wait())
                await asyncio.wait({waiter, receiver}, timeout=1.0, return_when=asyncio.FIRST_COMPLETED)
                waiter.cancel()
                ev.clear()
                if receiver.done():
                    break
                seq, packet, t_raw = engine.latest()
                if packet is not None and seq != last_seq:
                    await websocket.send_bytes(packet)
                    engine.record_send(t_raw)
                    last_seq = seq
                now = time.monotonic()
                if engine.status_seq != last_status or now - last_beat >= 1.0:
                    last_status, last_beat = engine.status_seq, now
                    await websocket.send_text(json.dumps({"type": "status", **engine.status()}, default=str))
        except (WebSocketDisconnect, RuntimeError, ConnectionError, OSError):
            pass
        finally:
            hub.events.discard(ev)
            receiver.cancel()

    @contextlib.asynccontextmanager
    async def lifespan(app: Any) -> AsyncIterator[None]:  # noqa: ARG001
        hub.loop = asyncio.get_running_loop()
        if start_engine:
            engine.start()
        try:
            yield
        finally:
            hub.loop = None
            if start_engine:
                await asyncio.to_thread(engine.stop)

    routes = [Route(p, page, methods=["GET", "HEAD"]) for p in _STATIC]
    routes += [Route("/api/status", status, methods=["GET"]), Route("/api/capture", capture, methods=["POST"]),
               WebSocketRoute("/ws", frames)]
    app = Starlette(routes=routes, lifespan=lifespan)
    return Guard(app)


def _uvicorn_server_class() -> type:
    import uvicorn

    class _Server(uvicorn.Server):
        """uvicorn's server, stopping on SIGINT/SIGTERM without re-raising them (the CLI reports them)."""

        received: int | None = None

        @contextlib.contextmanager
        def capture_signals(self) -> Any:  # uvicorn >= 0.29
            if threading.current_thread() is not threading.main_thread():
                yield
                return
            previous = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
            try:
                yield
            finally:
                for s, h in previous.items():
                    signal.signal(s, h)

        def install_signal_handlers(self) -> None:  # uvicorn < 0.29
            if threading.current_thread() is threading.main_thread():
                for s in (signal.SIGINT, signal.SIGTERM):
                    signal.signal(s, self._on_signal)

        def _on_signal(self, sig: int, frame: Any) -> None:  # noqa: ARG002
            self.received = sig
            if self.should_exit and sig == signal.SIGINT:
                self.force_exit = True
            self.should_exit = True

    return _Server


def serve(engine: LiveEngine, sock: socket.socket, *, token: str | None = None, duration_s: float | None = None,
          on_started: Callable[[], None] | None = None) -> int | None:
    """Serve until SIGINT/SIGTERM (or ``duration_s``); returns the signal that stopped it, if any.

    Parameters
    ----------
    engine : LiveEngine
        Started at start-up, stopped at shutdown.
    sock : socket.socket
        Listening socket (:func:`bind_socket`).
    token : str, optional
    duration_s : float, optional
        Stop after this many seconds (tests, benchmarks).
    on_started : callable, optional
        Called once the server accepts connections.
    """
    import uvicorn

    app = build_app(engine, token=token)
    config = uvicorn.Config(app, log_level="warning", access_log=False, lifespan="on", timeout_graceful_shutdown=3,
                            ws_ping_interval=None)
    server = _uvicorn_server_class()(config)

    def watch() -> None:
        while not server.started and not server.should_exit:
            time.sleep(0.02)
        if server.started and on_started is not None:
            on_started()
        if duration_s is not None:
            deadline = time.monotonic() + duration_s
            while time.monotonic() < deadline and not server.should_exit:
                time.sleep(0.05)
            server.should_exit = True

    threading.Thread(target=watch, name="pihim-live-watch", daemon=True).start()
    server.run(sockets=[sock])
    return server.received

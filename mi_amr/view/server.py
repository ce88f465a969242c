"""The viewer's web server (Starlette on uvicorn): the page, its files and
one websocket per tab, speaking `protocol`.

Safety (docs/design.md section 11): the page and the websocket need the
secret token (``?token=...``); the served page carries it in itself (a
``<meta>``), never in a cookie, so no other server on this machine (ports do
not separate cookies) ever receives it. The websocket also needs an
``Origin`` that is the viewer's own, and every request a ``Host`` that names
it (no DNS rebinding); the static files (code, no data) are public. The
server binds 127.0.0.1 unless told otherwise; the socket listens before the
URL is printed.

Each websocket message is parsed once (`protocol.parse`) and handed to the
engine (`dispatch`, as the notebook widget does); a malformed one gets an
``error`` reply and changes nothing. Replies wait in a bounded `Outbox` (a
newer histogram or status replaces an unsent one); frames wait for the
page's ``ack`` of the previous one and only the newest waits (no backlog).
A tab that goes away, however abruptly, ends its view quietly.
"""

from __future__ import annotations

import asyncio
import collections
import hmac
import json
import html
import ipaddress
import os
import secrets
import socket
import struct
import tempfile
import threading
from dataclasses import replace
from pathlib import Path

from . import protocol as p
from .dispatch import VIEW_CHANGES, answer, error_reply
from .engine import ViewEngine
from .protocol import MAX_MESSAGE
from .snapshot import SnapshotBudget

STATIC = Path(__file__).parent / "static"
#: The page's placeholder for its token (index.html), filled when served.
TOKEN_META = '<meta name="mi-amr-token" content="">'
#: A frame is sent without the previous one's ack after this long (seconds).
ACK_TIMEOUT = 2.0
#: Replies that may wait for one tab (beyond: the oldest is dropped).
MAX_PENDING = 64
#: Headers of every answer: nothing cached, the URL (with its token) never sent on.
HEADERS = {"Cache-Control": "no-store", "Referrer-Policy": "no-referrer", "X-Content-Type-Options": "nosniff"}


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or address) is this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def own_hosts(host: str, port: int) -> set[str] | None:
    """The ``Host`` headers that name a viewer bound to ``host``:``port``
    (None: any, for a server reachable from other machines)."""
    if not is_loopback(host):
        return None
    names = {host, "127.0.0.1", "localhost", "[::1]", f"[{host}]" if ":" in host else host}
    return {f"{n}:{port}" for n in names}


def make_app(engine: ViewEngine, token: str, out_dir, hosts: set[str] | None = None,
             budget: SnapshotBudget | None = None, on_error_shown=None):
    """The Starlette application serving ``engine``: ``hosts`` the ``Host``
    headers it answers (`own_hosts`; None: any), ``budget`` of snapshots,
    ``on_error_shown()`` once a tab was told that the load failed."""
    from starlette.applications import Starlette          # lazy: the mi-amr[view] extra
    from starlette.responses import FileResponse, HTMLResponse, PlainTextResponse, Response
    from starlette.routing import Route, WebSocketRoute

    out_dir = Path(out_dir).resolve()
    budget = budget or SnapshotBudget()
    template = (STATIC / "index.html").read_text()
    if TOKEN_META not in template:
        raise RuntimeError(f"static/index.html lacks {TOKEN_META!r}: the page could not carry its token")
    page_html = template.replace(TOKEN_META, f'<meta name="mi-amr-token" content="{html.escape(token)}">')

    def host_ok(conn) -> bool:
        return hosts is None or conn.headers.get("host", "") in hosts

    def origin_ok(conn) -> bool:
        """No Origin (not a browser) or the viewer's own: ``http://`` + the Host it asked."""
        origin = conn.headers.get("origin")
        return origin is None or origin == f"http://{conn.headers.get('host', '')}"

    def has_token(conn) -> bool:
        given = conn.query_params.get("token") or ""
        return hmac.compare_digest(given.encode(), token.encode())

    async def page(request):
        if not host_ok(request):
            return PlainTextResponse("403: unknown Host", status_code=403, headers=HEADERS)
        if not has_token(request):
            return PlainTextResponse("403: this viewer needs its token (the URL that mi-amr view printed)",
                                     status_code=403, headers=HEADERS)
        return HTMLResponse(page_html, headers=HEADERS)

    async def static(request):
        if not host_ok(request):
            return PlainTextResponse("403: unknown Host", status_code=403, headers=HEADERS)
        name = request.path_params["name"]
        files = {f.name: f for f in STATIC.iterdir() if f.is_file() and f.name != "index.html"}
        if name not in files:
            return PlainTextResponse("404", status_code=404, headers=HEADERS)
        return FileResponse(files[name], headers=HEADERS)

    async def favicon(request):
        return Response(status_code=204)

    async def ws_endpoint(ws):
        if not (host_ok(ws) and origin_ok(ws) and has_token(ws)):
            await ws.close(code=4403)           # before accepting: the handshake answers 403
            return
        try:
            await ws.accept()
            await _serve_socket(ws, engine, out_dir, budget, on_error_shown)
        except Exception:                       # a tab gone abruptly: nothing to say to anyone
            pass

    return Starlette(routes=[Route("/", page), Route("/static/{name}", static),
                             Route("/favicon.ico", favicon), WebSocketRoute("/ws", ws_endpoint)])


class Outbox:
    """The replies waiting for one tab, bounded: a newer histogram or status
    replaces an unsent one, and beyond `MAX_PENDING` the oldest goes (a
    page that reads nothing cannot grow the server's memory)."""

    COALESCED = ("histogram", "status")

    def __init__(self, limit: int = MAX_PENDING):
        self.limit = limit
        self._items: collections.deque = collections.deque()
        self._ready = asyncio.Event()

    def put(self, msg: p.ServerMessage):
        if msg.TYPE in self.COALESCED:
            for i, old in enumerate(self._items):
                if old.TYPE == msg.TYPE:
                    self._items[i] = msg
                    return
        self._items.append(msg)
        while len(self._items) > self.limit:
            self._items.popleft()
        self._ready.set()

    def __len__(self):
        return len(self._items)

    async def get(self) -> p.ServerMessage:
        while not self._items:
            self._ready.clear()
            await self._ready.wait()
        return self._items.popleft()


async def _serve_socket(ws, engine: ViewEngine, out_dir: Path, budget: SnapshotBudget, on_error_shown):
    loop = asyncio.get_running_loop()
    outbox = Outbox()
    latest = {"frame": None}
    frame_ready, acked = asyncio.Event(), asyncio.Event()
    acked.set()

    def soon(fn, *args):                             # from another thread; the tab may be gone
        try:
            loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:                         # its loop closed
            pass

    def send_frame(header, jpeg):                    # from the render thread: newest wins
        def put():
            latest["frame"] = (header, jpeg)
            frame_ready.set()
        soon(put)

    async def writer():
        while True:
            msg = await outbox.get()
            await ws.send_text(p.dumps(msg))
            if isinstance(msg, p.Status) and msg.state == "error" and on_error_shown is not None:
                on_error_shown()

    async def frames():
        while True:
            await frame_ready.wait()
            try:
                await asyncio.wait_for(acked.wait(), ACK_TIMEOUT)
            except asyncio.TimeoutError:
                pass
            frame_ready.clear()
            header, jpeg = latest["frame"]
            acked.clear()
            head = p.dumps(header).encode()
            await ws.send_bytes(struct.pack(">I", len(head)) + head + jpeg)

    def start(coro):                                 # a send to a tab that is gone ends its task;
        task = asyncio.create_task(coro)             # the loop below sees it done, and the
        task.add_done_callback(_retrieve)            # exception is taken here, never logged
        return task

    stop_status = engine.on_status(lambda s: soon(outbox.put, s))
    outbox.put(engine.status)
    tasks = [start(writer())]
    view = None
    expected = engine.expect_view()                  # nothing recorded ahead before its view opens
    try:
        while not engine.ready.is_set():             # loading: the status listener reports; the view
            await loop.run_in_executor(None, engine.ready.wait, 0.5)     # opens as soon as it is ready
        if engine.error:                             # the status said it; the page keeps showing it
            outbox.put(replace(engine.status, state="error", desc=engine.error))
            while (await ws.receive())["type"] != "websocket.disconnect":
                pass
            return
        view = engine.open_view(send_frame, lambda msg: soon(outbox.put, msg))
        expected()
        outbox.put(replace(engine.describe(view), out_dir=str(out_dir)))
        tasks.append(start(frames()))                # the first picture does not wait for the editor's histogram
        outbox.put(await loop.run_in_executor(None, engine.histogram, view))
        while True:
            message = await ws.receive()
            if message["type"] == "websocket.disconnect":
                break
            reply = await _handle(message, engine, view, out_dir, loop, acked, budget)
            if reply is not None:
                outbox.put(reply)
            if any(t.done() for t in tasks):         # a send failed: the tab is gone
                break
    finally:
        expected()
        for t in tasks:
            t.cancel()
        stop_status()
        if view is not None:
            engine.close_view(view)


def _retrieve(task: asyncio.Task) -> None:
    """Take a finished send task's exception (a disconnect) so that asyncio
    does not report it as never retrieved."""
    if not task.cancelled():
        task.exception()


async def _handle(message, engine, view, out_dir, loop, acked, budget=None) -> p.ServerMessage | None:
    """One page message -> a reply (or None); never raises for bad input.
    An ``ack`` opens the frame gate; a view change and a histogram are
    answered here, in order, the rest on a worker thread (`dispatch.answer`)."""
    about = None
    try:
        msg = p.parse(message.get("text"))
        about = msg.TYPE
        if isinstance(msg, p.Ack):
            acked.set()
            return None
        if isinstance(msg, VIEW_CHANGES + (p.HistogramRequest,)):
            return answer(engine, view, msg, out_dir, budget)
        return await loop.run_in_executor(None, answer, engine, view, msg, out_dir, budget)
    except Exception as e:
        return error_reply(e, about)


class ViewServer:
    """``engine`` served at ``http://HOST:PORT/?token=...`` (see module
    docstring); ``port`` 0 takes a free one. The socket listens once this
    object exists. `start` serves on a thread of its own (notebooks, tests),
    `run` on this one (the command line). ``error_shown`` is set once a tab
    was told that the load failed."""

    def __init__(self, engine: ViewEngine, host: str = "127.0.0.1", port: int = 0, token: str | None = None,
                 out_dir=".", quiet: bool = False, budget: SnapshotBudget | None = None):
        import uvicorn                                 # lazy: the mi-amr[view] extra
        self.engine, self.host = engine, host
        self.token = token or secrets.token_urlsafe(24)
        self.out_dir = Path(out_dir).resolve()
        self.error_shown = threading.Event()
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.sock.bind((host, port))
            self.sock.listen(128)                      # a first connection waits in the backlog
        except BaseException:
            self.sock.close()
            raise
        self.port = self.sock.getsockname()[1]
        app = make_app(engine, self.token, self.out_dir, own_hosts(host, self.port), budget, self.error_shown.set)
        config = uvicorn.Config(app, log_level="warning" if not quiet else "error",
                                ws_max_size=MAX_MESSAGE * 4, lifespan="off")
        self.server = uvicorn.Server(config)
        self._thread = None

    @property
    def origin(self) -> str:
        """``http://HOST:PORT``, the page's own origin."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    @property
    def url(self) -> str:
        return f"{self.origin}/?token={self.token}"

    def run(self):
        self.server.run(sockets=[self.sock])

    def start(self) -> "ViewServer":
        self._thread = threading.Thread(target=self.run, name="mi-amr view server", daemon=True)
        self._thread.start()
        return self

    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stop(self):
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=10)
        self.sock.close()


def redirect_file(url: str) -> Path:
    """A page that sends the browser on to ``url`` (with its token), in a
    fresh private folder (mode 0700), readable by this user alone (0600):
    the browser opens this file, so the token is on no command line (as
    Jupyter does). Remove its folder when the viewer ends."""
    folder = Path(tempfile.mkdtemp(prefix="mi-amr-view-"))
    page = folder / "open.html"
    fd = os.open(page, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    target = html.escape(url)
    with os.fdopen(fd, "w") as f:
        f.write(f"""<!doctype html>
<html><head><meta charset="utf-8"><meta name="referrer" content="no-referrer">
<meta http-equiv="refresh" content="0;url={target}"><title>mi-amr view</title></head>
<body><p>Opening <a href="{target}">mi-amr view</a>...</p>
<script>window.location.replace({json.dumps(url)});</script></body></html>
""")
    return page

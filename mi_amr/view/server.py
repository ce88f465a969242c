"""The viewer's web server (Starlette on uvicorn): the page, its files and
one websocket per tab, speaking `protocol`.

Every request needs the secret token: ``?token=...`` in the URL (the page
then keeps it in a cookie, as Jupyter does) or that cookie; without it, 403.
The server binds to 127.0.0.1 unless told otherwise. Each websocket
message is parsed once (`protocol.parse`) and handed to the engine; a
malformed one gets an ``error`` reply and changes nothing. Frames wait for
the page's ``ack`` of the previous one and only the newest waits (no
backlog).
"""

from __future__ import annotations

import asyncio
import hmac
import secrets
import socket
import struct
import sys
import threading
from dataclasses import replace
from pathlib import Path

from . import protocol as p
from .engine import ViewEngine
from .protocol import MAX_MESSAGE

STATIC = Path(__file__).parent / "static"
COOKIE = "mi_amr_view_token"
#: A frame is sent without the previous one's ack after this long (seconds).
ACK_TIMEOUT = 2.0


def make_app(engine: ViewEngine, token: str, out_dir):
    """The Starlette application serving ``engine``."""
    from starlette.applications import Starlette
    from starlette.responses import FileResponse, PlainTextResponse, Response
    from starlette.routing import Route, WebSocketRoute
    from starlette.websockets import WebSocket, WebSocketDisconnect

    out_dir = Path(out_dir)

    def authorised(conn) -> bool:
        given = conn.query_params.get("token") or conn.cookies.get(COOKIE) or ""
        return hmac.compare_digest(given.encode(), token.encode())

    async def page(request):
        if not authorised(request):
            return PlainTextResponse("403: this viewer needs its token (the URL that mi-amr view printed)",
                                     status_code=403)
        response = FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})
        response.set_cookie(COOKIE, token, httponly=True, samesite="strict")
        return response

    async def static(request):
        if not authorised(request):
            return PlainTextResponse("403", status_code=403)
        name = request.path_params["name"]
        files = {p.name: p for p in STATIC.iterdir() if p.is_file()}
        if name not in files:
            return PlainTextResponse("404", status_code=404)
        return FileResponse(files[name], headers={"Cache-Control": "no-store"})

    async def favicon(request):
        return Response(status_code=204)

    async def ws_endpoint(ws: WebSocket):
        if not authorised(ws):
            await ws.close(code=4403)
            return
        await ws.accept()
        await _serve_socket(ws, engine, out_dir, WebSocketDisconnect)

    return Starlette(routes=[Route("/", page), Route("/static/{name}", static),
                             Route("/favicon.ico", favicon), WebSocketRoute("/ws", ws_endpoint)])


async def _serve_socket(ws, engine: ViewEngine, out_dir: Path, disconnect):
    loop = asyncio.get_running_loop()
    outbox: asyncio.Queue = asyncio.Queue()          # JSON replies, in order
    latest = {"frame": None}
    frame_ready, acked = asyncio.Event(), asyncio.Event()
    acked.set()

    def status(s: p.Status):                         # from the loading thread
        loop.call_soon_threadsafe(outbox.put_nowait, s)

    def send_frame(header, jpeg):                    # from the render thread: newest wins
        def put():
            latest["frame"] = (header, jpeg)
            frame_ready.set()
        loop.call_soon_threadsafe(put)

    async def writer():
        while True:
            msg = await outbox.get()
            await ws.send_text(p.dumps(msg))

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

    stop_status = engine.on_status(status)
    await outbox.put(engine.status)
    tasks = [asyncio.create_task(writer())]
    view = None
    try:
        ready = await loop.run_in_executor(None, engine.ready.wait, 3600)
        if not ready or engine.error:
            await ws.send_text(p.dumps(replace(engine.status, state="error", desc=engine.error or "not ready")))
            return
        view = engine.open_view(send_frame)
        await outbox.put(engine.describe(view))
        await outbox.put(await loop.run_in_executor(None, engine.histogram, view))
        tasks.append(asyncio.create_task(frames()))
        while True:
            message = await ws.receive()
            if message["type"] == "websocket.disconnect":
                break
            reply = await _handle(message, engine, view, out_dir, loop, acked)
            if reply is not None:
                await outbox.put(reply)
    except disconnect:
        pass
    finally:
        for t in tasks:
            t.cancel()
        stop_status()
        if view is not None:
            engine.close_view(view)


async def _handle(message, engine, view, out_dir, loop, acked) -> p.ServerMessage | None:
    """One page message -> a reply (or None); never raises for bad input."""
    about = None
    try:
        msg = p.parse(message.get("text"))
        about = msg.TYPE
        match msg:
            case p.Ack():
                acked.set()
                return None
            case p.CameraChange() | p.TFChange() | p.DenoiseChange():
                if engine.change(view, msg):          # a new range or units: a new histogram
                    return engine.histogram(view)
                return None
            case p.HistogramRequest():
                return engine.histogram(view)
            case p.SnapshotRequest(name=name):
                paths = await loop.run_in_executor(None, engine.snapshot, view, out_dir, name)
                return p.SnapshotDone(tuple(str(f) for f in paths), view.spp)
    except p.ProtocolError as e:
        return p.Error(str(e), e.about)
    except ValueError as e:
        return p.Error(str(e), about)
    except Exception as e:                            # a bug must not end the session: say it
        return p.Error(f"{type(e).__name__}: {e}", about)


class ViewServer:
    """``engine`` served at ``http://HOST:PORT/?token=...`` (see module
    docstring); ``port`` 0 takes a free one. `start` serves on a thread of
    its own (notebooks, tests), `run` on this one (the command line)."""

    def __init__(self, engine: ViewEngine, host: str = "127.0.0.1", port: int = 0, token: str | None = None,
                 out_dir=".", quiet: bool = False):
        import uvicorn
        self.engine, self.host = engine, host
        self.token = token or secrets.token_urlsafe(24)
        self.sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind((host, port))
        self.port = self.sock.getsockname()[1]
        config = uvicorn.Config(make_app(engine, self.token, out_dir), log_level="warning" if not quiet else "error",
                                ws_max_size=MAX_MESSAGE * 4, lifespan="off")
        self.server = uvicorn.Server(config)
        self._thread = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/?token={self.token}"

    def run(self):
        self.server.run(sockets=[self.sock])

    def start(self) -> "ViewServer":
        self._thread = threading.Thread(target=self.run, name="mi-amr view server", daemon=True)
        self._thread.start()
        return self

    def stop(self):
        self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=10)
        self.sock.close()


def warn_if_exposed(host: str):
    if host not in ("127.0.0.1", "localhost", "::1"):
        print(f"mi-amr view: warning: serving on {host}, reachable from other machines; anyone with the "
              "token can read the data and write snapshots", file=sys.stderr)

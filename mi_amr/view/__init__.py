"""``mi-amr view``: explore AMR data in the browser (docs/design.md section 11).

`ViewEngine` renders (one `scene.LoadedScene`, a view per browser tab;
its parts: `views`, `scheduler`, `editor` and `snapshot`, which writes a
view to files), `ViewServer` serves the page and its websocket
(messages: `protocol`, routed to the engine by `dispatch`), `notebook`
shows the same page in Jupyter. Needs the ``mi-amr[view]`` extra
(Starlette, uvicorn; mitsuba-oidn for denoising)."""

from __future__ import annotations


def notebook(source, field=None, *, width: int = 1000, height: int = 640, out_dir=".", **engine_options):
    """Start a viewer of ``source`` on a background thread (loopback, a
    fresh token) and return an ``IPython.display.IFrame`` showing its page:
    the same page as ``mi-amr view``. ``engine_options`` go to `ViewEngine`
    (``res``, ``max_spp``, ``preview_scale``, ``variant``). The server is
    the frame's ``server`` attribute (``frame.server.stop()`` ends it)."""
    from IPython.display import IFrame

    from .engine import ViewEngine
    from .server import ViewServer
    engine = ViewEngine(source, field, **engine_options).start()
    server = ViewServer(engine, out_dir=out_dir, quiet=True).start()
    frame = IFrame(server.url, width=width, height=height)
    frame.server, frame.engine = server, engine
    return frame

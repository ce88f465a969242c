"""The viewer inside a notebook: `ViewWidget`, an anywidget on Jupyter's
comm channel (``sc.show()``, `mi_amr.data_scene.DataScene.show`).

The kernel runs the viewer's engine (`engine.ViewEngine`: progressive
passes, fast ones while the hand moves) for one view; the page is the
viewer's own page code (``static/viewer.js``, ``tf_editor.js``,
``camera.js``, ``viewer.css`` and the markup of ``index.html``), bundled by
`page_module` with ``static/widget.js`` (its transport: the widget's model)
into the widget's ES module, drawn in a shadow root of the cell's output.
Messages are the viewer's `protocol` messages: the page's go out as the
model's custom messages (``model.send``; those of 25 ms together as one
``{"type": "batch", "messages": [...]}``), the kernel's come back as custom
messages, frames as ``{"type": "frame", "header": Frame}`` with the JPEG
image as the message's one binary buffer; the page's reach the engine as
the server's do (`dispatch`). Nothing listens on any port: a
notebook served through JupyterHub, VS Code or a proxy works as a local one.
As the server does, the newest frame waits for the page's ``ack`` (of the
one before the previous: `MAX_IN_FLIGHT`; `ACK_TIMEOUT` at most) and older
ones are dropped.

State both ways, as traits: ``camera`` (``{"origin", "target", "up",
"fov"}``, world units and degrees), ``tf`` (the editor's state: ``points``,
``colormap``, ``log``, ``range``, ``density``; set it to that, to some of
those fields, to a preset or colormap name, or to a TF ``.json`` path),
``density_scale`` (extinction at opacity 1, inverse world units),
``mode`` (the lighting mode the picture refines in), ``hybrid``
(drag frames ray-marched, noise-free; False: 1-spp emission_absorption,
as the page's toggle beside the mode selector), ``iso`` (up to 4 iso
values in the field's own units, as ``DataScene.iso``: the isosurfaces
the page's iso control moves over the histogram) and ``iso_only`` (the
surfaces alone). Set from Python, they
change the picture (a bad value is a `ValueError`, nothing changed); moved
in the page, they follow (within `PULL_DELAY`; `ViewWidget.sync` at once).
Every change is also written into the `DataScene` the widget came from (``w.scene``): its camera, lighting mode,
iso values and the medium's TF table itself (a ``.json`` file in a folder of the
widget's, over the stored units: the log10 or linear storage the viewer
chose), so ``sc.render()`` renders the view on screen at full quality.

Threads: Dr.Jit is not safe to call from two threads at once. The engine
loads and renders only once a page shows the widget (its first message) or
a Python call needs the view (`ViewWidget.wait`, a trait set): a widget no
page shows (a script, a notebook run without a browser) renders nothing.
In IPython, each cell holds `engine.JIT_LOCK` while it runs (`CellHold`):
the engine renders while the kernel is idle, a cell's own Mitsuba calls
never run beside a pass. Elsewhere `DataScene.render` of the widget's scene
takes the lock; other code should too (or ``w.close()`` first).
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import json
import re
import tempfile
import threading
import time
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import anywidget
import mitsuba as mi
import numpy as np
import traitlets

from . import protocol as p
from .camera import OrbitCamera, world_up
from .dispatch import VIEW_CHANGES, answer, error_reply
from .engine import DEFAULT_MAX_SPP, JIT_LOCK, ViewEngine
from .snapshot import SnapshotBudget
from .tf_spec import PRESET_POINTS

STATIC = Path(__file__).parent / "static"
#: A frame is sent without the previous one's ack after this long (seconds), as the server does.
ACK_TIMEOUT = 2.0
#: Frames sent and not yet acked by the page, at most (the comm channel's round trip
#: through the kernel's message loop is longer than a websocket's).
MAX_IN_FLIGHT = 3
#: Longest wait of a trait set from Python for the data to load (seconds).
LOAD_TIMEOUT = 600.0
#: The page's changes reach the traits (and the DataScene) this long after them at most (seconds).
PULL_DELAY = 0.1

#: The widgets alive: their render threads end before the interpreter does
#: (a daemon thread inside Dr.Jit at exit aborts the process).
_LIVE = weakref.WeakSet()


@atexit.register
def _stop_engines():
    for widget in list(_LIVE):
        widget.engine.stop()


class CellHold:
    """In an IPython kernel, every cell holds `JIT_LOCK` while it runs
    (``pre_run_cell`` to ``post_run_cell``): a widget's engine renders while
    the kernel is idle and waits while a cell runs, so that a cell's own
    Mitsuba and Dr.Jit calls (``sc.render()``, a reference scene) never run
    beside a pass on another thread. `released` lets the engine run while
    this thread waits for it (`ViewWidget.wait`, ``close``)."""

    def __init__(self):
        self.held = 0
        self.registered = False

    def register(self):
        """Hook into the running IPython shell, once (nothing outside IPython)."""
        if self.registered:
            return
        try:
            from IPython import get_ipython          # lazy: notebooks only
        except ImportError:
            return
        shell = get_ipython()
        if shell is None:
            return
        shell.events.register("pre_run_cell", self.pre)
        shell.events.register("post_run_cell", self.post)
        self.registered = True

    def pre(self, *_):
        JIT_LOCK.acquire()
        self.held += 1

    def post(self, *_):
        while self.held:
            self.held -= 1
            JIT_LOCK.release()

    @contextlib.contextmanager
    def released(self):
        held, self.held = self.held, 0
        for _ in range(held):
            JIT_LOCK.release()
        try:
            yield
        finally:
            for _ in range(held):
                JIT_LOCK.acquire()
            self.held += held


#: The kernel's cells and the widgets' engines take turns (`CellHold`).
CELLS = CellHold()


_IMPORT = re.compile(r'^import\s*\{([^}]*)\}\s*from\s*"\./([\w.-]+\.js)";[ \t]*$', re.M)
_EXPORT = re.compile(r"^export\s+(?:async\s+)?(?:function\*?|const|let|class)\s+([\w$]+)", re.M)


def _module_name(file: str) -> str:
    return "__mi_amr_" + re.sub(r"\W", "_", file[:-3])


def _local_imports(source: str) -> list[str]:
    return [m.group(2) for m in _IMPORT.finditer(source)]


def _bound_imports(source: str, file: str) -> str:
    """``source`` with its ``import { a, b } from "./x.js"`` lines as
    bindings of the bundled module's object; any other import is refused."""
    body = _IMPORT.sub(lambda m: f"const {{{m.group(1)}}} = {_module_name(m.group(2))};", source)
    if re.search(r"^\s*import\b", body, re.M):
        raise ValueError(f"static/{file}: page_module bundles only `import {{ ... }} from \"./file.js\"`")
    return body


def page_module() -> str:
    """The widget's ES module, from the viewer's page files (one copy):
    ``viewer.js``'s local imports (``camera.js``, ``tf_editor.js``, any
    other ``./*.js`` it imports), each wrapped in a function that returns
    its exports, ``viewer.js`` itself as ``startViewer(widgetHost)``, the
    markup of index.html's ``<main>`` and viewer.css as ``MARKUP`` and
    ``STYLE``, then ``widget.js`` (the anywidget entry)."""
    order, seen = [], set()

    def visit(file):                        # dependencies first
        if file in seen:
            return
        seen.add(file)
        for dep in _local_imports((STATIC / file).read_text()):
            visit(dep)
        order.append(file)
    visit("viewer.js")
    parts = []
    for file in order[:-1]:
        source = (STATIC / file).read_text()
        names = _EXPORT.findall(source)
        body = re.sub(r"^export\s+", "", _bound_imports(source, file), flags=re.M)
        parts.append(f"const {_module_name(file)} = (() => {{\n{body}\nreturn {{ {', '.join(names)} }};\n}})();")
    parts.append(f"function startViewer(widgetHost) {{\n{_bound_imports((STATIC / 'viewer.js').read_text(), 'viewer.js')}\n}}")
    page = (STATIC / "index.html").read_text()
    markup = re.search(r"<main>.*</main>", page, re.S)
    if markup is None:
        raise ValueError("static/index.html: no <main> element for the widget")
    head = f"const MARKUP = {json.dumps(markup.group(0))};\nconst STYLE = {json.dumps((STATIC / 'viewer.css').read_text())};\n"
    return head + "\n".join(parts) + "\n" + (STATIC / "widget.js").read_text()


def camera_dict(camera: OrbitCamera) -> dict:
    """An orbit camera as the ``camera`` trait: origin, target, up (lists of
    3 floats, world units) and fov (degrees along x)."""
    return {"origin": [float(x) for x in camera.origin], "target": [float(x) for x in camera.target],
            "up": [float(x) for x in camera.up], "fov": float(camera.fov)}


class ViewWidget(anywidget.AnyWidget):
    """The viewer of ``scene`` (a `DataScene`) in a notebook cell (see the
    module docstring). ``res``: the picture's width in pixels;
    ``max_spp``: where refining stops; ``out_dir``: where the snapshot
    button writes; ``preview_scale``: the fast passes' share of ``res``;
    ``hybrid``: the drag frames ray-marched (the ``hybrid`` trait's start)."""

    _esm = page_module()
    camera = traitlets.Dict().tag(sync=True)
    tf = traitlets.Any(None, allow_none=True).tag(sync=True)
    density_scale = traitlets.Float(0.0).tag(sync=True)
    mode = traitlets.Unicode(None, allow_none=True).tag(sync=True)
    hybrid = traitlets.Bool(True).tag(sync=True)
    iso = traitlets.List(traitlets.Float()).tag(sync=True)
    iso_only = traitlets.Bool(False).tag(sync=True)

    def __init__(self, scene, *, res: int = 256, max_spp: int = DEFAULT_MAX_SPP, out_dir=".",
                 preview_scale: float = 0.5, hybrid: bool = True, **kwargs):
        super().__init__(**kwargs)
        self.scene = scene
        self.out_dir = Path(out_dir).resolve()
        self._pulling = threading.local()        # traits being set from the view (no echo back)
        self._lock = threading.Lock()            # the frame gate
        self._latest, self._in_flight, self._sent_at, self._last_frame = None, 0, 0.0, None
        self._pull_timer = None                  # a pull of the page's changes, due
        self._table = (None, None)               # (spec, its TF file) written last
        self._attached = threading.Event()
        self._budget = SnapshotBudget()
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="mi-amr widget")
        self._tf_dir = Path(tempfile.mkdtemp(prefix="mi-amr-widget-"))
        self.view = None
        variant = mi.variant() or "llvm_ad_rgb"
        self.engine = ViewEngine(scene.source, scene.field, res=res, max_spp=max_spp, preview_scale=preview_scale,
                                 variant=variant, mode=scene.mode, plan=scene.plan, hybrid=hybrid)
        scene._lock = JIT_LOCK                   # its renders wait for the engine's passes
        with self._from_view():
            self.camera = {"origin": scene.origin.tolist(), "target": scene.target.tolist(),
                           "up": scene.up.tolist(), "fov": float(scene.fov)}
            self.density_scale, self.mode = float(scene.density_scale), scene.mode
            self.hybrid = bool(hybrid)
        self._started = False
        self._stop_status = self.engine.on_status(self._send_json)
        self.on_msg(self._on_page)
        _LIVE.add(self)
        CELLS.register()

    def _start(self):
        """Load and render from the first page message or the first Python
        call that needs the view: a widget that no page shows (a script, a
        notebook run without a browser) renders nothing beside the code."""
        with self._lock:
            if self._started:
                return
            self._started = True
        self.engine.start()
        threading.Thread(target=self._attach, name="mi-amr widget attach", daemon=True).start()

    # ---- life cycle ------------------------------------------------------------------
    def _attach(self):
        """Once the data are loaded: the view, in the scene's TF, and its hello to the page."""
        self.engine.ready.wait()
        if self.engine.error:
            self._attached.set()
            return
        view = self.engine.open_view(self._frame, self._send_json)
        tf = self.scene.tf
        if tf not in PRESET_POINTS:              # a colormap or a file: the editor's state from it
            try:
                self._apply_tf(view, tf)
            except ValueError:
                pass
        self.view = view
        self._attached.set()
        self._pull()
        self._describe()

    def wait(self, timeout: float = LOAD_TIMEOUT, recorded: bool = False) -> "ViewWidget":
        """Wait until the data are loaded and the view is open (``recorded``:
        and the passes a drag needs are recorded); a `ValueError` when the
        load failed (its one line) or took too long."""
        self._start()
        deadline = time.monotonic() + timeout
        with CELLS.released():
            if not self._attached.wait(timeout):
                raise ValueError(f"the data did not load within {timeout:g} s")
            if self.engine.error:
                raise ValueError(f"the data could not be loaded: {self.engine.error}")
            while recorded and self.engine.warming and time.monotonic() < deadline:
                time.sleep(0.05)
        return self

    def close(self):
        """End the engine's render thread and this widget."""
        if self._pull_timer is not None:
            self._pull_timer.cancel()
        if self.view is not None:
            self.engine.close_view(self.view)
        self._stop_status()
        with CELLS.released():
            self.engine.stop()
        self._pool.shutdown(wait=False)
        super().close()

    # ---- to the page -------------------------------------------------------------------
    def _send_json(self, msg: p.Message):
        self.send(p.to_json(msg))

    def _frame(self, header: p.Frame, jpeg: bytes):
        """From the render thread: the newest frame goes when the page acked
        the last (or `ACK_TIMEOUT` passed); older unsent ones are dropped."""
        with self._lock:
            self._latest = self._last_frame = (header, jpeg)
            if self._in_flight < MAX_IN_FLIGHT or time.monotonic() - self._sent_at > ACK_TIMEOUT:
                self._send_latest()

    def _send_latest(self):                      # under self._lock
        header, jpeg = self._latest
        self._latest, self._sent_at = None, time.monotonic()
        self._in_flight = min(self._in_flight + 1, MAX_IN_FLIGHT)
        self.send({"type": "frame", "header": p.to_json(header)}, buffers=[jpeg])

    def _ack(self):
        with self._lock:
            self._in_flight = max(0, self._in_flight - 1)
            if self._latest is not None:
                self._send_latest()

    def _describe(self, frame: bool = True):
        """The view's hello (with where snapshots go) and (``frame``) its
        newest frame again, for a page shown late."""
        self._send_json(replace(self.engine.describe(self.view), out_dir=str(self.out_dir)))
        with self._lock:
            if frame and self._last_frame is not None:
                self._latest = self._last_frame
                self._send_latest()

    # ---- from the page ---------------------------------------------------------------
    def _on_page(self, _widget, content, buffers):
        """A page message, or a batch of them (``{"type": "batch",
        "messages": [...]}``: widget.js sends those of 25 ms together), on
        the kernel's thread; never raises."""
        if isinstance(content, dict) and content.get("type") == "batch" and \
                isinstance(content.get("messages"), list) and len(content) == 2:
            for message in content["messages"][:256]:
                self._on_message(message)
            return
        self._on_message(content)

    def _on_message(self, content):
        about = content.get("type") if isinstance(content, dict) else None
        self._start()
        try:
            msg = p.parse_message(content)
            if isinstance(msg, p.Ack):
                self._ack()
                return
            if not self._attached.is_set() or self.view is None:
                self._send_json(self.engine.status)      # still loading (or failed): the page shows it
                return
            if isinstance(msg, p.IsoChange):        # a refusal says where the values stay
                reply = answer(self.engine, self.view, msg, self.out_dir, self._budget)
                self._pull_soon()
                if reply is not None:
                    self._send_json(reply)
            elif isinstance(msg, VIEW_CHANGES):
                histogram = self.engine.change(self.view, msg)
                self._pull_soon()
                if histogram:                    # a new range or units: its histogram from the worker
                    self._pool.submit(self._answer, p.HistogramRequest())
            else:                                # slower: on the widget's worker thread
                self._pool.submit(self._answer, msg)
        except Exception as e:                   # one line for the page (a bug too: the session goes on)
            self._send_json(error_reply(e, about))

    def _answer(self, msg):
        """Answer a request on the worker thread (`dispatch.answer`, as the
        server does); a `Hello` says where snapshots go, ``describe`` also
        sends the newest frame again, the TF editor's changes reach the traits."""
        try:
            if isinstance(msg, p.Describe):
                self._describe()
                return
            reply = answer(self.engine, self.view, msg, self.out_dir, self._budget)
            if not isinstance(msg, (p.HistogramRequest, p.SnapshotRequest)):    # the TF editor's: save, load, field
                self._pull()
            if isinstance(reply, p.Hello):
                reply = replace(reply, out_dir=str(self.out_dir))
            if reply is not None:
                self._send_json(reply)
        except Exception as e:
            self._send_json(error_reply(e, msg.TYPE))

    # ---- the view's state as traits, and into the DataScene ------------------------------
    @contextlib.contextmanager
    def _from_view(self):
        self._pulling.on = True
        try:
            yield
        finally:
            self._pulling.on = False

    def _pull_soon(self):
        """`_pull` within `PULL_DELAY` (a drag's changes: one pull for many)."""
        with self._lock:
            if self._pull_timer is not None:
                return
            self._pull_timer = threading.Timer(PULL_DELAY, self._pull)
            self._pull_timer.daemon = True
            self._pull_timer.start()

    def sync(self) -> "ViewWidget":
        """The page's changes so far in the traits and the scene now."""
        self._pull()
        return self

    def _pull(self):
        """The view's camera, TF, mode, hybrid toggle and isosurfaces as the
        traits, and into the scene (nothing once the widget is closed)."""
        with self._lock:
            timer, self._pull_timer = self._pull_timer, None
        if timer is not None:                    # a pull due later (`_pull_soon`): this one serves it
            timer.cancel()
        view = self.view
        if view is None or view.closed or self.engine.loaded is None:
            return
        camera, spec, mode, iso = view.camera, view.spec, view.mode, (view.iso, view.iso_only)
        with self._from_view(), self.hold_sync():
            self.camera = camera_dict(camera)
            self.tf = spec.to_json()
            self.density_scale = float(spec.density)
            self.mode = mode
            self.hybrid = view.hybrid
            self.iso = list(iso[0])
            self.iso_only = iso[1]
        self._into_scene(camera, spec, mode, iso)

    def _into_scene(self, camera: OrbitCamera, spec, mode, iso=((), False)):
        """The view's state into the `DataScene` (``sc.render()`` renders it):
        the camera, the mode, the iso values (field units) and the medium's
        own table over stored units."""
        sc, loaded = self.scene, self.engine.loaded
        if loaded.plan is not None and loaded.plan.data is not sc.plan.data:    # the page chose another field
            sc.plan, sc.field = replace(loaded.plan, notes=list(loaded.plan.notes)), self.engine.field
        sc.origin, sc.target, sc.up, sc.fov = camera.origin, camera.target, camera.up, camera.fov
        sc.mode = mode
        key = replace(spec, density=0.0)         # the table does not hold the density scale
        if self._table[0] != key:
            table = loaded.table(spec)
            text = table.to_json()
            name = self._tf_dir / f"tf-{hashlib.sha1(text.encode()).hexdigest()[:16]}.json"
            if not name.exists():
                name.write_text(text)
            self._table = (key, (str(name), tuple(float(x) for x in table.domain)))
        sc.plan.transform = "log10" if loaded.stored_log else "none"
        (sc.tf, sc.tf_range), sc.density_scale = self._table[1], spec.density
        sc.iso = iso[0]                          # before iso_only, which needs values
        sc.iso_only = bool(iso[1] and iso[0])

    def _ready_view(self):
        self.wait()
        return self.view

    def _changed_from_python(self):
        """After a change set from Python: the traits normalised, the page told."""
        self._pull()
        self._describe(frame=False)

    def _apply_tf(self, view, value):
        """``value`` (a dict of editor fields, a preset or colormap name, a
        TF .json path) into ``view``; a `ValueError` names what is wrong."""
        if isinstance(value, dict):
            fields = {k: (list(v) if isinstance(v, tuple) else v) for k, v in value.items()}
            if "points" in fields:
                fields["points"] = [list(q) for q in fields["points"]]
            self.engine.change(view, p.parse_message(dict(fields, type="tf")))
        elif isinstance(value, (str, Path)) and str(value) in PRESET_POINTS:
            cmap, points = PRESET_POINTS[str(value)]
            self.engine.change(view, p.TFChange(points=tuple(tuple(q) for q in points), colormap=cmap))
        elif isinstance(value, (str, Path)) and str(value).endswith(".json"):
            self.engine.request(view, p.TFLoad(Path(value).read_text()))
        elif isinstance(value, str) and value in self.engine.loaded.colormaps:
            self.engine.change(view, p.TFChange(points=((0.0, 0.0), (1.0, 1.0)), colormap=value))
        else:
            raise ValueError(f"tf: a dict of the editor's fields, a preset ({', '.join(PRESET_POINTS)}), "
                             f"a colormap ({', '.join(self.engine.loaded.colormaps)}) or a .json file; "
                             f"got {value!r}")

    @traitlets.validate("tf")
    def _set_tf(self, proposal):
        if getattr(self._pulling, "on", False):
            return proposal.value
        view = self._ready_view()
        self._apply_tf(view, proposal.value)
        self._changed_from_python()
        return view.spec.to_json()

    @traitlets.validate("density_scale")
    def _set_density(self, proposal):
        if getattr(self._pulling, "on", False):
            return proposal.value
        view = self._ready_view()
        self.engine.change(view, p.TFChange(density=float(proposal.value)))
        self._changed_from_python()
        return float(view.spec.density)

    @traitlets.validate("mode")
    def _set_mode(self, proposal):
        if getattr(self._pulling, "on", False):
            return proposal.value
        view = self._ready_view()
        self.engine.change(view, p.parse_message({"type": "mode", "mode": proposal.value}))
        self._changed_from_python()
        return view.mode

    @traitlets.validate("hybrid")
    def _set_hybrid(self, proposal):
        if getattr(self._pulling, "on", False):
            return proposal.value
        view = self._ready_view()
        self.engine.change(view, p.HybridChange(bool(proposal.value)))
        self._changed_from_python()
        return view.hybrid

    @traitlets.validate("iso")
    def _set_iso(self, proposal):
        if getattr(self._pulling, "on", False):
            return proposal.value
        view = self._ready_view()
        self.engine.change(view, p.parse_message({"type": "iso", "values": list(proposal.value)}))
        self._changed_from_python()
        return list(view.iso)

    @traitlets.validate("iso_only")
    def _set_iso_only(self, proposal):
        if getattr(self._pulling, "on", False):
            return proposal.value
        view = self._ready_view()
        self.engine.change(view, p.IsoChange(only=bool(proposal.value)))
        self._changed_from_python()
        return view.iso_only

    @traitlets.validate("camera")
    def _set_camera(self, proposal):
        if getattr(self._pulling, "on", False):
            return proposal.value
        view = self._ready_view()
        value, now = proposal.value, camera_dict(view.camera)
        unknown = sorted(set(value) - set(now))
        if unknown:
            raise ValueError(f"camera: no field(s) {', '.join(unknown)} (fields: origin, target, up, fov)")
        new = dict(now, **value)
        try:
            vectors = {k: np.asarray(new[k], np.float64).reshape(3) for k in ("origin", "target", "up")}
            fov = float(new["fov"])
        except (TypeError, ValueError):
            raise ValueError("camera: origin, target and up are 3 numbers each, fov a number") from None
        if not all(np.isfinite(v).all() for v in vectors.values()) or not 0 < fov < 180:
            raise ValueError("camera: finite origin, target and up, fov in (0, 180) degrees")
        camera = OrbitCamera.looking(vectors["origin"], vectors["target"], world_up(vectors["up"]), fov,
                                     view.camera.floor)
        self.engine.place_camera(view, camera)
        self._changed_from_python()
        return camera_dict(view.camera)

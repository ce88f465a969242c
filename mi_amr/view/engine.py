"""The viewer's renderer: one scene, any number of views of it.

`ViewEngine` loads AMR data (a scene planned from the data alone,
`mi_amr.autoscene`) or an XML scene with an ``amr`` medium, then renders on
one thread, progressively: each view (a browser tab) has its own camera,
transfer function and accumulated image, and the thread serves the views in
turn, one pass of 1 spp at a time. Before a pass it puts the view's camera
and TF into the scene: the camera through ``mi.traverse``, the TF through
`set_transfer_function` (majorants recomputed, nothing recompiled); the
pass itself is a ``dr.freeze``-recorded ``mi.render``, replayed without
tracing. A change restarts the view's accumulation; a pass rendered for a
state that changed meanwhile is shown (the newest picture there is) but
accumulated into nothing; the first pass after a change is rendered at
``preview_scale`` of the resolution (quick feedback while a control is
dragged). With the denoiser (`mitsuba_oidn`) on, a view sees denoised
previews and denoised images of its accumulation at 1, 2, 4, 8, ... spp.

The loaded scene is one `LoadedScene` (``engine.loaded``); the engine takes
and gives `protocol` messages. Images reach a view through its
``send(header, jpeg_bytes)`` (header: a `protocol.Frame`), called from the
render thread; the server keeps only the newest unsent one (stale frames
are dropped, never queued).
"""

from __future__ import annotations

import io
import itertools
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .camera import OrbitCamera
from .protocol import (CameraChange, DenoiseChange, Frame, Hello, HistogramReply, Status, TFChange, ViewChange,
                       parse_message)
from .scene import LoadedScene, load_scene
from .snapshot import write_snapshot
from .tf_spec import TFSpec, colormap_stops

#: Samples per pixel after which a view stops refining.
DEFAULT_MAX_SPP = 1024
#: Held around every Dr.Jit call of a viewer (scene changes, frozen passes):
#: recording a frozen function while another thread traces or renders is
#: not safe. Code that renders in the same process while a viewer runs (a
#: notebook, a test) takes it too: ``with mi_amr.view.engine.JIT_LOCK: ...``.
JIT_LOCK = threading.RLock()

def denoiser():
    """``(denoise function or None, why not)``: Intel Open Image Denoise
    through ``mitsuba_oidn`` (the ``mi-amr[view]`` extra)."""
    try:
        import mitsuba_oidn
    except ImportError as e:
        return None, f"denoising needs mitsuba-oidn: pip install 'mi-amr[view]' ({e})"
    return (lambda img: np.asarray(mitsuba_oidn.denoise(np.ascontiguousarray(img, np.float32), hdr=True))), None


def encode_jpeg(image: np.ndarray, quality: int = 90) -> bytes:
    """A linear RGB image as the page shows it (sRGB, 8 bits, JPEG)."""
    from PIL import Image

    from ..images import srgb8
    buf = io.BytesIO()
    Image.fromarray(srgb8(image)).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


@dataclass
class View:
    """One viewer (a browser tab): its state and its accumulation."""
    id: int
    camera: OrbitCamera
    spec: TFSpec
    send: object                         # send(protocol.Frame header, jpeg bytes), thread-safe
    denoise: bool = True
    version: int = 0                     # bumped by every change
    accum: np.ndarray | None = None
    spp: int = 0
    accum_version: int = -1
    preview_version: int = -1
    denoised: np.ndarray | None = None   # the newest denoised image of the accumulation
    closed: bool = False


class ViewEngine:
    """Loads ``source`` (data path, yt data set or XML scene) on a thread of
    its own, then renders for the views (see the module docstring).

    ``res``: image width (the height follows the scene's film aspect);
    ``max_spp``: where each view stops refining; ``preview_scale``: the
    resolution of the first pass after a change (1: no preview)."""

    def __init__(self, source, field: str | None = None, *, res: int = 256, max_spp: int = DEFAULT_MAX_SPP,
                 preview_scale: float = 0.5, variant: str = "llvm_ad_rgb"):
        if not 16 <= res <= 4096:
            raise ValueError(f"res must lie in [16, 4096], got {res}")
        if not 0.1 <= preview_scale <= 1:
            raise ValueError(f"preview_scale must lie in [0.1, 1], got {preview_scale}")
        self.source, self.field, self.res, self.max_spp = source, field, int(res), int(max_spp)
        self.preview_scale, self.variant = float(preview_scale), variant
        self.status = Status("loading", "starting", 0, None)
        self.error: str | None = None
        self.ready = threading.Event()
        self.loaded: LoadedScene | None = None    # set on the render thread, dropped when it ends
        self._views: dict[int, View] = {}
        self._ids = itertools.count(1)
        self._wake = threading.Condition(threading.RLock())     # the views and their state
        self._stop = False
        self._listeners: list = []               # status(Status) callbacks
        self._failures = 0
        self._seeds = itertools.count()
        self._denoise, self.denoiser_missing = denoiser()
        self._thread = threading.Thread(target=self._run, name="mi-amr view", daemon=True)

    @property
    def colormaps(self) -> tuple:
        """The loaded scene's colormaps ("scene" first for an XML scene)."""
        return self.loaded.colormaps

    @property
    def initial_spec(self) -> TFSpec:
        """The TF a new view starts from."""
        return self.loaded.initial_spec

    # ---- Life cycle ----------------------------------------------------------
    def start(self) -> "ViewEngine":
        self._thread.start()
        return self

    def stop(self):
        """End the render thread, which lets go of the scene first."""
        with self._wake:
            self._stop = True
            self._wake.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=60)

    def _release(self):
        """On the render thread, before it ends: drop the loaded scene (its
        frozen recordings, every Dr.Jit variable of it) and collect it here.
        Freed later from another thread (after this one's Dr.Jit state is
        gone), they crashed a later render."""
        import gc
        with self._wake:
            self._views.clear()
        with JIT_LOCK:
            self.loaded = None
            gc.collect()
        try:
            import drjit as dr
            dr.sync_thread()
        except Exception:
            pass

    def on_status(self, callback):
        """``callback(Status)`` on load progress and when ready or failed;
        returns a function that stops it."""
        self._listeners.append(callback)
        return lambda: self._listeners.remove(callback) if callback in self._listeners else None

    def _set_status(self, **kw):
        self.status = replace(self.status, **kw)
        for fn in list(self._listeners):
            fn(self.status)

    # ---- Loading ---------------------------------------------------------------
    def _load(self):
        from .._llvm import ensure_llvm_path
        ensure_llvm_path()
        import mitsuba as mi
        if mi.variant() != self.variant:
            mi.set_variant(self.variant)
        from ..progress import listen

        last = [0.0]

        def heard(desc, done, total):
            now = time.perf_counter()
            if done is None or now - last[0] > 0.1:
                last[0] = now
                self._set_status(desc=desc, done=done or 0, total=total)
        stop_listening = listen(heard)
        try:
            with JIT_LOCK:
                self.loaded = load_scene(self.source, self.field, self.res, lambda desc: self._set_status(desc=desc))
        finally:
            stop_listening()

    # ---- Views -------------------------------------------------------------------
    def open_view(self, send) -> View:
        """A new view with the scene's initial camera and TF."""
        if not self.ready.is_set():
            raise RuntimeError("the data are still loading")
        with self._wake:
            v = View(next(self._ids), self.loaded.initial_camera, self.loaded.initial_spec, send,
                     denoise=self._denoise is not None)
            self._views[v.id] = v
            self._wake.notify_all()
            return v

    def close_view(self, view: View):
        with self._wake:
            view.closed = True
            self._views.pop(view.id, None)

    def describe(self, view: View) -> Hello:
        """What a page needs to draw its controls."""
        s = self.loaded
        return Hello(view.id, view.camera, view.spec, tuple(s.colormaps), s.log_available, self._denoise is not None,
                     self.denoiser_missing, view.denoise, tuple(s.size), self.max_spp, s.description,
                     colormap_stops(s.colormaps, s.scene_rgb))

    def change(self, view: View, change: ViewChange | dict) -> bool:
        """Apply a camera, TF or denoise change to ``view`` (a page message
        as a dict is parsed first; a `ValueError` names what is wrong, and
        the view is then unchanged). Returns whether the histogram's range
        or units changed."""
        if isinstance(change, dict):
            change = parse_message(change)
        with self._wake:
            before = view.spec
            match change:
                case CameraChange():
                    view.camera = view.camera.moved(change)
                case TFChange():
                    view.spec = view.spec.changed(change, self.loaded.log_available, self.loaded.colormaps)
                case DenoiseChange(on=on):
                    if on and self._denoise is None:
                        raise ValueError(self.denoiser_missing)
                    view.denoise = on                  # the version bump below restarts the view
                case _:
                    raise ValueError(f"not a view change: {type(change).__name__}")
            view.version += 1
            self._wake.notify_all()
            return (before.range, before.log) != (view.spec.range, view.spec.log)

    def histogram(self, view: View) -> HistogramReply:
        """The volume-weighted histogram under the view's TF editor."""
        spec = view.spec
        return HistogramReply(tuple(self.loaded.shares(spec)), tuple(spec.range), spec.log)

    # ---- Rendering ---------------------------------------------------------------
    def _run(self):
        try:
            self._load()
        except BaseException as e:                   # shown in the page, and by the CLI
            self.error = f"{type(e).__name__}: {e}" if not isinstance(e, (ValueError, OSError)) else str(e)
            self._set_status(state="error", desc=self.error)
            self.ready.set()
            self._release()
            return
        self._set_status(state="ready", desc="ready")
        self.ready.set()
        turn = 0
        while True:
            with self._wake:
                stopping = self._stop
            if stopping:
                self._release()
                return
            with self._wake:
                views = [v for v in self._views.values() if self._needs_work(v)]
                if not views:
                    self._wake.wait(0.25)
                    continue
                turn += 1
                view = views[turn % len(views)]
                version, camera, spec = view.version, view.camera, view.spec
                preview = self.preview_scale < 1 and view.preview_version != version \
                    and view.accum_version != version
            self._pass(view, version, camera, spec, preview)

    def _needs_work(self, v: View) -> bool:
        return v.accum_version != v.version or v.spp < self.max_spp

    def _pass(self, view: View, version: int, camera, spec, preview: bool):
        full = self.loaded.size
        size = [max(8, int(full[0] * self.preview_scale)), max(8, int(full[1] * self.preview_scale))] \
            if preview else list(full)
        t0 = time.perf_counter()
        try:
            with JIT_LOCK:
                self.loaded.apply(camera, spec, size)
                image = self.loaded.render(next(self._seeds), size)
        except Exception as e:                       # say it, forget the recording, go on
            import sys
            print(f"mi-amr view: a pass failed ({type(e).__name__}: {str(e).splitlines()[0]}); "
                  "rendering again", file=sys.stderr)
            self._failures += 1
            with JIT_LOCK:
                self.loaded.forget(size)
            if self._failures >= 3:
                self._set_status(state="error", desc=f"rendering fails: {e}")
                with self._wake:
                    self._stop = True
            return
        self._failures = 0
        render_ms = 1e3 * (time.perf_counter() - t0)
        with self._wake:
            if view.closed:
                return
            if view.version != version:
                # the view changed while this pass ran (a drag): show it, as the
                # newest picture there is, but accumulate nothing into it
                preview, shown, spp, denoised = True, image, 1, False
            elif preview:
                view.preview_version = version
                shown, spp = image, 1
                denoised = view.denoise and self._denoise is not None          # clean while dragging, too
            else:
                if view.accum_version != version:
                    view.accum, view.spp, view.accum_version, view.denoised = image.astype(np.float64), 1, version, None
                else:
                    view.accum += image
                    view.spp += 1
                spp = view.spp
                shown = view.accum / spp
                denoised = view.denoise and self._denoise is not None
                if denoised and not (spp & (spp - 1) == 0 or spp == self.max_spp):   # at 1, 2, 4, 8, ... spp
                    shown = None                         # keep the last denoised image on screen
            send = view.send
        if shown is not None and denoised:               # outside the lock: the page's changes go on
            shown = self._denoise(shown)
            if not preview:
                with self._wake:
                    if view.accum_version == version and view.spp == spp:
                        view.denoised = shown
        if shown is not None:
            header = Frame(version, spp, bool(denoised), bool(preview), size[0], size[1], round(render_ms, 1),
                           self.max_spp)
            send(header, encode_jpeg(shown))

    # ---- Snapshots -----------------------------------------------------------------
    def snapshot(self, view: View, out_dir, name: str) -> list[Path]:
        """The view's files (`snapshot.write_snapshot`): ``NAME.exr``,
        ``.png``, ``.xml``, ``.tf.json`` in ``out_dir``; ``name`` must be a
        plain file name. A `ValueError` before the first full frame."""
        with self._wake:
            if view.accum is None or view.accum_version != view.version:
                raise ValueError("no image yet: wait for the first full frame")
            image = (view.accum / view.spp).astype(np.float32)
            shown = view.denoised if view.denoise and view.denoised is not None else image
            camera, spec, spp = view.camera, view.spec, view.spp
        return write_snapshot(self.loaded, out_dir, name, image, shown, camera, spec, spp)

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
previews and denoised images of its accumulation at 1, 2, 4, 8, 16 spp,
then about each second (`DENOISE_INTERVAL`) and at ``max_spp``; between
them each pass re-sends the last denoised image with the real spp count.
Switching the denoiser keeps the accumulation.

A change that cannot render never reaches the render thread (`change`
refuses it with a `ValueError`); a pass that fails all the same is
reported to its view alone (``notify``), which goes back to the last state
that rendered. The render thread survives any pass; a failed load is the
only fatal error (``error``, one line).

The loaded scene is one `LoadedScene` (``engine.loaded``); the engine takes
and gives `protocol` messages. Images reach a view through its
``send(header, jpeg_bytes)`` (header: a `protocol.Frame`), called from the
render thread; the server keeps only the newest unsent one (stale frames
are dropped, never queued).
"""

from __future__ import annotations

import gc
import io
import itertools
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .._llvm import ensure_llvm_path
from ..images import srgb8
from ..params import plugin_error
from ..progress import listen
from .camera import FLOOR_MARGIN, MAX_ELEVATION, OrbitCamera
from .protocol import (CameraChange, DenoiseChange, Error, Frame, Hello, HistogramReply, Status, TFChange, ViewChange,
                       parse_message)
from .protocol import Describe, EditorRequest, FieldChange, TFFile, TFLoad, TFSave
from .scene import LoadedScene, load_scene
from .snapshot import Snapshot, SnapshotBudget, write_snapshot
from .tf_spec import PRESET_POINTS, TFSpec, colormap_stops

#: Samples per pixel after which a view stops refining.
DEFAULT_MAX_SPP = 1024
#: With the denoiser on, a new denoised image of the accumulation at least this often (seconds).
DENOISE_INTERVAL = 1.0
#: Passes of one state that may fail in a row before its view stops rendering (until it changes).
MAX_FAILURES = 3
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


def one_line(e: BaseException) -> str:
    """An exception as one line for a person: its message's first line
    (Mitsuba's plugin failures without their traceback), its type named
    unless it is a ValueError, OSError or RuntimeError."""
    text = str(e).strip()
    if "failed to instantiate" in text:
        text = plugin_error(text)
    first = text.splitlines()[0] if text else ""
    return first if isinstance(e, (ValueError, OSError, RuntimeError)) and first else f"{type(e).__name__}: {first}"


def encode_jpeg(image: np.ndarray, quality: int = 90) -> bytes:
    """A linear RGB image as the page shows it (sRGB, 8 bits, JPEG)."""
    from PIL import Image  # lazy: the mi-amr[view] extra (JPEG frames)
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
    notify: object = None                # notify(protocol message) to the view's page, thread-safe
    denoise: bool = True
    version: int = 0                     # bumped by every change message (the page counts them too)
    epoch: int = 0                       # bumped by every change of the picture: the accumulation restarts
    accum: np.ndarray | None = None
    spp: int = 0
    accum_epoch: int = -1
    preview_epoch: int = -1
    denoised: np.ndarray | None = None   # the newest denoised image of the accumulation,
    denoised_spp: int = 0                # ... of this many samples,
    denoised_jpeg: bytes = b""           # ... as the page got it,
    denoised_at: float = -1e9            # ... made then (time.monotonic)
    redisplay: bool = False              # show the accumulation again (the denoiser was switched)
    good: tuple | None = None            # the last (camera, spec) that rendered
    failures: int = 0                    # passes of the view's state failed in a row
    broken: str | None = None            # why its state does not render (nothing to go back to)
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
        if not 1 <= max_spp <= 1_000_000:
            raise ValueError(f"max_spp must lie in [1, 1000000], got {max_spp}")
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
        self._field_requests: list = []          # (name, done Event, result dict): for the render thread
        self._seeds = itertools.count()
        self._denoise, self.denoiser_missing = denoiser()
        self._denoise_lock = threading.Lock()    # one denoise at a time (render thread, snapshots)
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
        with self._wake:
            self._views.clear()
        with JIT_LOCK:
            self.loaded = None
            gc.collect()
        try:
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
        ensure_llvm_path()
        if mi.variant() != self.variant:
            mi.set_variant(self.variant)

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
    def open_view(self, send, notify=None) -> View:
        """A new view with the scene's initial camera and TF; ``send(header,
        jpeg)`` gets its frames, ``notify(message)`` the render thread's
        errors for it."""
        if not self.ready.is_set():
            raise RuntimeError("the data are still loading")
        with self._wake:
            v = View(next(self._ids), self.loaded.initial_camera, self.loaded.initial_spec, send, notify,
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
                     colormap_stops(s.colormaps, s.scene_rgb), editor=self._editor_extras())

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
                    camera = view.camera.moved(change)
                    check_camera(camera)
                    view.camera = camera
                case TFChange():
                    spec = view.spec.changed(change, self.loaded.log_available, self.loaded.colormaps)
                    self.loaded.check(spec)            # one that cannot render is refused here
                    view.spec = spec
                case DenoiseChange(on=on):
                    if on and self._denoise is None:
                        raise ValueError(self.denoiser_missing)
                    view.denoise = on                  # the accumulation stays: shown again
                    view.version += 1
                    view.redisplay = view.accum_epoch == view.epoch
                    self._wake.notify_all()
                    return False
                case _:
                    raise ValueError(f"not a view change: {type(change).__name__}")
            view.version += 1
            view.epoch += 1
            view.broken = None
            self._wake.notify_all()
            return (before.range, before.log) != (view.spec.range, view.spec.log)

    # ---- The TF editor's requests ------------------------------------------------------
    def _editor_extras(self) -> dict:
        """Hello's ``editor``: the fields to choose from (or why none), the
        values' units, why log10 is off, the presets, the start camera and
        the camera's clamps (the page orbits as `OrbitCamera.moved` does)."""
        s = self.loaded
        current = s.field
        if s.fields and current is not None:
            current = next((f for f in s.fields if f == current or f.split(",")[-1] == current), current)
        presets = {k: {"colormap": c, "points": [list(q) for q in pts]} for k, (c, pts) in PRESET_POINTS.items()}
        return {"fields": list(s.fields), "field": current, "field_note": s.field_note, "units": s.units,
                "log_note": s.log_note, "presets": presets, "home": s.initial_camera.to_json(),
                "max_elevation": MAX_ELEVATION, "floor_margin": FLOOR_MARGIN}

    def request(self, view: View, msg: EditorRequest):
        """Answer a TF-editor request (`protocol.EditorRequest`): the TF as a
        file (`TFFile`), a TF file loaded into the view (a new `Hello`),
        another field (`switch_field`; None), a new `Hello`. A `ValueError`
        says what is wrong; the view is then unchanged."""
        match msg:
            case TFSave():
                return TFFile(view.spec.file_json(self.loaded.scene_rgb))
            case TFLoad(text=text):
                with self._wake:
                    spec = view.spec.from_file(text, self.loaded.log_available, self.loaded.colormaps)
                    if hasattr(self.loaded, "check"):
                        self.loaded.check(spec)
                    view.spec = spec
                    view.version += 1
                    view.epoch += 1
                    self._wake.notify_all()
                return self.describe(view)
            case FieldChange(name=name):
                self.switch_field(name)
                return None
            case Describe():
                return self.describe(view)
        raise ValueError(f"not an editor request: {type(msg).__name__}")

    def switch_field(self, name: str, timeout: float = 600.0):
        """Render the field ``name`` of the same data (one of
        ``loaded.fields``) in every view, each keeping its camera; loaded on
        the render thread between passes, then every view's page gets a new
        `Hello` (its ``notify``). A failure is a `ValueError` to the caller
        and changes nothing."""
        s = self.loaded
        if not s.fields:
            raise ValueError(f"field: {s.field_note}")
        if name not in s.fields:
            raise ValueError(f"field: one of {', '.join(s.fields)}")
        done, result = threading.Event(), {}
        with self._wake:
            self._field_requests.append((name, done, result))
            self._wake.notify_all()
        if not done.wait(timeout):
            raise ValueError(f"field {name}: not loaded within {timeout:g} s")
        if "error" in result:
            raise ValueError(result["error"])

    def _serve_field_requests(self):
        """On the render thread: load the fields asked for (`switch_field`)."""
        with self._wake:
            requests, self._field_requests = self._field_requests, []
        for name, done, result in requests:
            try:
                with JIT_LOCK:
                    new = load_scene(self.source, name, self.res, lambda desc: self._set_status(desc=desc))
            except Exception as e:                   # the last good scene stays
                result["error"] = f"field {name}: {one_line(e)}"
                done.set()
                continue
            with self._wake:
                old, self.loaded, self.field = self.loaded, new, name
                views = list(self._views.values())
                for v in views:
                    v.spec, v.epoch = new.initial_spec, v.epoch + 1      # version: the page's count
                self._wake.notify_all()
            with JIT_LOCK:
                del old                          # its Dr.Jit objects go on this thread
                gc.collect()
            self._set_status(desc=f"field {name}")
            for v in views:
                if v.notify is not None:
                    v.notify(self.describe(v))
            done.set()

    def histogram(self, view: View) -> HistogramReply:
        """The volume-weighted histogram under the view's TF editor."""
        spec = view.spec
        below, above = self.loaded.outside(spec)
        return HistogramReply(tuple(self.loaded.shares(spec)), tuple(spec.range), spec.log, below, above)

    # ---- Rendering ---------------------------------------------------------------
    def _run(self):
        try:
            self._load()
        except BaseException as e:                   # shown in the page, and by the CLI
            self.error = one_line(e)
            self._set_status(state="error", desc=self.error)
            self.ready.set()
            self._release()
            return
        self._set_status(state="ready", desc="ready")
        self.ready.set()
        turn = 0
        while True:
            self._serve_field_requests()
            with self._wake:
                if self._stop:
                    break
                views = [v for v in self._views.values() if self._needs_work(v)]
                if not views:
                    self._wake.wait(0.25)
                    continue
                turn += 1
                view = views[turn % len(views)]
                epoch, camera, spec, redisplay = view.epoch, view.camera, view.spec, view.redisplay
                preview = self.preview_scale < 1 and view.preview_epoch != epoch and view.accum_epoch != epoch
            try:
                if redisplay:
                    self._redisplay(view)
                else:
                    self._pass(view, epoch, camera, spec, preview)
            except Exception as e:                   # this view's trouble, nobody else's
                self._failed(view, epoch, camera, spec, e)
        self._release()

    def _needs_work(self, v: View) -> bool:
        if v.broken:
            return False
        return v.redisplay or v.accum_epoch != v.epoch or v.spp < self.max_spp

    def _denoise_due(self, view: View, spp: int) -> bool:
        """Denoise the accumulation now: at 1, 2, 4, 8, 16 spp, then each
        `DENOISE_INTERVAL`, and at ``max_spp``."""
        return spp >= self.max_spp or (spp <= 16 and spp & (spp - 1) == 0) \
            or time.monotonic() - view.denoised_at >= DENOISE_INTERVAL

    def _denoised(self, image: np.ndarray) -> np.ndarray:
        with self._denoise_lock:
            return self._denoise(image)

    def _pass(self, view: View, epoch: int, camera, spec, preview: bool):
        full = self.loaded.size
        size = [max(8, int(full[0] * self.preview_scale)), max(8, int(full[1] * self.preview_scale))] \
            if preview else list(full)
        t0 = time.perf_counter()
        with JIT_LOCK:
            try:
                self.loaded.apply(camera, spec, size)
                image = self.loaded.render(next(self._seeds), size)
            except Exception:
                self.loaded.forget(size)             # its recording and what the scene holds
                raise
        render_ms = round(1e3 * (time.perf_counter() - t0), 1)
        with self._wake:
            if view.closed:
                return
            view.good, view.failures = (camera, spec), 0
            stale = view.epoch != epoch
            if stale:
                # the view changed while this pass ran (a drag): show it, as the
                # newest picture there is, but accumulate nothing into it
                preview, shown, spp, denoise = True, image, 1, False
            elif preview:
                view.preview_epoch = epoch
                shown, spp = image, 1
                denoise = view.denoise and self._denoise is not None          # clean while dragging, too
            else:
                if view.accum_epoch != epoch:
                    view.accum, view.spp, view.accum_epoch = image.astype(np.float64), 1, epoch
                    view.denoised, view.denoised_spp, view.denoised_jpeg = None, 0, b""
                else:
                    view.accum += image
                    view.spp += 1
                spp = view.spp
                shown = view.accum / spp
                denoise = view.denoise and self._denoise is not None
                if denoise and not self._denoise_due(view, spp):
                    shown = None                     # the last denoised image, with the real count
            version, send, old = view.version, view.send, (view.denoised_spp, view.denoised_jpeg)
        if shown is None:
            if old[1]:
                send(Frame(version, spp, True, False, size[0], size[1], render_ms, self.max_spp, old[0]), old[1])
            return
        if denoise:                                  # outside the lock: the page's changes go on
            shown = self._denoised(shown)
        jpeg = encode_jpeg(shown)
        if denoise and not preview:
            with self._wake:
                if view.accum_epoch == epoch and view.spp == spp:
                    view.denoised, view.denoised_spp, view.denoised_jpeg = shown, spp, jpeg
                    view.denoised_at = time.monotonic()
        send(Frame(version, spp, bool(denoise), bool(preview), size[0], size[1], render_ms, self.max_spp), jpeg)

    def _redisplay(self, view: View):
        """The accumulation shown again, denoised or not (the denoiser was switched)."""
        with self._wake:
            view.redisplay = False
            if view.accum_epoch != view.epoch or view.accum is None:
                return
            epoch, spp, version, send = view.epoch, view.spp, view.version, view.send
            mean = view.accum / spp
            denoise = view.denoise and self._denoise is not None
            have = view.denoised if denoise and view.denoised_spp == spp else None
        shown = have if have is not None else self._denoised(mean) if denoise else mean
        jpeg = encode_jpeg(shown)
        if denoise and have is None:
            with self._wake:
                if view.accum_epoch == epoch and view.spp == spp:
                    view.denoised, view.denoised_spp, view.denoised_jpeg = shown, spp, jpeg
                    view.denoised_at = time.monotonic()
        h, w = mean.shape[:2]
        send(Frame(version, spp, bool(denoise), False, w, h, 0.0, self.max_spp), jpeg)

    def _failed(self, view: View, epoch: int, camera, spec, e: Exception):
        """A pass of ``view`` failed: back to its last state that rendered,
        or after `MAX_FAILURES` in a row of that one, stop rendering it
        until it changes; its page is told, no other."""
        why = one_line(e)
        reply = None
        with self._wake:
            if view.closed:
                return
            view.failures += 1
            if view.epoch != epoch:                  # changed meanwhile: the newer state is tried next
                return
            if view.good is not None and view.good != (camera, spec):
                view.camera, view.spec = view.good
                view.epoch += 1
                view.failures = 0
                reply = Error(f"this view could not be rendered ({why}); back to its last picture", "render",
                              camera=view.camera, tf=view.spec)
            elif view.failures >= MAX_FAILURES:
                view.broken = why
                reply = Error(f"rendering this view fails ({why}); change it to try again", "render")
            notify = view.notify
        if reply is not None and notify is not None:
            notify(reply)

    # ---- Snapshots -----------------------------------------------------------------
    def take_snapshot(self, view: View, out_dir, name: str, budget: SnapshotBudget | None = None) -> Snapshot:
        """The view's files (`snapshot.write_snapshot`): ``NAME.exr``,
        ``.png``, ``.xml``, ``.tf.json`` in ``out_dir`` (a numbered name when
        one is taken), the PNG and EXR from the same samples; ``name`` must
        be a plain file name. A `ValueError` before the first full frame,
        or beyond ``budget``."""
        with self._wake:
            if view.accum is None or view.accum_epoch != view.epoch:
                raise ValueError("no image yet: wait for the first full frame")
            image = (view.accum / view.spp).astype(np.float32)
            camera, spec, spp = view.camera, view.spec, view.spp
            denoise = view.denoise and self._denoise is not None
            shown = view.denoised if denoise and view.denoised_spp == spp else None
        if shown is None:
            shown = self._denoised(image) if denoise else image
        return write_snapshot(self.loaded, out_dir, name, image, shown, camera, spec, spp, budget)

    def snapshot(self, view: View, out_dir, name: str) -> list[Path]:
        """`take_snapshot`'s four files: [exr, png, xml, tf.json]."""
        return self.take_snapshot(view, out_dir, name).files[:4]


def check_camera(camera: OrbitCamera):
    """A `ValueError` when ``camera`` cannot render (a position float32 cannot hold)."""
    with np.errstate(over="ignore", invalid="ignore"):
        where = np.asarray(camera.origin, np.float64).astype(np.float32)
    if not np.isfinite(where).all():
        raise ValueError("camera: too far away to render (its position overflows float32)")

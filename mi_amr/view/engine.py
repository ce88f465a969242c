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
accumulated into nothing.

Lighting modes (``amrvolpath``'s ``mode``, docs/design.md section 6d): each
view refines in its own mode (``mode``, default the scene's), while a
camera or TF change is answered by a *fast* pass: `FAST_MODE`
(emission_absorption), 1 spp at ``preview_scale`` of the resolution, shown
raw. Once no camera or TF change has come for `SETTLE` seconds the view's
mode takes over: one pass at the fast passes' size (denoised where the
denoiser is on), then full-size passes that accumulate. The fast
passes keep to `FAST_BUDGET`: while their running mean takes longer, they
render at the next smaller size of `FAST_LADDER` (down to half of the
preview size), and at a larger one again once it fits. Every pass kind is a
frozen recording of the one scene (`LoadedScene.render`); the ones a view
needs are recorded ahead while no view waits for a picture (`_warm_up`):
a page's first picture, and a drag's switch of size, replay instead of
tracing.

With the denoiser (`mitsuba_oidn`) on, a view sees denoised previews of
its mode and denoised images of its accumulation at 1, 2, 4, 8, 16 spp,
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
import math
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..images import srgb8
from ..params import plugin_error
from ..plugins.integrator import MODES
from ..progress import listen
from .camera import FLOOR_MARGIN, MAX_ELEVATION, OrbitCamera
from .protocol import (CameraChange, DenoiseChange, Error, Frame, Hello, HistogramReply, ModeChange, Status, TFChange,
                       ViewChange, parse_message)
from .protocol import Describe, EditorRequest, FieldChange, TFFile, TFLoad, TFSave
from .protocol import AnnotateChange, AnnotationsRequest, ClipChange, SliceRequest
from .view_annotations import annotations_reply, burnt_in, slice_reply
from .scene import LoadedScene, load_scene
from .snapshot import Snapshot, SnapshotBudget, write_snapshot
from .tf_spec import PRESET_POINTS, TFSpec, colormap_stops

#: Samples per pixel after which a view stops refining.
DEFAULT_MAX_SPP = 1024
#: With the denoiser on, a new denoised image of the accumulation at least this often (seconds).
DENOISE_INTERVAL = 1.0
#: Passes of one state that may fail in a row before its view stops rendering (until it changes).
MAX_FAILURES = 3
#: The lighting mode of the passes that answer a camera or TF change (drag frames).
FAST_MODE = "emission_absorption"
#: Seconds without a camera or TF change after which a view's own mode refines.
SETTLE = 0.1
#: The fast passes' film sizes, as shares of ``preview_scale`` of the resolution.
FAST_LADDER = (1.0, 0.75, 0.5)
#: Seconds a fast pass may take (a running mean): beyond, the next smaller
#: size of `FAST_LADDER` is used; a larger one once it would fit in 3/4 of it.
FAST_BUDGET = 0.03
#: Held around every Dr.Jit call of a viewer (scene changes, frozen passes):
#: recording a frozen function while another thread traces or renders is
#: not safe. Code that renders in the same process while a viewer runs (a
#: notebook, a test) takes it too: ``with mi_amr.view.engine.JIT_LOCK: ...``.
JIT_LOCK = threading.RLock()
#: Seconds a snapshot asked for during a field reload waits for the new field's first full frame.
SNAPSHOT_WAIT = 120.0

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
    mode: str | None = None              # the lighting mode it refines in (None: the scene's integrator)
    version: int = 0                     # bumped by every change message (the page counts them too)
    changed_at: float = -1e9             # the last camera or TF change (time.monotonic)
    fast_epoch: int = -1                 # the epoch a fast pass was shown for
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
    replanned: bool = False              # the spec's range and density were planned again (log10 toggle)
    clip: tuple | None = None            # (normal, offset) world: the medium kept where normal . x <= offset
    annotate: AnnotateChange | None = None   # what the page draws over the picture (a snapshot's PNG too)


class ViewEngine:
    """Loads ``source`` (data path, yt data set or XML scene) on a thread of
    its own, then renders for the views (see the module docstring).

    ``res``: image width (the height follows the scene's film aspect);
    ``max_spp``: where each view stops refining; ``preview_scale``: the
    resolution of the fast passes and of the first pass in a view's mode
    after a change (1: full size); ``mode``: the lighting mode views start
    in (None: the scene's integrator's own; a mode needs ``amrvolpath``);
    ``fast_ladder``: the fast passes' sizes as shares of the preview size,
    largest first (`FAST_LADDER`); ``plan``: the `ScenePlan` of data
    ``source`` made already (a notebook's `DataScene`), else planned at load."""

    def __init__(self, source, field: str | None = None, *, res: int = 256, max_spp: int = DEFAULT_MAX_SPP,
                 preview_scale: float = 0.5, variant: str = "llvm_ad_rgb", mode: str | None = None,
                 fast_ladder=FAST_LADDER, embed_data: bool = False, plan=None):
        if not 16 <= res <= 4096:
            raise ValueError(f"res must lie in [16, 4096], got {res}")
        if not 1 <= max_spp <= 1_000_000:
            raise ValueError(f"max_spp must lie in [1, 1000000], got {max_spp}")
        if not 0.1 <= preview_scale <= 1:
            raise ValueError(f"preview_scale must lie in [0.1, 1], got {preview_scale}")
        if mode is not None and mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        self.mode = mode                         # after the load: the scene's when None
        if not fast_ladder or any(not 0 < f <= 1 for f in fast_ladder) or list(fast_ladder) != sorted(fast_ladder,
                                                                                                      reverse=True):
            raise ValueError(f"fast_ladder: shares in (0, 1], largest first, got {fast_ladder!r}")
        self.fast_ladder = tuple(float(f) for f in fast_ladder)
        self.source, self.field, self.res, self.max_spp = source, field, int(res), int(max_spp)
        self.preview_scale, self.variant = float(preview_scale), variant
        self.embed_data = bool(embed_data)       # snapshots of yt data: copy them (else name them)
        self._plan = plan
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
        self._warm = []                          # (size, mode) recorded ahead (`_warm_up`)
        self._expected = 0                       # pages waiting for the load to open a view (`expect_view`)
        self._fast_level = 0                     # the fast passes' size: FAST_LADDER[level]
        self._fast_ms = {}                       # film size -> running mean of its fast passes (s)
        self._reloads = 0                        # field switches asked for and not done (snapshots wait)

    @property
    def colormaps(self) -> tuple:
        """The loaded scene's colormaps ("scene" first for an XML scene)."""
        return self.loaded.colormaps

    @property
    def warming(self) -> bool:
        """Whether passes are still to be recorded ahead (`_warm_up`)."""
        return bool(self._warm)

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
                self.loaded = load_scene(self.source, self.field, self.res, lambda desc: self._set_status(desc=desc),
                                         plan=self._plan)
        finally:
            stop_listening()
        if self.mode is not None and self.mode not in self.loaded.modes:
            raise ValueError(f"--mode {self.mode}: {self.loaded.mode_note}")
        self.mode = self.mode or self.loaded.scene_mode
        self._warm = self._warm_list()
        encode_jpeg(np.zeros((8, 8, 3), np.float32))  # the JPEG encoder loaded now, not at the first frame

    # ---- Views -------------------------------------------------------------------
    def open_view(self, send, notify=None) -> View:
        """A new view with the scene's initial camera and TF; ``send(header,
        jpeg)`` gets its frames, ``notify(message)`` the render thread's
        errors for it."""
        if not self.ready.is_set():
            raise RuntimeError("the data are still loading")
        with self._wake:
            v = View(next(self._ids), self.loaded.initial_camera, self.loaded.initial_spec, send, notify,
                     denoise=self._denoise is not None, mode=self.mode)
            self._views[v.id] = v
            self._wake.notify_all()
            return v

    def expect_view(self):
        """A page waits for the load to open a view: until the returned
        function is called (once it opened it, or left), nothing is
        recorded ahead, so that its first pass does not wait behind a
        recording (it records what it needs itself)."""
        with self._wake:
            self._expected += 1
        done = []

        def release():
            with self._wake:
                if not done:
                    done.append(True)
                    self._expected -= 1
                    self._wake.notify_all()
        return release

    def close_view(self, view: View):
        with self._wake:
            view.closed = True
            self._views.pop(view.id, None)

    def describe(self, view: View) -> Hello:
        """What a page needs to draw its controls."""
        s = self.loaded
        return Hello(view.id, view.camera, view.spec, tuple(s.colormaps), s.log_available, self._denoise is not None,
                     self.denoiser_missing, view.denoise, tuple(s.size), self.max_spp, s.description,
                     colormap_stops(s.colormaps, s.scene_rgb), editor=self._editor_extras(),
                     modes=s.modes or None, mode=view.mode, fast_mode=self._fast_mode(),
                     mode_note=s.mode_note or None)

    def place_camera(self, view: View, camera: OrbitCamera):
        """Put ``camera`` into ``view`` as it is (its field of view too: a
        camera set from Python, `widget`); a `ValueError` when it cannot
        render, and the view is then unchanged."""
        check_camera(camera)
        with self._wake:
            view.camera = camera
            view.epoch += 1
            view.changed_at = time.monotonic()
            view.broken = None
            self._wake.notify_all()

    def change(self, view: View, change: ViewChange | dict) -> bool:
        """Apply a camera, TF, denoise or mode change to ``view`` (a page
        message as a dict is parsed first; a `ValueError` names what is
        wrong, and the view is then unchanged). Returns whether the
        histogram's range or units changed."""
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
                    replan = spec.log != before.log and change.density in (None, before.density)
                    if replan:                         # the log10 toggle: range and density planned again
                        spec = self.loaded.replanned(spec)
                    self.loaded.check(spec)            # one that cannot render is refused here
                    view.spec = spec
                    view.replanned = replan or view.replanned
                case DenoiseChange(on=on):
                    if on and self._denoise is None:
                        raise ValueError(self.denoiser_missing)
                    view.denoise = on                  # the accumulation stays: shown again
                    view.version += 1
                    view.redisplay = view.accum_epoch == view.epoch
                    self._wake.notify_all()
                    return False
                case ModeChange(mode=mode):
                    if mode not in self.loaded.modes:
                        raise ValueError(f"mode: {self.loaded.mode_note or 'one of ' + ', '.join(self.loaded.modes)}")
                    view.mode = mode
                    view.version += 1
                    view.epoch += 1
                    view.fast_epoch = view.epoch         # the picture did not move: no fast pass
                    for size in self._ladder() if mode != self._fast_mode() else ():   # its previews, ahead
                        if (size, mode) not in self._warm and not self.loaded.recorded(size, mode):
                            self._warm.append((size, mode))
                    view.broken = None
                    self._wake.notify_all()
                    return False
                case _:
                    raise ValueError(f"not a view change: {type(change).__name__}")
            view.version += 1
            view.epoch += 1
            view.changed_at = time.monotonic()
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
        if s.fields and current is not None:       # as the user named it: density -> enzo,Density
            named = current.lower()
            current = next((f for f in s.fields if f.lower() == named), None) or \
                next((f for f in s.fields if f.split(",")[-1].lower() == named.split(",")[-1]), current)
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
            case ClipChange(normal=normal, offset=offset):
                self.set_clip(view, None if normal is None else (normal, offset))
                return None
            case AnnotateChange():
                view.annotate = msg
                return None
            case AnnotationsRequest():
                with JIT_LOCK:
                    loaded = self.loaded
                return annotations_reply(loaded)           # the page draws the legend from its TF
            case SliceRequest():
                with JIT_LOCK:
                    loaded = self.loaded
                return slice_reply(loaded, msg, loaded.table(view.spec), loaded.stored_log)
        raise ValueError(f"not an editor request: {type(msg).__name__}")

    # ---- The clip plane ----------------------------------------------------------------
    def set_clip(self, view: View, clip):
        """Keep the medium where ``normal . x <= offset`` (``clip`` = (normal,
        offset), world units; None: all of it) in ``view``'s pictures: put
        into the medium before each of its passes, as its camera and TF
        (`AMRMedium.set_clip_plane`: opaque, nothing recompiles). A bad
        plane is a `ValueError`; the view is then unchanged."""
        if clip is not None:
            n = np.asarray(clip[0], np.float64).reshape(3)
            if not (np.isfinite(n).all() and np.any(n) and np.isfinite(float(clip[1]))):
                raise ValueError(f"clip: a nonzero finite normal and a finite offset, got {clip}")
            clip = (tuple(float(x) for x in n), float(clip[1]))
        with self._wake:
            view.version += 1                    # a change message: the page counts it
            if clip == view.clip:
                return
            view.clip = clip
            view.epoch += 1
            view.changed_at = time.monotonic()
            view.broken = None
            self._wake.notify_all()

    def _put_clip(self, clip):
        """The view's clip plane into the medium, when another is there (under `JIT_LOCK`)."""
        if "clip" not in self.loaded.applied or self.loaded.applied["clip"] != clip:
            self.loaded.medium.set_clip_plane(*(clip or (None,)))
            self.loaded.applied["clip"] = clip

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
            self._reloads += 1
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
                self._reload_done()
                done.set()
                continue
            with self._wake:
                old, self.loaded, self.field = self.loaded, new, name
                views = list(self._views.values())
                for v in views:
                    v.spec, v.epoch = new.initial_spec, v.epoch + 1      # version: the page's count
                # another scene: its own recordings and fast-pass times
                self._warm, self._fast_ms, self._fast_level = self._warm_list(), {}, 0
                self._wake.notify_all()
            with JIT_LOCK:
                del old                          # its Dr.Jit objects go on this thread
                gc.collect()
                new.passes.clear()               # recorded while the old scene was alive
            self._set_status(desc=f"field {name}")
            for v in views:
                if v.notify is not None:
                    v.notify(self.describe(v))
            self._reload_done()
            done.set()

    def _reload_done(self):
        with self._wake:
            self._reloads -= 1
            self._wake.notify_all()

    def histogram(self, view: View) -> HistogramReply:
        """The volume-weighted histogram under the view's TF editor."""
        spec = view.spec
        below, above = self.loaded.outside(spec)
        density, view.replanned = (spec.density if view.replanned else None), False
        return HistogramReply(tuple(self.loaded.shares(spec)), tuple(spec.range), spec.log, below, above, density)

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
            warm = None
            with self._wake:
                if self._stop:
                    break
                now = time.monotonic()
                plans = [(v, *self._next_pass(v, now)) for v in self._views.values()]
                work = [(v, kind) for v, kind, _ in plans if kind is not None]
                # no view waits for a picture (only refinements of one shown): record ahead
                if self._warm and not self._expected and all(kind is None and at == math.inf or kind == "full" and v.accum_epoch == v.epoch
                                      for v, kind, at in plans):
                    warm = self._warm.pop(0)
                elif not work:
                    wake_at = min((at for _, _, at in plans), default=math.inf)
                    self._wake.wait(min(0.25, max(0.001, wake_at - now)))
                    continue
                else:
                    turn += 1
                    view, kind = work[turn % len(work)]
                    epoch, version, camera, spec, mode = view.epoch, view.version, view.camera, view.spec, view.mode
            if warm is not None:
                self._warm_up(*warm)
                continue
            try:
                if kind == "redisplay":
                    self._redisplay(view)
                else:
                    self._pass(view, kind, epoch, version, camera, spec, mode)
            except Exception as e:                   # this view's trouble, nobody else's
                self._failed(view, epoch, camera, spec, e)
        self._release()

    def _fast_mode(self) -> str | None:
        """The mode of the passes that answer a camera or TF change:
        `FAST_MODE`, or None (the scene's integrator) without modes."""
        return FAST_MODE if FAST_MODE in self.loaded.modes else None

    def _ladder(self) -> list:
        """The fast passes' film sizes, [width, height], largest first (`FAST_LADDER`)."""
        full = list(self.loaded.size)
        sizes = [[max(8, int(full[0] * self.preview_scale * f)), max(8, int(full[1] * self.preview_scale * f))]
                 for f in self.fast_ladder]
        return [q for k, q in enumerate(sizes) if q not in sizes[:k]]

    def _sizes(self, mode=None) -> tuple[list, list]:
        """(the film size of the fast passes, or of a preview in ``mode``;
        the full one), [width, height]. A preview takes the fast passes'
        size where that is recorded for its mode, else the preview size."""
        ladder = self._ladder()
        small = ladder[min(self._fast_level, len(ladder) - 1)]
        if mode is not None and mode != self._fast_mode() and not self.loaded.recorded(small, mode):
            small = ladder[0]
        return small, list(self.loaded.size)

    def _fast_timed(self, size, seconds: float):
        """A fast pass of ``size`` took ``seconds``: update its running mean,
        then step down the ladder when over `FAST_BUDGET`, or up when the
        larger size (its time scaled by the pixels) fits in 3/4 of it; only
        to sizes recorded already (no tracing in the middle of a drag)."""
        key = tuple(size)
        mean = self._fast_ms.get(key)
        mean = seconds if mean is None else 0.7 * mean + 0.3 * seconds
        self._fast_ms[key] = mean
        ladder, fast = self._ladder(), self._fast_mode()
        level = min(self._fast_level, len(ladder) - 1)
        if list(size) != ladder[level]:
            return
        scaled = lambda q: mean * q[0] * q[1] / (size[0] * size[1])       # noqa: E731
        step = 0
        if mean > FAST_BUDGET and level + 1 < len(ladder) and self.loaded.recorded(ladder[level + 1], fast):
            step = 1
        elif level > 0 and self.loaded.recorded(ladder[level - 1], fast) and \
                scaled(ladder[level - 1]) < 0.75 * FAST_BUDGET:
            step = -1
        if step:                                 # the new size's mean starts from this one, scaled
            self._fast_level = level + step
            self._fast_ms[tuple(ladder[level + step])] = scaled(ladder[level + step])

    def _next_pass(self, v: View, now: float) -> tuple[str | None, float]:
        """What ``v`` needs next and when: ``("redisplay" | "fast" |
        "preview" | "full", now)``, or ``(None, when)``: nothing before
        ``when`` (the hand is still moving; inf: nothing at all)."""
        if v.broken:
            return None, math.inf
        if v.redisplay:
            return "redisplay", now
        e = v.epoch
        if v.accum_epoch == e:
            return ("full", now) if v.spp < self.max_spp else (None, math.inf)
        if v.fast_epoch != e and v.preview_epoch != e:
            return "fast", now
        if now < v.changed_at + SETTLE:
            return None, v.changed_at + SETTLE
        if v.preview_epoch != e and self.preview_scale < 1:
            return "preview", now
        return "full", now

    def _warm_list(self) -> list:
        """The recordings a view needs, in the order it needs them: the fast
        pass, the engine's mode at preview size, then at full size; then
        both at the smaller fast sizes."""
        ladder, full, fast = self._ladder(), list(self.loaded.size), self._fast_mode()
        preview = self.preview_scale < 1
        items = [(ladder[0], fast)] + ([(ladder[0], self.mode)] if preview else []) + [(full, self.mode)]
        for size in ladder[1:]:
            items += [(size, fast)] + ([(size, self.mode)] if preview else [])
        return [item for k, item in enumerate(items) if item not in items[:k]]

    def _warm_up(self, size, mode):
        """Record (and throw away) one pass of ``size`` in ``mode`` with the
        start camera and TF, so that a view's first such pass replays."""
        with JIT_LOCK:
            if self.loaded.recorded(size, mode):
                return
            try:
                self.loaded.apply(self.loaded.initial_camera, self.loaded.initial_spec, size)
                self.loaded.render(next(self._seeds), size, mode)
            except Exception:                        # a view's own pass will say what is wrong
                self.loaded.forget(size, mode)

    def _denoise_due(self, view: View, spp: int) -> bool:
        """Denoise the accumulation now: at 1, 2, 4, 8, 16 spp, then each
        `DENOISE_INTERVAL`, and at ``max_spp``."""
        return spp >= self.max_spp or (spp <= 16 and spp & (spp - 1) == 0) \
            or time.monotonic() - view.denoised_at >= DENOISE_INTERVAL

    def _denoised(self, image: np.ndarray) -> np.ndarray:
        with self._denoise_lock:
            return self._denoise(image)

    def _pass(self, view: View, kind: str, epoch: int, rendered: int, camera, spec, mode):
        """One pass of ``kind`` ("fast", "preview" or "full") for ``view``'s
        state of ``epoch`` (its version ``rendered``), then its frame."""
        pass_mode = self._fast_mode() if kind == "fast" else mode
        small, full = self._sizes(pass_mode)
        size = full if kind == "full" else small
        t0 = time.perf_counter()
        with JIT_LOCK:
            try:
                self.loaded.apply(camera, spec, size)
                self._put_clip(view.clip)
                image = self.loaded.render(next(self._seeds), size, pass_mode)
            except Exception:
                self.loaded.forget(size, pass_mode)  # its recording and what the scene holds
                raise
        took = time.perf_counter() - t0
        render_ms = round(1e3 * took, 1)
        if kind == "fast":
            self._fast_timed(size, took)
        preview = kind != "full"
        with self._wake:
            if view.closed:
                return
            view.good, view.failures = (camera, spec), 0
            stale = view.epoch != epoch
            if stale:
                # the view changed while this pass ran (a drag): show it, as the
                # newest picture there is, but accumulate nothing into it
                preview, shown, spp, denoise = True, image, 1, False
            elif kind == "fast":                     # raw: a drag frame is about speed
                view.fast_epoch = epoch
                shown, spp, denoise = image, 1, False
            elif kind == "preview":
                view.preview_epoch = epoch
                shown, spp = image, 1
                denoise = view.denoise and self._denoise is not None
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
        extra = {"mode": pass_mode, "rendered": rendered, "fast": kind == "fast"}
        if shown is None:
            if old[1]:
                send(Frame(version, spp, True, False, size[0], size[1], render_ms, self.max_spp, old[0], **extra),
                     old[1])
            return
        if denoise:                                  # outside the lock: the page's changes go on
            shown = self._denoised(shown)
        jpeg = encode_jpeg(shown)
        if denoise and not preview:
            with self._wake:
                if view.accum_epoch == epoch and view.spp == spp:
                    view.denoised, view.denoised_spp, view.denoised_jpeg = shown, spp, jpeg
                    view.denoised_at = time.monotonic()
        send(Frame(version, spp, bool(denoise), bool(preview), size[0], size[1], render_ms, self.max_spp, **extra),
             jpeg)

    def _redisplay(self, view: View):
        """The accumulation shown again, denoised or not (the denoiser was switched)."""
        with self._wake:
            view.redisplay = False
            if view.accum_epoch != view.epoch or view.accum is None:
                return
            epoch, spp, version, send, mode = view.epoch, view.spp, view.version, view.send, view.mode
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
        send(Frame(version, spp, bool(denoise), False, w, h, 0.0, self.max_spp, mode=mode, rendered=version,
                   fast=False), jpeg)

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
        or beyond ``budget``. Asked for while a field reloads, it waits for
        the reload and the new field's first full frame (at most
        ``SNAPSHOT_WAIT`` seconds, then refused with a message). With the
        view's annotations' ``burn_in`` on, its PNG has them drawn in."""
        with self._wake:
            if self._reloads:                    # passes do not notify: look again every 20 ms
                deadline = time.monotonic() + SNAPSHOT_WAIT
                while not (view.closed or not self._reloads and view.accum_epoch == view.epoch) \
                        and time.monotonic() < deadline:
                    self._wake.wait(min(0.02, max(0.0, deadline - time.monotonic())))
                if view.closed or self._reloads or view.accum_epoch != view.epoch:
                    raise ValueError(f"snapshot refused: the field was still reloading after {SNAPSHOT_WAIT:g} s "
                                     "(ask again once the picture shows)")
            if view.accum is None or view.accum_epoch != view.epoch:
                raise ValueError("no image yet: wait for the first full frame")
            image = (view.accum / view.spp).astype(np.float32)
            camera, spec, spp, mode = view.camera, view.spec, view.spp, view.mode
            loaded, annotate, clip = self.loaded, view.annotate, view.clip
            denoise = view.denoise and self._denoise is not None
            shown = view.denoised if denoise and view.denoised_spp == spp else None
        if shown is None:
            shown = self._denoised(image) if denoise else image
        if annotate is not None and annotate.burn_in:
            shown = burnt_in(loaded, shown, camera, loaded.table(spec), loaded.stored_log, annotate)
        return write_snapshot(loaded, out_dir, name, image, shown, camera, spec, spp, budget, mode=mode,
                              embed_data=self.embed_data, clip=clip)

    def snapshot(self, view: View, out_dir, name: str) -> list[Path]:
        """`take_snapshot`'s four files: [exr, png, xml, tf.json]."""
        return self.take_snapshot(view, out_dir, name).files[:4]


def check_camera(camera: OrbitCamera):
    """A `ValueError` when ``camera`` cannot render (a position float32 cannot hold)."""
    with np.errstate(over="ignore", invalid="ignore"):
        where = np.asarray(camera.origin, np.float64).astype(np.float32)
    if not np.isfinite(where).all():
        raise ValueError("camera: too far away to render (its position overflows float32)")

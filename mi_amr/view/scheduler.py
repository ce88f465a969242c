"""The viewer's render scheduler: one render thread serving every view.

The thread serves the views in turn, one pass of 1 spp at a time, each
view (a browser tab) with its own camera, transfer function and
accumulated image. Before a pass it puts the view's camera and TF into
the scene: the camera through ``mi.traverse``, the TF through
`set_transfer_function` (majorants recomputed, nothing recompiled), the
clip plane through the medium's ``set_clip_plane``; the pass itself is a
``dr.freeze``-recorded ``mi.render``, replayed without tracing. A change
restarts the view's accumulation; a pass rendered for a state that changed
meanwhile is shown (the newest picture there is) but accumulated into
nothing.

Lighting modes (``amrvolpath``'s ``mode``, docs/design.md section 6d): each
view refines in its own mode (``mode``, default the scene's), while a
camera or TF change is answered by a *fast* pass at ``preview_scale`` of
the resolution, shown raw. The hybrid viewer (docs/design.md sections 11
and 14; the view's ``hybrid``, on unless the engine's ``hybrid=False``): its fast
passes are `FAST_MODE` (``ray_march``, the sci-vis ray marcher) through
the scene's centred sensor (`scene.centre_sensor`: each pixel's ray
through its centre, each step sampled at its midpoint: the same picture
whatever the seed, noise-free) with the marcher's step set to the
engine's ``fast_step_scale`` finest cells (`FAST_STEP_SCALE`; an opaque
input of the recording: nothing recompiles); with the hybrid off,
`PLAIN_FAST_MODE` (``emission_absorption``), 1 spp. Once no camera or TF
change has come for `SETTLE` seconds the view's mode takes over from
there: one pass at the fast passes' size (denoised where the denoiser is
on), then full-size passes that accumulate. The fast passes keep to `FAST_BUDGET`: while their
running mean takes longer, the hybrid's march with the next coarser step of
`FAST_STEPS` first; then they render at the next smaller size of
`FAST_LADDER` (down to half of the preview size; the hybrid's never below
half the view's width), and at a larger size, then a finer step, again once
it fits. Every pass
kind is a frozen recording of the one scene (`LoadedScene.render`); the
ones a view needs are recorded ahead while no view waits for a picture
(`_warm_up`): a page's first picture, and a drag's switch of size, replay
instead of tracing.

With the denoiser (`mitsuba_oidn`) on, a view sees denoised previews of
its mode and denoised images of its accumulation at 1, 2, 4, 8, 16 spp,
then about each second (`DENOISE_INTERVAL`) and at ``max_spp``; between
them each pass re-sends the last denoised image with the real spp count.
Switching the denoiser keeps the accumulation.

A view stops refining once it is clean, as ``mi-amr render`` stops
(docs/manual/adaptive.md): every `CLEAN_CHECK` passes (from 16 on) its
odd and even passes are two half pictures, and when every 16 x 16 tile's
estimated error (`mi_amr.adaptive.half_errors`) is below the noise of
`mi_amr.adaptive` (`DENOISED_NOISE` while the view is denoised, else
`DEFAULT_NOISE`) it gets no more passes (its last frame denoised, with
``max_spp`` its count: the page says it is done) until it changes: the
render thread goes idle. Switching the denoiser off asks for
the lower noise, and refining goes on.

A pass that fails is reported to its view alone (``notify``), which goes
back to the last state that rendered, or after `MAX_FAILURES` in a row
stops rendering until it changes (`_failed`). The render thread
survives any pass; a failed load is the only fatal error (``error``, one
line). Images reach a view through its ``send(header, jpeg_bytes)``
(header: a `protocol.Frame`), called from the render thread.

`RenderScheduler` is a part of `engine.ViewEngine` (a mixin over the
engine's state: ``loaded``, the views and their condition ``_wake``); the
state it keeps itself is set up by `RenderScheduler._init_scheduler`.
"""

from __future__ import annotations

import gc
import io
import itertools
import math
import threading
import time

import drjit as dr
import numpy as np

from ..adaptive import DEFAULT_NOISE, DENOISED_NOISE, half_errors
from ..images import srgb8
from ..params import plugin_error
from .protocol import Error, Frame
from .views import View

#: Samples per pixel after which a view stops refining.
DEFAULT_MAX_SPP = 1024
#: With the denoiser on, a new denoised image of the accumulation at least this often (seconds).
DENOISE_INTERVAL = 1.0
#: A view's accumulation is checked for noise every this many passes (an
#: even count: the halves hold as many), from twice as many on
#: (`RenderScheduler._check_clean`).
CLEAN_CHECK = 8
#: Passes of one state that may fail in a row before its view stops rendering (until it changes).
MAX_FAILURES = 3
#: The lighting mode of the passes that answer a camera or TF change (drag
#: frames) in the hybrid viewer (a view's ``hybrid`` on): the ray marcher.
FAST_MODE = "ray_march"
#: ... with the hybrid off (``mi-amr view --no-hybrid``, the page's toggle).
PLAIN_FAST_MODE = "emission_absorption"
#: The ray marcher's step in the hybrid's drag frames, in finest cells under
#: each leaf (its ``step_scale``; the view's own ``ray_march`` passes keep the
#: integrator's): coarser than the marcher's default 0.5 to keep up with the
#: hand (what it costs in the picture and saves in time on 10^7 cells:
#: docs/performance/view.md, "The hybrid viewer").
FAST_STEP_SCALE = 4.0
#: The hybrid's drag frames' steps, as multiples of ``fast_step_scale``,
#: finest first: over `FAST_BUDGET` they march with the next coarser one.
FAST_STEPS = (1.0, 2.0, 4.0)
#: A pass's time at the next coarser step of `FAST_STEPS`, as a share of its
#: time (on 10^7 cells 0.65 from 4 to 8 finest cells, 0.76 from 8 to 16).
STEP_GAIN = 0.7
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


class RenderScheduler:
    """The render thread of `engine.ViewEngine` and its planning of passes
    (module docstring): which view gets which pass next, the fast passes'
    size, the passes recorded ahead, the denoising cadence, failed passes."""

    def _init_scheduler(self):
        self._stop = False
        self._seeds = itertools.count()
        self._denoise_lock = threading.Lock()    # one denoise at a time (render thread, snapshots)
        self._thread = threading.Thread(target=self._run, name="mi-amr view", daemon=True)
        self._warm = []                          # (size, mode) recorded ahead (`_warm_up`)
        self._fast_levels = {}                   # fast mode -> its passes' size: `_ladder(mode)`[level]
        self._fast_ms = {}                       # (film size, fast mode) -> running mean of its passes (s)
        self._march_level = 0                    # the hybrid's drag frames' step: FAST_STEPS[level]
        self._odd = {}                           # view id -> (accum epoch, sum of its odd passes)
        self._clean = {}                         # view id -> (accum epoch, its estimated error): `_check_clean`

    @property
    def warming(self) -> bool:
        """Whether passes are still to be recorded ahead (`_warm_up`)."""
        return bool(self._warm)

    # ---- Life cycle ----------------------------------------------------------
    def start(self) -> "RenderScheduler":
        """Start the render thread: it loads the scene, then renders; returns the engine."""
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
                if self._warm and not self._expected and all(
                        kind is None and at == math.inf or kind == "full" and v.accum_epoch == v.epoch
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

    # ---- Planning passes ---------------------------------------------------------
    def _new_scene(self):
        """A scene was loaded (the first, or another field's under ``_wake``):
        the passes it needs, to record ahead (`_warm_list`), and fast-pass
        times of its own."""
        self._warm, self._fast_ms, self._fast_levels, self._march_level = self._warm_list(), {}, {}, 0

    def _fast_step(self) -> float:
        """The ray marcher's step in the hybrid's drag frames now, finest cells
        (``fast_step_scale`` times `FAST_STEPS`' level kept to the budget)."""
        return self.fast_step_scale * FAST_STEPS[self._march_level]

    def _fast_mode(self, view: View | None = None) -> str | None:
        """The mode of the passes that answer a camera or TF change of
        ``view`` (None: of a view as the engine opens it): `FAST_MODE` while
        its hybrid is on and the scene has it, else `PLAIN_FAST_MODE`; None
        (the scene's integrator) without modes."""
        modes = self.loaded.modes
        if (self.hybrid if view is None else view.hybrid) and FAST_MODE in modes:
            return FAST_MODE
        return PLAIN_FAST_MODE if PLAIN_FAST_MODE in modes else None

    def _hybrid_modes(self) -> dict | None:
        """The drag frames' mode with a view's hybrid ``{"on": FAST_MODE,
        "off": PLAIN_FAST_MODE}``, or None where the scene has no marcher."""
        return {"on": FAST_MODE, "off": PLAIN_FAST_MODE} if FAST_MODE in self.loaded.modes else None

    @property
    def _fast_level(self) -> int:
        """The fast passes' size of a view as the engine opens it: `_ladder`'s index."""
        return self._fast_levels.get(self._fast_mode(), 0)

    def _ladder(self, fast: str | None = "") -> list:
        """The film sizes, [width, height], largest first, of the passes in
        the fast mode ``fast`` (default: a view's as the engine opens it):
        `FAST_LADDER` of the preview size; the hybrid's (`FAST_MODE`) only
        those at least half the view's width (the first one always)."""
        fast = self._fast_mode() if fast == "" else fast
        full = list(self.loaded.size)
        sizes = [[max(8, int(full[0] * self.preview_scale * f)), max(8, int(full[1] * self.preview_scale * f))]
                 for f in self.fast_ladder]
        sizes = [q for k, q in enumerate(sizes) if q not in sizes[:k]]
        if fast == FAST_MODE:
            sizes = sizes[:1] + [q for q in sizes[1:] if 2 * q[0] >= full[0]]
        return sizes

    def _sizes(self, mode=None, view: View | None = None) -> tuple[list, list]:
        """(the film size of ``view``'s fast passes, or of its preview in
        ``mode``; the full one), [width, height]. A preview takes the fast
        passes' size where that is recorded for its mode, else the preview size."""
        fast = self._fast_mode(view)
        ladder = self._ladder(fast)
        small = ladder[min(self._fast_levels.get(fast, 0), len(ladder) - 1)]
        if mode is not None and mode != fast and not self.loaded.recorded(small, mode):
            small = ladder[0]
        return small, list(self.loaded.size)

    def _fast_timed(self, size, seconds: float, fast: str | None = ""):
        """A fast pass of ``size`` in ``fast`` (default: a view's as the
        engine opens it) took ``seconds``: update its running mean, then
        when over `FAST_BUDGET` march with a coarser step (the hybrid's,
        `FAST_STEPS`) or else step down its ladder, and when under it step
        up the ladder where the larger size (its time scaled by the pixels)
        fits in 3/4 of it, or else march with a finer step where that (its
        time over `STEP_GAIN`) fits; only to sizes recorded already (no
        tracing in the middle of a drag; a step compiles nothing)."""
        fast = self._fast_mode() if fast == "" else fast
        key = (tuple(size), fast)
        mean = self._fast_ms.get(key)
        mean = seconds if mean is None else 0.7 * mean + 0.3 * seconds
        self._fast_ms[key] = mean
        ladder = self._ladder(fast)
        level = min(self._fast_levels.get(fast, 0), len(ladder) - 1)
        if list(size) != ladder[level]:
            return
        scaled = lambda q: mean * q[0] * q[1] / (size[0] * size[1])       # noqa: E731
        step = 0
        centred = fast == FAST_MODE
        coarser = centred and self._march_level + 1 < len(FAST_STEPS)
        finer = centred and self._march_level > 0
        if mean > FAST_BUDGET and coarser:       # the hybrid: a coarser step first (no recording needed)
            self._march_level += 1
            self._fast_ms[key] = STEP_GAIN * mean
        elif mean > FAST_BUDGET and level + 1 < len(ladder) and \
                self.loaded.recorded(ladder[level + 1], fast, centred):
            step = 1
        elif level > 0 and self.loaded.recorded(ladder[level - 1], fast, centred) and \
                scaled(ladder[level - 1]) < 0.75 * FAST_BUDGET:
            step = -1
        elif finer and mean / STEP_GAIN < 0.75 * FAST_BUDGET:
            self._march_level -= 1
            self._fast_ms[key] = mean / STEP_GAIN
        if step:                                 # the new size's mean starts from this one, scaled
            self._fast_levels[fast] = level + step
            self._fast_ms[(tuple(ladder[level + step]), fast)] = scaled(ladder[level + step])

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
            return ("full", now) if v.spp < self.max_spp and not self._is_clean(v) else (None, math.inf)
        if v.fast_epoch != e and v.preview_epoch != e:
            return "fast", now
        if now < v.changed_at + SETTLE:
            return None, v.changed_at + SETTLE
        if v.preview_epoch != e and self.preview_scale < 1:
            return "preview", now
        return "full", now

    def _warm_list(self) -> list:
        """The recordings a view as the engine opens it needs, in the order
        it needs them: the fast pass (in the fast mode in use), the engine's
        mode at preview size, then at full size; then both at the smaller
        fast sizes. (A view that turns its hybrid off or on, or chooses
        another mode, asks for its own: `views.ViewRegistry.change`.)"""
        fast = self._fast_mode()
        ladder, full = self._ladder(fast), list(self.loaded.size)
        preview = self.preview_scale < 1
        items = [self._fast_item(ladder[0], fast)] + ([(ladder[0], self.mode)] if preview else []) + \
            [(full, self.mode)]
        for size in ladder[1:]:
            items += [self._fast_item(size, fast)] + ([(size, self.mode)] if preview else [])
        return [item for k, item in enumerate(items) if item not in items[:k]]

    @staticmethod
    def _fast_item(size, fast) -> tuple:
        """The recording of a fast pass of ``size`` in ``fast``, as `_warm_up`'s
        arguments: the hybrid's (`FAST_MODE`) centred."""
        return (size, fast, True) if fast == FAST_MODE else (size, fast)

    def _warm_up(self, size, mode, centred: bool = False):
        """Record (and throw away) one pass of ``size`` in ``mode`` (``centred``:
        `LoadedScene.render`'s) with the start camera and TF, so that a
        view's first such pass replays."""
        with JIT_LOCK:
            if self.loaded.recorded(size, mode, centred):
                return
            try:
                self.loaded.apply(self.loaded.initial_camera, self.loaded.initial_spec, size)
                self.loaded.render(next(self._seeds), size, mode, centred=centred)
            except Exception:                        # a view's own pass will say what is wrong
                self.loaded.forget(size, mode, centred)

    def _denoise_due(self, view: View, spp: int) -> bool:
        """Denoise the accumulation now: at 1, 2, 4, 8, 16 spp, then each
        `DENOISE_INTERVAL`, and at ``max_spp`` or once clean."""
        return spp >= self.max_spp or (spp <= 16 and spp & (spp - 1) == 0) \
            or time.monotonic() - view.denoised_at >= DENOISE_INTERVAL or self._is_clean(view)

    # ---- Stopping when clean -------------------------------------------------------
    @staticmethod
    def _noise(view: View) -> float:
        """The noise at which ``view`` is clean (module docstring)."""
        return DENOISED_NOISE if view.denoise else DEFAULT_NOISE

    def _is_clean(self, view: View) -> bool:
        """Whether ``view``'s accumulation was found clean (`_check_clean`)."""
        found = self._clean.get(view.id)
        return found is not None and found[0] == view.accum_epoch and found[1] < self._noise(view)

    def _check_clean(self, view: View, image: np.ndarray):
        """Under ``_wake``, after ``image`` went into ``view``'s accumulation:
        keep its odd passes' sum, and every `CLEAN_CHECK` passes estimate
        the accumulation's error from its two halves (odd and even passes)."""
        for gone in [k for k in self._odd if k not in self._views]:
            self._odd.pop(gone, None)
            self._clean.pop(gone, None)
        epoch, spp = view.accum_epoch, view.spp
        if spp % 2:
            held = self._odd.get(view.id)
            self._odd[view.id] = (epoch, image.astype(np.float64) + (held[1] if held and held[0] == epoch else 0.0))
        elif spp % CLEAN_CHECK == 0 and spp >= 2 * CLEAN_CHECK:
            odd = self._odd.get(view.id)
            if odd is not None and odd[0] == epoch:
                half = spp // 2
                errors = half_errors(odd[1] / half, (view.accum - odd[1]) / half, 16)
                self._clean[view.id] = (epoch, float(errors.max()))

    def _denoised(self, image: np.ndarray) -> np.ndarray:
        with self._denoise_lock:
            return self._denoise(image)

    # ---- Passes ------------------------------------------------------------------
    def _pass(self, view: View, kind: str, epoch: int, rendered: int, camera, spec, mode):
        """One pass of ``kind`` ("fast", "preview" or "full") for ``view``'s
        state of ``epoch`` (its version ``rendered``), then its frame."""
        pass_mode = self._fast_mode(view) if kind == "fast" else mode
        small, full = self._sizes(pass_mode, view)
        size = full if kind == "full" else small
        # the hybrid's drag frames march centred with the fast step; every other pass with the integrator's own
        centred = kind == "fast" and pass_mode == FAST_MODE
        step = self._fast_step() if centred else None
        t0 = time.perf_counter()
        with JIT_LOCK:
            try:
                self.loaded.apply(camera, spec, size)
                self._put_clip(view.clip)
                self._put_iso(view)
                image = self.loaded.render(next(self._seeds), size, pass_mode, step_scale=step, centred=centred)
            except Exception:
                self.loaded.forget(size, pass_mode, centred)  # its recording and what the scene holds
                raise
        took = time.perf_counter() - t0
        render_ms = round(1e3 * took, 1)
        if kind == "fast":
            self._fast_timed(size, took, pass_mode)
        preview = kind != "full"
        stop_at = self.max_spp                       # the frames' max_spp: where this view's refining ends
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
                self._check_clean(view, image)
                spp = view.spp
                if self._is_clean(view):             # refining ends here: the page says done
                    stop_at = spp
                shown = view.accum / spp
                denoise = view.denoise and self._denoise is not None
                if denoise and not self._denoise_due(view, spp):
                    shown = None                     # the last denoised image, with the real count
            version, send, old = view.version, view.send, (view.denoised_spp, view.denoised_jpeg)
        extra = {"mode": pass_mode, "rendered": rendered, "fast": kind == "fast"}
        if shown is None:
            if old[1]:
                send(Frame(version, spp, True, False, size[0], size[1], render_ms, stop_at, old[0], **extra),
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
        send(Frame(version, spp, bool(denoise), bool(preview), size[0], size[1], render_ms, stop_at, **extra),
             jpeg)

    def _put_clip(self, clip):
        """The view's clip plane into the medium, when another is there (under `JIT_LOCK`)."""
        if "clip" not in self.loaded.applied or self.loaded.applied["clip"] != clip:
            self.loaded.medium.set_clip_plane(*(clip or (None,)))
            self.loaded.applied["clip"] = clip

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

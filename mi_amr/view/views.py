"""The viewer's views: one `View` per browser tab (its camera, transfer
function, lighting mode, hybrid toggle, clip plane, isosurfaces and accumulated image)
and the registry of them (`ViewRegistry`: open, close, describe, change).

A change that cannot render never reaches the render thread: `ViewRegistry.change`
refuses it with a `ValueError` and the view is unchanged. Every change
bumps the view's ``version`` (the page counts its change messages too);
one that changes the picture bumps its ``epoch`` as well, which restarts
its accumulation (`scheduler`). The views and their state are guarded by
the engine's condition ``_wake``, which also wakes the render thread.

`ViewRegistry` is a part of `engine.ViewEngine` (a mixin over the engine's
state); `ViewRegistry._init_views` sets up what it keeps itself.
"""

from __future__ import annotations

import itertools
import threading
import time
from dataclasses import dataclass

import numpy as np

from .camera import OrbitCamera
from .isosurfaces import apply_iso, check_iso, iso_hello
from .protocol import (AnnotateChange, CameraChange, DenoiseChange, Hello, HybridChange, IsoChange, ModeChange,
                       TFChange, ViewChange, parse_message)
from .tf_spec import TFSpec, colormap_stops


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
    hybrid: bool = True                  # drag frames ray-marched, else emission_absorption (`scheduler`)
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
    iso: tuple = ()                      # iso values, the field's own units (`isosurfaces`)
    iso_only: bool = False               # the surfaces drawn alone (the gas off)


class ViewRegistry:
    """The views of `engine.ViewEngine` (module docstring): opened for a
    page, described to it, changed by it, closed when it goes."""

    def _init_views(self):
        self._views: dict[int, View] = {}
        self._ids = itertools.count(1)
        self._wake = threading.Condition(threading.RLock())     # the views and their state
        self._expected = 0                       # pages waiting for the load to open a view (`expect_view`)

    def open_view(self, send, notify=None) -> View:
        """A new view with the scene's initial camera and TF; ``send(header,
        jpeg)`` gets its frames, ``notify(message)`` the render thread's
        errors for it."""
        if not self.ready.is_set():
            raise RuntimeError("the data are still loading")
        with self._wake:
            v = View(next(self._ids), self.loaded.initial_camera, self.loaded.initial_spec, send, notify,
                     denoise=self._denoise is not None, mode=self.mode, hybrid=self.hybrid,
                     iso=self.loaded.initial_iso, iso_only=self.loaded.initial_iso_only)
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
        marches = self._hybrid_modes()
        return Hello(view.id, view.camera, view.spec, tuple(s.colormaps), s.log_available, self._denoise is not None,
                     self.denoiser_missing, view.denoise, tuple(s.size), self.max_spp, s.description,
                     colormap_stops(s.colormaps, s.scene_rgb), editor=self._editor_extras(),
                     modes=s.modes or None, mode=view.mode, fast_mode=self._fast_mode(view),
                     mode_note=s.mode_note or None, hybrid=view.hybrid if marches else None,
                     fast_modes=marches, iso=iso_hello(s, view.iso, view.iso_only))

    def iso_state(self, view: View) -> dict:
        """``view``'s isosurfaces as `Hello` gives them (`isosurfaces.iso_hello`)."""
        with self._wake:
            return iso_hello(self.loaded, view.iso, view.iso_only)

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
        """Apply a camera, TF, denoise, mode, hybrid or iso change to ``view`` (a page
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
                    self._record_ahead(view)             # its previews
                    view.broken = None
                    self._wake.notify_all()
                    return False
                case HybridChange(on=on):
                    if on and not self._hybrid_modes():
                        raise ValueError(f"hybrid: the drag frames' ray marcher needs lighting modes: "
                                         f"{self.loaded.mode_note or 'this scene has none'}")
                    view.hybrid = on                   # the picture stays; the next drag's frames change
                    view.version += 1
                    self._record_ahead(view)             # its fast passes and previews
                    self._wake.notify_all()
                    return False
                case IsoChange(values=values, only=only):
                    values = view.iso if values is None else check_iso(self.loaded, values)
                    only = view.iso_only if only is None else only
                    if (values, only) == (view.iso, view.iso_only):
                        view.version += 1                # a change message: the page counts it
                        return False
                    view.iso, view.iso_only = values, only
                case _:
                    raise ValueError(f"not a view change: {type(change).__name__}")
            view.version += 1
            view.epoch += 1
            view.changed_at = time.monotonic()
            view.broken = None
            self._wake.notify_all()
            return (before.range, before.log) != (view.spec.range, view.spec.log)

    def _record_ahead(self, view: View):
        """Ask `scheduler` to record ahead what ``view`` needs now (under
        ``_wake``): its fast passes' sizes in its fast mode, and in its own
        mode (its previews)."""
        fast = self._fast_mode(view)
        for size in self._ladder(fast):
            for item in (self._fast_item(size, fast), (size, view.mode)):
                if item not in self._warm and not self.loaded.recorded(*item):
                    self._warm.append(item)

    def _put_iso(self, view: View):
        """On the render thread, under `JIT_LOCK`: ``view``'s isosurfaces into
        the medium (`isosurfaces.apply_iso`); where that changed the kernels
        (the medium's first value), what the views need is recorded ahead again."""
        if apply_iso(self.loaded, view.iso, view.iso_only):
            with self._wake:
                self._warm = self._warm_list()
                for v in self._views.values():
                    self._record_ahead(v)

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


def check_camera(camera: OrbitCamera):
    """A `ValueError` when ``camera`` cannot render (a position float32 cannot hold)."""
    with np.errstate(over="ignore", invalid="ignore"):
        where = np.asarray(camera.origin, np.float64).astype(np.float32)
    if not np.isfinite(where).all():
        raise ValueError("camera: too far away to render (its position overflows float32)")

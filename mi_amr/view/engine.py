"""The viewer's renderer: one scene, any number of views of it.

`ViewEngine` loads AMR data (a scene planned from the data alone,
`mi_amr.autoscene`) or an XML scene with an ``amr`` medium on a thread of
its own, then renders on that thread, progressively, for its views (a
browser tab or a notebook widget each). It is the one object callers
hold; its parts, one concept each, are mixins over its state:

* `views.ViewRegistry`: the views (`views.View`: camera, TF, lighting
  mode, clip plane, isosurfaces, accumulation): open, describe, change (a change that
  cannot render is refused with a `ValueError`), close;
* `scheduler.RenderScheduler`: the render thread and its passes (fast
  passes while the hand moves, ray-marched in the hybrid viewer, the
  view's mode once it settles, passes recorded ahead, the denoising
  cadence, failed passes);
* `editor.EditorRequests`: the TF editor's requests, the histogram,
  field switches, the annotations, clip and slice requests;
* `snapshot.ViewSnapshots`: a view written to files.

This module keeps what they share: the options, the load and its status
(``status``, ``error``, ``ready``, `on_status`), and the loaded scene, one
`LoadedScene` (``engine.loaded``). The engine takes and gives `protocol`
messages (a page's are routed to it by `dispatch`, for the server and the
widget alike). Images reach a view through its ``send(header,
jpeg_bytes)`` (header: a `protocol.Frame`), called from the render thread;
the server keeps only the newest unsent one (stale frames are dropped,
never queued). Code that renders in the same process while a viewer runs
holds `JIT_LOCK`.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import mitsuba as mi
import numpy as np

from ..plugins.integrator import MODES
from ..plugins.iso_surfaces import parse_iso_values
from ..progress import listen
from .editor import EditorRequests
from .isosurfaces import apply_iso, check_iso, scene_iso
from .protocol import Status
from .scene import LoadedScene, load_scene
from .scheduler import (DEFAULT_MAX_SPP, DENOISE_INTERVAL, FAST_BUDGET, FAST_LADDER, FAST_MODE, FAST_STEP_SCALE,
                        FAST_STEPS, JIT_LOCK, MAX_FAILURES, PLAIN_FAST_MODE, SETTLE, RenderScheduler, denoiser,
                        encode_jpeg, one_line)
from .snapshot import SNAPSHOT_WAIT, Snapshot, SnapshotBudget, ViewSnapshots
from .tf_spec import TFSpec
from .views import View, ViewRegistry, check_camera

#: What callers import from here (the parts' names, as before the engine was split).
__all__ = ["ViewEngine", "View", "check_camera", "denoiser", "encode_jpeg", "one_line", "DEFAULT_MAX_SPP",
           "DENOISE_INTERVAL", "FAST_BUDGET", "FAST_LADDER", "FAST_MODE", "FAST_STEP_SCALE", "FAST_STEPS", "JIT_LOCK",
           "MAX_FAILURES", "PLAIN_FAST_MODE", "SETTLE", "SNAPSHOT_WAIT"]


class ViewEngine(ViewRegistry, EditorRequests, RenderScheduler, ViewSnapshots):
    """Loads ``source`` (data path, yt data set or XML scene) on a thread of
    its own, then renders for the views (see the module docstring and its
    parts').

    ``res``: image width (the height follows the scene's film aspect);
    ``max_spp``: where each view stops refining; ``preview_scale``: the
    resolution of the fast passes and of the first pass in a view's mode
    after a change (1: full size); ``mode``: the lighting mode views start
    in (None: the scene's integrator's own; a mode needs ``amrvolpath``);
    ``fast_ladder``: the fast passes' sizes as shares of the preview size,
    largest first (`FAST_LADDER`); ``hybrid``: whether views start with
    ray-marched drag frames (`FAST_MODE`; False: `PLAIN_FAST_MODE`; each view
    may change its own); ``fast_step_scale``: the ray marcher's finest
    step in those frames, finest cells (`FAST_STEP_SCALE`; coarser by
    `FAST_STEPS` to keep to `FAST_BUDGET`); ``plan``: the
    `ScenePlan` of data ``source`` made already (a notebook's `DataScene`),
    else planned at load; ``iso``: the iso values views start with, in the
    field's own units (at most 4; None: the scene's own), ``iso_only``: the
    surfaces alone (`isosurfaces`; ``mi-amr view --iso``)."""

    def __init__(self, source, field: str | None = None, *, res: int = 256, max_spp: int = DEFAULT_MAX_SPP,
                 preview_scale: float = 0.5, variant: str = "llvm_ad_rgb", mode: str | None = None,
                 fast_ladder=FAST_LADDER, embed_data: bool = False, plan=None, hybrid: bool = True,
                 fast_step_scale: float = FAST_STEP_SCALE, iso=None, iso_only: bool = False):
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
        if not isinstance(hybrid, bool):
            raise ValueError(f"hybrid must be True or False, got {hybrid!r}")
        if not (isinstance(fast_step_scale, (int, float)) and 0 < fast_step_scale <= 1000):
            raise ValueError(f"fast_step_scale must lie in (0, 1000] finest cells, got {fast_step_scale!r}")
        self.hybrid, self.fast_step_scale = hybrid, float(fast_step_scale)
        self.iso = None if iso is None else parse_iso_values(iso, "iso")     # checked against the data at load
        if iso_only and not self.iso:
            raise ValueError("iso_only: needs iso values (--iso V ...)")
        self.iso_only = bool(iso_only)
        self.source, self.field, self.res, self.max_spp = source, field, int(res), int(max_spp)
        self.preview_scale, self.variant = float(preview_scale), variant
        self.embed_data = bool(embed_data)       # snapshots of yt data: copy them (else name them)
        self._plan = plan
        self.status = Status("loading", "starting", 0, None)
        self.error: str | None = None
        self.ready = threading.Event()
        self.loaded: LoadedScene | None = None    # set on the render thread, dropped when it ends
        self._listeners: list = []               # status(Status) callbacks
        self._denoise, self.denoiser_missing = denoiser()
        self._init_views()
        self._init_editor()
        self._init_scheduler()

    @property
    def colormaps(self) -> tuple:
        """The loaded scene's colormaps ("scene" first for an XML scene)."""
        return self.loaded.colormaps

    @property
    def initial_spec(self) -> TFSpec:
        """The TF a new view starts from."""
        return self.loaded.initial_spec

    # ---- Status ------------------------------------------------------------------
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
        self.loaded.initial_iso, self.loaded.initial_iso_only = scene_iso(self.loaded)
        if self.iso is not None:                 # --iso: the views' start, searched for from the first pass
            self.loaded.initial_iso, self.loaded.initial_iso_only = check_iso(self.loaded, self.iso), self.iso_only
            with JIT_LOCK:
                apply_iso(self.loaded, self.loaded.initial_iso, self.iso_only)
        self._new_scene()                        # the passes it needs, to record ahead
        encode_jpeg(np.zeros((8, 8, 3), np.float32))  # the JPEG encoder loaded now, not at the first frame

    # ---- Snapshots -----------------------------------------------------------------
    def take_snapshot(self, view: View, out_dir, name: str, budget: SnapshotBudget | None = None) -> Snapshot:
        """`snapshot.ViewSnapshots.take_snapshot`, waiting at most this
        module's `SNAPSHOT_WAIT` (read at each call) for a field reload."""
        return super().take_snapshot(view, out_dir, name, budget, wait=SNAPSHOT_WAIT)

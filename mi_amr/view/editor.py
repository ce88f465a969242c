"""The page's requests beyond view changes: the TF editor's state and
requests (the TF as a file, a TF file loaded, another field, a new
`Hello`), the histogram under the editor, and the annotations, clip plane
and slice (`view_annotations`).

Another field of the same data is loaded on the render thread between
passes (`EditorRequests.switch_field`): every view keeps its camera, starts
from the new field's TF (and its isosurfaces: none unless the scene has
some), and its page gets a new `Hello`; a field that
fails to load leaves the last good scene. While a reload is pending
(``_reloads``), a snapshot waits for it (`snapshot.ViewSnapshots`).

`EditorRequests` is a part of `engine.ViewEngine` (a mixin over the
engine's state); `EditorRequests._init_editor` sets up what it keeps itself.
"""

from __future__ import annotations

import gc
import threading

from .camera import FLOOR_MARGIN, MAX_ELEVATION
from .isosurfaces import scene_iso
from .protocol import (AnnotateChange, AnnotationsRequest, ClipChange, Describe, EditorRequest, FieldChange,
                       HistogramReply, SliceRequest, TFFile, TFLoad, TFSave)
from .scene import load_scene
from .scheduler import JIT_LOCK, one_line
from .tf_spec import PRESET_POINTS
from .view_annotations import annotations_reply, slice_reply
from .views import View


class EditorRequests:
    """The TF editor's requests, the histogram, field switches, the
    annotations, clip and slice requests of `engine.ViewEngine` (module
    docstring)."""

    def _init_editor(self):
        self._field_requests: list = []          # (name, done Event, result dict): for the render thread
        self._reloads = 0                        # field switches asked for and not done (snapshots wait)

    # ---- Requests ----------------------------------------------------------------------
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
        another field (`switch_field`; None), a new `Hello`; and the
        annotations' (`protocol.ClipChange`: `set_clip`, None; what the page
        draws over the picture, None; the geometry `AnnotationsReply`; a
        `SliceReply`). A `ValueError` says what is wrong; the view is then
        unchanged."""
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

    # ---- Fields ------------------------------------------------------------------------
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
            new.initial_iso, new.initial_iso_only = scene_iso(new)      # in the new field's units
            with self._wake:
                old, self.loaded, self.field = self.loaded, new, name
                views = list(self._views.values())
                for v in views:
                    v.spec, v.epoch = new.initial_spec, v.epoch + 1      # version: the page's count
                    v.iso, v.iso_only = new.initial_iso, new.initial_iso_only
                self._new_scene()                # its own recordings and fast-pass times
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

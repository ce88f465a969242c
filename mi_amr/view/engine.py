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

Images reach a view through its ``send(header, jpeg_bytes)``, called from
the render thread; the server keeps only the newest unsent one (stale
frames are dropped, never queued).
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
from .tf_spec import COLORMAPS, PRESET_POINTS, Histogram, TFSpec, colormap_stops

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

    from ..tools.images import srgb8
    buf = io.BytesIO()
    Image.fromarray(srgb8(image)).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


@dataclass
class View:
    """One viewer (a browser tab): its state and its accumulation."""
    id: int
    camera: OrbitCamera
    spec: TFSpec
    send: object                         # send(header dict, jpeg bytes), thread-safe
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
        self.status = {"state": "loading", "desc": "starting", "done": 0, "total": None}
        self.error: str | None = None
        self.ready = threading.Event()
        self._views: dict[int, View] = {}
        self._ids = itertools.count(1)
        self._wake = threading.Condition(threading.RLock())     # the views and their state
        self._stop = False
        self._listeners: list = []               # status(dict) callbacks
        self._histogram = None
        self.scene_rgb = None                    # the medium's own colours (XML scenes)
        self._denoise, self.denoiser_missing = denoiser()
        self._thread = threading.Thread(target=self._run, name="mi-amr view", daemon=True)

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
        """On the render thread, before it ends: drop the scene, its frozen
        recordings and every Dr.Jit variable of it, and collect them here.
        Freed later from another thread (after this one's Dr.Jit state is
        gone), they crashed a later render."""
        import gc
        with self._wake:
            self._views.clear()
        with JIT_LOCK:
            for name in ("_render", "_forget", "params", "medium", "scene", "_applied", "_histogram"):
                self.__dict__.pop(name, None)
            gc.collect()
        try:
            import drjit as dr
            dr.sync_thread()
        except Exception:
            pass

    def on_status(self, callback):
        """``callback(status dict)`` on load progress and when ready or failed;
        returns a function that stops it."""
        self._listeners.append(callback)
        return lambda: self._listeners.remove(callback) if callback in self._listeners else None

    def _set_status(self, **kw):
        self.status = dict(self.status, **kw)
        for fn in list(self._listeners):
            fn(dict(self.status))

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
                self._load_scene(mi)
        finally:
            stop_listening()

    def _load_scene(self, mi):
        """The scene, its parameters and the frozen pass (under `JIT_LOCK`)."""
        import drjit as dr
        import mi_amr
        if str(self.source).lower().endswith(".xml"):
            self._load_xml(mi)
        else:
            self._load_data(mi)
        self.medium = mi_amr.amr_media(self.scene)[0]
        self.params = mi.traverse(self.scene)
        # the first sensor's keys (named after its id: "sensor" in planned scenes)
        films = [k[:-len("film.size")] for k in self.params.keys() if k.endswith("film.size")]
        if not films:
            raise ValueError(f"{self.source}: the scene's sensor has no film to render into")
        prefix = "sensor." if "sensor.film.size" in self.params.keys() else films[0]
        self._keys = {"to_world": prefix + "to_world", "size": prefix + "film.size"}
        self.params[self._keys["size"]] = self.size
        self.params.update()
        self._applied = {}

        frozen = {}

        def render(seed: int, size) -> np.ndarray:
            # one recording per film size: a replay does not see the film's size
            # (a scalar of the recorded kernels), so one recording must never
            # serve another size
            if tuple(size) not in frozen:
                frozen[tuple(size)] = dr.freeze(lambda scene, seed: mi.render(scene, spp=1, seed=seed))
            image = np.array(frozen[tuple(size)](self.scene, dr.opaque(mi.UInt32, seed)), dtype=np.float32)
            if image.shape[:2] != (size[1], size[0]):
                raise RuntimeError(f"rendered {image.shape[:2]}, expected {(size[1], size[0])}")
            return image
        self._render = render
        self._forget = lambda size: frozen.pop(tuple(size), None)
        self._failures = 0
        self._seeds = itertools.count()

    def _load_data(self, mi):
        from ..autoscene import MIN_POSITIVE_SHARE, plan_scene, positive_share, scene_for
        self._set_status(desc=f"reading {self.source}")
        plan = plan_scene(self.source, self.field)
        self.stored_log = plan.transform == "log10" or positive_share(plan.data) >= MIN_POSITIVE_SHARE
        self.log_available = self.stored_log
        cmap, points = PRESET_POINTS.get(plan.tf, PRESET_POINTS["spiky"])
        self.initial_spec = TFSpec(points, cmap, plan.transform == "log10", plan.tf_range, plan.density_scale)
        self.plan = replace(plan, transform="log10" if self.stored_log else "none")
        self.scene_rgb = None
        self.colormaps = COLORMAPS
        d = scene_for(self.plan, res=self.res, spp=1)
        medium = d["volume"]["interior"]
        medium.pop("tf_min"), medium.pop("tf_max")
        medium["transfer_function"] = self.initial_spec.table(self.stored_log)
        self._set_status(desc="building the medium")
        self.scene = mi.load_dict(d, parallel=False)
        self.size = [self.res, self.res]
        self.initial_camera = OrbitCamera.looking(self.plan.origin, self.plan.target, self.plan.up, self.plan.fov)
        self.description = f"{self.source}" + (f" field {self.field}" if self.field else "")

    def _load_xml(self, mi):
        import mi_amr
        self._set_status(desc=f"loading {self.source}")
        self.scene = mi.load_file(str(self.source), parallel=False)
        media = mi_amr.amr_media(self.scene)
        if not media:
            raise ValueError(f"{self.source}: the scene has no amr medium to explore")
        med = media[0]
        self.plan = None
        self.stored_log = med.volume.meta.get("value_transform") == "log10"
        self.log_available = self.stored_log
        self.scene_rgb = np.asarray(med.tf.rgba[:, :3], np.float64)
        self.colormaps = ("scene",) + COLORMAPS
        u = np.linspace(0, 1, 65)
        alpha = np.interp(u, np.linspace(0, 1, len(med.tf)), med.tf.rgba[:, 3])
        self.initial_spec = TFSpec([(float(a), float(b)) for a, b in zip(u, alpha)], "scene",
                                   self.stored_log, tuple(med.tf.domain), float(med.density_scale))
        sensor = self.scene.sensors()[0]
        m = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
        origin, forward, up = m[:3, 3], m[:3, 2], m[:3, 1]
        bbox = self.scene.bbox()
        centre = 0.5 * (np.array(bbox.min, np.float64) + np.array(bbox.max, np.float64))
        dist = max(float(np.linalg.norm(centre - origin)), 1e-3)
        sensor_params = mi.traverse(sensor)
        fov = float(np.ravel(sensor_params["x_fov"])[0]) if "x_fov" in sensor_params.keys() else 45.0
        self.initial_camera = OrbitCamera.looking(origin, origin + dist * forward, up, fov)
        w, h = sensor.film().size()
        self.size = [self.res, max(16, int(round(self.res * h / w)))]
        self.description = str(self.source)

    # ---- Views -------------------------------------------------------------------
    def open_view(self, send) -> View:
        """A new view with the scene's initial camera and TF."""
        if not self.ready.is_set():
            raise RuntimeError("the data are still loading")
        with self._wake:
            v = View(next(self._ids), self.initial_camera, self.initial_spec, send,
                     denoise=self._denoise is not None)
            self._views[v.id] = v
            self._wake.notify_all()
            return v

    def close_view(self, view: View):
        with self._wake:
            view.closed = True
            self._views.pop(view.id, None)

    def describe(self, view: View) -> dict:
        """What a page needs to draw its controls."""
        return {"type": "hello", "view": view.id, "camera": view.camera.to_json(), "tf": view.spec.to_json(),
                "colormaps": list(self.colormaps), "log_available": self.log_available,
                "denoiser": self._denoise is not None, "denoiser_missing": self.denoiser_missing,
                "denoise": view.denoise, "size": self.size, "max_spp": self.max_spp,
                "data": self.description, "colormap_stops": colormap_stops(self.colormaps, self.scene_rgb)}

    def change(self, view: View, msg: dict):
        """Apply a page message of type camera, tf or denoise to ``view``
        (a `ValueError` names what is wrong; the view is then unchanged).
        Returns whether the histogram's range or units changed."""
        kind = msg.get("type")
        with self._wake:
            before = view.spec
            if kind == "camera":
                view.camera = view.camera.from_message(msg)
            elif kind == "tf":
                view.spec = TFSpec.from_message(msg, view.spec, self.log_available, self.colormaps)
            elif kind == "denoise":
                on = msg.get("on")
                if not isinstance(on, bool):
                    raise ValueError("denoise: 'on' must be true or false")
                if on and self._denoise is None:
                    raise ValueError(self.denoiser_missing)
                view.denoise = on                  # the version bump below restarts the view
            else:
                raise ValueError(f"unknown message type {kind!r}")
            view.version += 1
            self._wake.notify_all()
            return (before.range, before.log) != (view.spec.range, view.spec.log)

    def histogram(self, view: View) -> dict:
        """The volume-weighted histogram under the view's TF editor."""
        if self._histogram is None:
            self._histogram = Histogram(self.medium.volume)
        spec = view.spec
        return {"type": "histogram", "counts": self._histogram.shares(spec, self.stored_log),
                "range": list(spec.range), "log": spec.log}

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

    def _apply(self, camera: OrbitCamera, spec: TFSpec, size):
        """Put a view's state into the scene (only what differs)."""
        moved = self._applied.get("camera") != camera
        resized = self._applied.get("size") != size
        if moved:
            self.params[self._keys["to_world"]] = camera.transform()
        if resized:
            self.params[self._keys["size"]] = size
        if moved or resized:
            self.params.update()
            self._applied.update(camera=camera, size=size)
        if self._applied.get("spec") != spec:
            self.medium.set_transfer_function(spec.table(self.stored_log, self.scene_rgb), spec.density)
            self._applied["spec"] = spec

    def _pass(self, view: View, version: int, camera, spec, preview: bool):
        size = [max(8, int(self.size[0] * self.preview_scale)), max(8, int(self.size[1] * self.preview_scale))] \
            if preview else list(self.size)
        t0 = time.perf_counter()
        try:
            with JIT_LOCK:
                self._apply(camera, spec, size)
                image = self._render(next(self._seeds), size)
        except Exception as e:                       # say it, forget the recording, go on
            import sys
            print(f"mi-amr view: a pass failed ({type(e).__name__}: {str(e).splitlines()[0]}); "
                  "rendering again", file=sys.stderr)
            self._failures += 1
            self._forget(size)
            self._applied = {}
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
            header = {"type": "frame", "version": version, "spp": spp, "denoised": denoised,
                      "preview": preview, "width": size[0], "height": size[1],
                      "render_ms": round(render_ms, 1), "max_spp": self.max_spp}
            send(header, encode_jpeg(shown))

    # ---- Snapshots -----------------------------------------------------------------
    def snapshot(self, view: View, out_dir, name: str) -> list[Path]:
        """Write ``NAME.exr`` (the accumulated image, linear), ``NAME.png``
        (what the page shows) and ``NAME.xml`` (+ ``NAME.tf.json``): the
        scene with the view's camera and TF, which ``mi-amr render`` renders
        to the same picture. ``name`` must be a plain file name."""
        from ..tools.images import write_exr, write_png
        out_dir = Path(out_dir).resolve()
        stem = safe_name(name)
        with self._wake:
            if view.accum is None or view.accum_version != view.version:
                raise ValueError("no image yet: wait for the first full frame")
            image = (view.accum / view.spp).astype(np.float32)
            shown = view.denoised if view.denoise and view.denoised is not None else image
            camera, spec, spp = view.camera, view.spec, view.spp
        out_dir.mkdir(parents=True, exist_ok=True)
        paths = [out_dir / f"{stem}{ext}" for ext in (".exr", ".png", ".xml", ".tf.json")]
        write_exr(paths[0], image)
        write_png(paths[1], shown)
        tf = spec.table(self.stored_log, self.scene_rgb)
        tf.to_json(paths[3])
        if self.plan is not None:
            self._snapshot_data_xml(paths[2], paths[3], camera, spec, tf, spp)
        else:
            self._snapshot_scene_xml(paths[2], paths[3], camera, spec, spp)
        return paths

    def _data_file(self, out_dir: Path) -> Path:
        """A file the XML can load: the source itself, or (yt data, a
        field's own .scalars) the data written once as ``.amrb``."""
        from ..autoscene import field_scalars
        src = Path(str(self.source))
        if src.suffix in (".cells", ".npz", ".amrb") and src.is_file() and field_scalars(src, self.field) is None:
            return src.resolve()
        target = out_dir / f"{src.stem or 'data'}{'-' + str(self.field).replace(',', '-') if self.field else ''}.amrb"
        if not target.exists():
            from ..native_file import save_native
            from ..data.blocks import BlockVolume
            data = self.plan.data
            save_native(data if isinstance(data, BlockVolume) else BlockVolume.from_cells(data), target)
        return target

    def _snapshot_data_xml(self, path: Path, tf_path: Path, camera, spec, tf, spp: int):
        from ..autoscene import write_scene_xml
        plan = replace(self.plan, tf=str(tf_path), tf_range=tf.domain, density_scale=spec.density,
                       origin=camera.origin, target=camera.target, up=camera.up, fov=camera.fov,
                       notes=[f"data: {self.description}", f"a snapshot of mi-amr view at {spp} spp: TF "
                              f"{tf_path.name} ({'log10' if spec.log else 'linear'} display over "
                              f"[{spec.range[0]:.4g}, {spec.range[1]:.4g}], colormap {spec.colormap}), "
                              f"density_scale {spec.density:.4g}"])
        write_scene_xml(plan, self._data_file(path.parent), path, res=self.size[0], spp=spp)

    def _snapshot_scene_xml(self, path: Path, tf_path: Path, camera, spec, spp: int):
        """The source XML with the view's camera (a lookat), TF (the .json)
        and density scale; relative paths still resolve (a <path> to the
        source's folder)."""
        import xml.etree.ElementTree as ET
        src = Path(str(self.source)).resolve()
        tree = ET.parse(src)
        root = tree.getroot()
        root.insert(0, ET.Element("path", value=str(src.parent)))
        sensor = root.find("sensor")
        for t in sensor.findall("transform"):
            if t.get("name") == "to_world":
                sensor.remove(t)
        t = ET.SubElement(sensor, "transform", name="to_world")
        fmt = lambda v: ", ".join(f"{float(x):.9g}" for x in v)     # noqa: E731
        ET.SubElement(t, "lookat", origin=fmt(camera.origin), target=fmt(camera.target), up=fmt(camera.up))
        for el in sensor.iter():
            if el.get("name") == "sample_count":
                el.set("value", str(spp))
            if el.get("name") in ("width", "height"):
                el.set("value", str(self.size[0] if el.get("name") == "width" else self.size[1]))
        medium = next(m for m in root.iter("medium") if m.get("type") == "amr")
        for el in list(medium):
            if el.get("name") in ("transfer_function", "density_scale", "tf_min", "tf_max"):
                medium.remove(el)
        medium.insert(0, ET.Element("string", name="transfer_function", value=str(tf_path)))
        medium.insert(1, ET.Element("float", name="density_scale", value=f"{spec.density:.9g}"))
        tree.write(path)


def safe_name(name) -> str:
    """A snapshot name as a plain file stem: letters, digits, ``-``, ``_``,
    ``.`` (not leading), at most 100 characters; anything else (a path, a
    separator, ``..``) is a `ValueError`."""
    if not isinstance(name, str) or not 1 <= len(name) <= 100:
        raise ValueError("snapshot name: 1 to 100 characters")
    if name.startswith(".") or any(not (c.isascii() and (c.isalnum() or c in "-_.")) for c in name):
        raise ValueError(f"snapshot name {name!r}: letters, digits, '-', '_' and '.' only (not leading), "
                         "no folders")
    return name

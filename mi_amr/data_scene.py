"""A picture of AMR data from Python, in the words yt users know:
``sc = mi_amr.scene(ds_or_path, field="density")``, ``sc.render()``,
``sc.save("x.exr")`` (docs/manual/python.md).

`DataScene` plans as ``mi-amr render DATA --field F`` plans
(`mi_amr.autoscene.plan_scene`, printing nothing), keeps the plan's
choices as attributes to edit (``tf``, ``tf_range``, ``density_scale``,
the camera's ``origin``/``target``/``up``/``fov``, ``mode``, ``res``,
``spp``) and renders them with the command line's estimator and chunks
(`mi_amr.distributed.render_local`): the same seed gives the image
``mi-amr render`` writes. The Mitsuba scene is loaded once and kept; a
new TF, density scale, camera or image size goes into it as parameters
(majorants recomputed, nothing rebuilt, no kernel compiled); a new mode or
log10/linear choice loads it again. ``mitsuba_scene`` and ``params`` give
the Mitsuba objects for scripting and gradients.

No Mitsuba variant need be set first: a scene renders in the one set, else
in the one ``mi-amr render`` chooses (`mi_amr.rendering.use_variant`:
``cuda_ad_rgb`` where a CUDA device works, else ``llvm_ad_rgb``), or in
``variant=`` given to `scene` or `show`.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import mitsuba as mi
import numpy as np

from .autoscene import ScenePlan, plan_scene
from .scene_writer import scene_for, write_scene_xml
from .data.opening import is_native
from .distributed import render_local
from .annotations import Annotations, PinholeCamera, Placement, burn_in, srgb_png_bytes, write_srgb_png
from .data.volume import as_volume
from .images import png_bytes, srgb8, write_exr, write_png
from .slicing import Slice, Slicer, axis_index
from .native_file import save_data
from .plugins.integrator import MODES
from .plugins.iso_surfaces import parse_iso_values
from .plugins.medium import AMRMedium, scene_media
from .rendering import chunk_for, default_spp, use_variant
from .scene_xml import dict_with_integrator_parameters
from .transfer.function import TransferFunction


class Image(np.ndarray):
    """A rendered picture: float32 ``(H, W, C)`` linear RGB (a numpy array),
    shown inline by Jupyter as an sRGB PNG (`_repr_png_`)."""

    def _repr_png_(self) -> bytes:
        shown = getattr(self, "annotated_srgb", None)          # set by ``render(annotate=...)``
        return png_bytes(np.asarray(self)) if shown is None else srgb_png_bytes(shown)

    def annotated(self, annotate=True) -> np.ndarray:
        """The picture as sRGB 8-bit pixels (H, W, 3) with annotations drawn
        on it (`DataScene.annotate`: ``annotate`` True for the outline and
        the legend, or names among outline, axes, levels, legend); the
        float image itself stays as rendered (its EXR never has them)."""
        scene = getattr(self, "scene", None)
        if scene is None:
            raise ValueError("annotated: this image does not come from DataScene.render")
        return scene.annotate(self, annotate)

    def to_bitmap(self) -> mi.Bitmap:
        """The picture as a ``mitsuba.Bitmap`` (linear RGB, float32)."""
        return mi.Bitmap(np.ascontiguousarray(np.asarray(self, np.float32)[..., :3]), mi.Bitmap.PixelFormat.RGB)


def _plan_vector(name: str, doc: str, as_tuple: bool) -> property:
    """A 3-vector of the plan (``ScenePlan.NAME``) as an attribute: read as
    a float64 array, written as the plan keeps it (array or tuple)."""
    def get(self):
        return np.asarray(getattr(self.plan, name), np.float64)

    def put(self, value):
        v = np.asarray(value, np.float64).reshape(3)
        setattr(self.plan, name, tuple(float(x) for x in v) if as_tuple else v)
    return property(get, put, doc=doc)


class DataScene:
    """AMR data planned into a scene (see the module docstring). ``data``:
    a path of any kind mi-amr opens, a yt data set, `AMRCells`, a
    `BlockVolume` or a `ScenePlan`; ``field``: the field (yt data);
    ``mode``: the ``amrvolpath`` lighting mode (None: ``multi``); ``res``,
    ``spp``: the picture's width and height (pixels) and samples per pixel
    (None: `mi_amr.rendering.default_spp` of the mode);
    ``variant``: the Mitsuba variant, set for the process (None: the one
    set, else ``mi-amr render``'s choice, `mi_amr.rendering.use_variant`);
    ``plan``: `mi_amr.autoscene.plan_scene` options (``tf``, ``log``,
    ``value_range``, ``density_scale``, ``emission``...)."""

    def __init__(self, data, field: str | None = None, *, mode: str | None = None, res: int = 400,
                 spp: int | None = None, variant: str | None = None, **plan):
        if mode is not None and mode not in MODES:
            raise ValueError(f"mode: one of {', '.join(MODES)}, got {mode!r}")
        use_variant(variant)                         # before the data are read: a refused variant is one line
        self.source, self.field = data, field
        self.plan: ScenePlan = data if isinstance(data, ScenePlan) else plan_scene(data, field, **plan)
        self.mode, self.res = mode, int(res)
        self.spp = default_spp(mode) if spp is None else int(spp)
        #: A clip plane ``(normal, offset)`` in world space (the domain
        #: centred at 0, its longest side 1): the medium is kept where
        #: ``normal . x <= offset``; None: none (`AMRMedium.set_clip_plane`).
        self.clip = None
        self._loaded = None           # (key, mi.Scene, the state put into it)
        self._lock = contextlib.nullcontext()     # a widget's engine.JIT_LOCK while it renders (`show`)

    # ---- the plan's choices, to edit ---------------------------------------------
    tf = property(lambda self: self.plan.tf, lambda self, v: setattr(self.plan, "tf", str(v)),
                  doc="The TF: a preset name, a matplotlib colormap or a TF .json file.")
    density_scale = property(lambda self: self.plan.density_scale,
                             lambda self, v: setattr(self.plan, "density_scale", float(v)),
                             doc="Extinction at opacity 1, inverse world units (the domain's longest side 1).")
    fov = property(lambda self: self.plan.fov, lambda self, v: setattr(self.plan, "fov", float(v)),
                   doc="The camera's field of view along x, degrees.")

    @property
    def tf_range(self) -> tuple[float, float]:
        """The TF's domain, in the values' units (log10 units when ``log``)."""
        return self.plan.tf_range

    @tf_range.setter
    def tf_range(self, value):
        lo, hi = (float(x) for x in value)
        if not hi > lo:
            raise ValueError(f"tf_range: LO < HI, got ({lo}, {hi})")
        self.plan.tf_range = (lo, hi)

    @property
    def iso(self) -> tuple:
        """Isosurface values in the field's own units (at most 4; () none;
        docs/manual/isosurfaces.md). Setting them moves the surfaces of the
        loaded scene (nothing is compiled once it has any)."""
        return tuple(self.plan.iso)

    @iso.setter
    def iso(self, values):
        values = parse_iso_values(values, "iso")
        before = self.plan.iso
        self.plan.iso = values
        try:
            self.plan.medium_iso()
        except ValueError:
            self.plan.iso = before
            raise
        if not values:
            self.plan.iso_only = False

    @property
    def iso_only(self) -> bool:
        """Whether only the isosurfaces are drawn (the gas off)."""
        return self.plan.iso_only

    @iso_only.setter
    def iso_only(self, value):
        if value and not self.plan.iso:
            raise ValueError("iso_only: set iso values first")
        self.plan.iso_only = bool(value)

    @property
    def log(self) -> bool:
        """Whether the medium holds log10 of the values (choose it with
        ``mi_amr.scene(..., log=True)``)."""
        return self.plan.transform == "log10"

    origin = _plan_vector("origin", "The camera's position, world units (the domain centred at 0, z up).", False)
    target = _plan_vector("target", "The point the camera looks at, world units.", True)
    up = _plan_vector("up", "The camera's up direction.", True)

    @property
    def notes(self) -> list:
        """What the plan chose and why (what ``mi-amr render`` prints)."""
        return list(self.plan.notes)

    @property
    def visibility(self):
        """The plan's predicted picture (`mi_amr.visibility.Visibility`)."""
        return self.plan.visibility

    # ---- Mitsuba -----------------------------------------------------------------
    @property
    def mitsuba_scene(self) -> mi.Scene:
        """The Mitsuba scene with this scene's current choices in it (in the
        variant set now: a scene made before a change of variant loads again)."""
        key = (use_variant(), self.mode, self.plan.transform, id(self.plan.data), repr(self.plan.emission))
        if self._loaded is None or self._loaded[0] != key:
            d = scene_for(self.plan, res=self.res, spp=self.spp)
            if self.mode:
                d = dict_with_integrator_parameters(d, {"mode": self.mode})
            self._loaded = (key, mi.load_dict(d, parallel=False), {})
        self._apply()
        return self._loaded[1]
    @property
    def params(self) -> mi.SceneParameters:
        """``mi.traverse`` of `mitsuba_scene` (for scripting and gradients:
        use ``amrprbvolpath`` for derivatives)."""
        return mi.traverse(self.mitsuba_scene)

    @property
    def medium(self) -> AMRMedium:
        """The scene's ``amr`` medium."""
        return next(m for m in scene_media(self.mitsuba_scene) if isinstance(m, AMRMedium))

    def _state(self) -> dict:
        return {"tf": (self.plan.tf, tuple(self.plan.tf_range), self.plan.density_scale),
                "camera": (tuple(self.origin), tuple(self.target), tuple(self.up), self.plan.fov),
                "res": self.res,
                "iso": (tuple(self.plan.iso), self.plan.iso_only),
                "clip": None if self.clip is None else (tuple(float(x) for x in self.clip[0]), float(self.clip[1]))}

    def _apply(self):
        """Put what changed since the last render into the loaded scene."""
        _, scene, before = self._loaded
        now = self._state()
        if not before:                              # just loaded: everything but the clip is in it
            before = dict(now, clip=None)
        if now["iso"] != before["iso"]:
            medium = next(m for m in scene_media(scene) if isinstance(m, AMRMedium))
            medium.set_iso(self.plan.medium_iso(), only=self.plan.iso_only)
        if now["clip"] != before["clip"]:
            medium = next(m for m in scene_media(scene) if isinstance(m, AMRMedium))
            medium.set_clip_plane(*(now["clip"] or (None,)))
        if now["tf"] != before["tf"]:
            tf, tf_range, density = now["tf"]
            medium = next(m for m in scene_media(scene) if isinstance(m, AMRMedium))
            medium.set_transfer_function(TransferFunction.load(tf, tf_range), density)
        if now["camera"] != before["camera"] or now["res"] != before["res"]:
            fresh = mi.traverse(mi.load_dict({"type": "scene", "sensor": scene_for(
                self.plan, res=self.res, spp=self.spp)["sensor"]}, parallel=False))
            params = mi.traverse(scene)
            for k in ("sensor.to_world", "sensor.x_fov", "sensor.film.size"):
                params[k] = fresh[k]
            params.update()
        self._loaded = (self._loaded[0], scene, dict(now))

    # ---- pictures ----------------------------------------------------------------
    def render(self, spp: int | None = None, res: int | None = None, seed: int = 0, progress: bool = False,
               annotate=None) -> Image:
        """The picture at ``spp`` samples per pixel and ``res`` x ``res``
        pixels (defaults: the scene's), float32 (H, W, 3) linear RGB; the
        same chunks and seeds as ``mi-amr render --seed SEED``. ``annotate``
        (True, or names among outline, axes, levels, legend): a notebook
        shows the picture with them (`Image.annotated`)."""
        spp = self.spp if spp is None else int(spp)
        if spp < 1:
            raise ValueError(f"spp: at least 1, got {spp}")
        if res is not None:
            if int(res) < 1:
                raise ValueError(f"res: at least 1, got {res}")
            self.res = int(res)
        with self._lock:
            scene = self.mitsuba_scene
            image = render_local(scene, spp, chunk_for(spp, None), seed, progress=progress, desc="mi_amr.scene")
        image = np.array(image, dtype=np.float32)
        if not np.all(np.isfinite(image)):
            raise ValueError(f"the rendered image holds {int((~np.isfinite(image)).sum())} non-finite values")
        image = image.view(Image)
        image.scene = self
        if annotate:
            image.annotated_srgb = self.annotate(image, annotate)
        return image

    def save(self, path, spp: int | None = None, res: int | None = None, seed: int = 0, annotate=None) -> dict:
        """Render and write ``path`` (EXR), its PNG preview and the scene as
        XML beside it (``PATH.xml``, naming the data file: the source itself
        when it is a native file, else the data written once as
        ``PATH.amrb``), as ``mi-amr render`` does. Returns the paths."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        image = self.render(spp, res, seed)
        png = path.with_suffix(".png")           # ``annotate``: drawn into the PNG only, never the EXR
        written = {"exr": write_exr(path, image), "png": write_srgb_png(png, self.annotate(image, annotate))
                   if annotate else write_png(png, image)}
        source = self.source
        if isinstance(source, (str, Path)) and is_native(source) and Path(source).is_file():
            data_file = Path(source).resolve()
        else:
            data_file = save_data(self.plan.data, path.with_suffix(".amrb")).resolve()
            written["data"] = data_file
        written["xml"] = write_scene_xml(self.plan, data_file, path.with_suffix(".xml"), res=self.res,
                                         spp=self.spp if spp is None else int(spp), mode=self.mode)
        return written

    def show(self, res: int = 256, **options):
        """The viewer in the notebook cell: a `mi_amr.view.widget.ViewWidget`
        on Jupyter's comm channel (no port opened), ``res`` pixels wide;
        its camera, TF, density scale and mode are written back into this
        scene as they change, so `render` renders the view on screen.
        ``options``: ``max_spp``, ``out_dir`` (snapshots), ``preview_scale``.
        The widget renders in the variant set now (`use_variant`)."""
        from .view.widget import ViewWidget      # lazy: the mi-amr[notebooks] extra (anywidget)
        use_variant()
        return ViewWidget(self, res=res, **options)

    # ---- annotations and slices (mi_amr.annotations, mi_amr.slicing) -----------------------
    def _blocks(self):
        """The plan's data as blocks (made once for per-cell data) and a
        `Slicer` of them as the medium holds the values (log10 when `log`)."""
        key = (id(self.plan.data), self.log)
        if getattr(self, "_slicing", (None,))[0] != key:
            volume = as_volume(self.plan.data)
            self._slicing = (key, volume, Slicer(volume, transform="log10" if self.log else None))
        return self._slicing[1:]

    @property
    def placement(self) -> Placement:
        """Where the data sit in the world (the medium's ``to_world``)."""
        return Placement.of(self._blocks()[0], self.plan.to_world_matrix())

    @property
    def camera(self) -> PinholeCamera:
        """The sensor's camera (projects world points to the picture's pixels)."""
        return PinholeCamera.looking(self.origin, self.target, self.up, self.plan.fov, (self.res, self.res))

    def annotate(self, image, annotate=True) -> np.ndarray:
        """``image`` (linear, or sRGB 8-bit) as sRGB 8-bit pixels with the
        annotations ``annotate`` drawn on it (`Annotations.parse`): outline,
        axes in the data's length unit, AMR level boxes, the TF's legend."""
        rgb8 = np.asarray(image) if np.asarray(image).dtype == np.uint8 else srgb8(np.asarray(image))
        h, w = rgb8.shape[:2]
        volume = self._blocks()[0]
        camera = PinholeCamera.looking(self.origin, self.target, self.up, self.plan.fov, (w, h))
        meta = volume.meta or {}
        name = str(meta.get("field") or "").strip("()").split(",")[-1].strip(" '\"")     # ('gas', 'density')
        label = " ".join(x for x in (name, f"[{meta['units']}]" if meta.get("units") else "") if x)
        tf = TransferFunction.load(self.plan.tf, self.plan.tf_range)
        return burn_in(rgb8, camera, self.placement, volume, Annotations.parse(annotate), tf, label, self.log)

    def slice(self, axis, position: float = 0.0, res=256, method: str = "tent") -> Slice:
        """The field on the plane normal to ``axis`` (x, y, z or 0, 1, 2) at
        world coordinate ``position`` along it (as `clip` offsets; 0 the
        domain's centre), ``res`` pixels along its longer side (or
        (width, height)): values as the medium holds them (log10 when
        `log`), through the reconstruction ``method``, with the AMR level
        per pixel (`mi_amr.slicing.Slice`; ``.image(tf)`` colours it)."""
        from_axis, p = axis_index(axis), self.placement
        unit = (float(position) - p.to_world[from_axis, 3]) / p.to_world[from_axis, from_axis]
        if not 0.0 <= unit <= 1.0:
            lo, hi = p.to_world[from_axis, 3], p.to_world[from_axis, 3] + p.to_world[from_axis, from_axis]
            raise ValueError(f"slice position: a world coordinate in the domain [{lo:.4g}, {hi:.4g}], got {position}")
        return self._blocks()[1].slice(from_axis, unit, res, method)

    def __repr__(self):
        return (f"DataScene[{self.plan.notes[0] if self.plan.notes else ''}; tf {self.tf!r} over "
                f"{self.tf_range}{' (log10)' if self.log else ''}, density_scale {self.density_scale:.4g}, "
                f"mode {self.mode or 'multi'}, {self.res}x{self.res}, {self.spp} spp]")


def scene(data, field: str | None = None, **options) -> DataScene:
    """``DataScene(data, field, **options)``: AMR data planned into a scene
    (`DataScene`), as ``yt.create_scene`` makes one; ``options``: ``mode``,
    ``res``, ``spp``, ``variant`` and the plan's options (`DataScene`)."""
    return DataScene(data, field, **options)


def show(data, field: str | None = None, *, res: int = 256, max_spp: int | None = None, out_dir=".",
         preview_scale: float = 0.5, **options):
    """``scene(data, field, **options).show(res, ...)``: the viewer of AMR
    data in the notebook cell (`DataScene.show`); ``w.scene`` is the scene."""
    widget = {"out_dir": out_dir, "preview_scale": preview_scale}
    if max_spp is not None:
        widget["max_spp"] = max_spp
    return scene(data, field, **options).show(res, **widget)

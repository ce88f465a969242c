"""A scene loaded for the viewer: what its views start from and what renders
them.

`load_scene` reads AMR data (a path or yt data set, planned from the data
alone by `mi_amr.autoscene`) or an XML scene with an ``amr`` medium into a
`LoadedScene`: the Mitsuba scene, its first ``amr`` medium, its parameters,
the ``dr.freeze``-recorded 1-spp passes, and a view's starting camera and
TF. Dropping the object releases all of it (on the thread that rendered).

Lighting modes: when the scene's integrator is ``amrvolpath``, one
integrator object per mode (`MODES`; the scene's own serves its mode, the
others are copies of its parameters with another ``mode``) renders the one
scene through ``mi.render(scene, integrator=...)``: no second scene, so
no second medium for Dr.Jit to dispatch over, and each (mode, film size)
has its frozen recording. The ray marcher's ``step_scale`` is an opaque
input of its recordings: a pass may march with another step
(`LoadedScene.render`'s ``step_scale``: the hybrid viewer's drag frames)
and the next with the integrator's own, nothing recompiled.

Centred passes (``centred=True``: the hybrid viewer's ray-marched drag
frames) render through a second sensor, `centre_sensor`: the scene's
perspective camera (its transform, field of view and film size mirrored
by `LoadedScene.apply`) with a 1-spp stratified sampler without jitter, so
each pixel's ray leaves its centre and every random number of the pass is
its stratum's midpoint: the marcher samples each step's midpoint, and the
surfaces behind the medium get one fixed light sample. Such a pass is the
same whatever the seed (noise-free, biased where the path tracer's
average is not); it never joins an accumulation.

An XML scene's own TF table is kept exactly: the editor starts from its
entries (or, for a table of more than `MAX_POINTS` entries, from
`EDITOR_POINTS` samples of its opacity), and while a view's curve, colours,
units and range are still the scene's the medium gets the scene's table
itself, never one resampled from the editor's points.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from ..autoscene import MIN_POSITIVE_SHARE, plan_scene, planned_display
from ..data.statistics import positive_share
from ..scene_writer import scene_for
from ..data.opening import is_native
from ..data.yt_import import load_dataset
from ..plugins.integrator import DEFAULT_STEP_SCALE, MODES, AMRVolpathIntegrator
from ..plugins.medium import amr_media
from ..transfer.classification import check_density_scale
from ..transfer.function import TransferFunction
from .camera import OrbitCamera, floor_height, world_up
from .protocol import MAX_POINTS
from .tf_spec import COLORMAPS, Histogram, TFSpec, preset_points

#: Opacity samples the editor starts from for an XML scene's TF table of more
#: than `MAX_POINTS` entries (the table itself is kept; see the module docstring).
EDITOR_POINTS = 65


class FrozenPasses:
    """1-spp ``mi.render`` passes of one scene, ``dr.freeze``-recorded once
    per film size and integrator (a replay does not see the film's size, a
    scalar of the recorded kernels: one recording must never serve another
    size; an integrator's mode is a Python constant of its kernels)."""

    def __init__(self):
        self._frozen = {}

    def render(self, scene, seed: int, size, integrator=None, key=None, sensor=None) -> np.ndarray:
        """One pass, (height, width, channels) float32, for ``size`` = [width,
        height] pixels, by ``integrator`` (None: the scene's) through
        ``sensor`` (None: the scene's first), whose recordings ``key``
        names (the mode, and whether centred)."""
        k = (tuple(size), key)

        def replay(record: bool) -> np.ndarray:
            if record:
                self._frozen[k] = self._record(integrator, sensor)
            return np.array(self._frozen[k](scene, dr.opaque(mi.UInt32, seed)), dtype=np.float32)
        try:
            image = replay(k not in self._frozen)
        except RuntimeError as e:
            # a recording made while other Dr.Jit instances were alive (the
            # scene a field switch replaced, until it is collected) cannot be
            # replayed once they are gone: record this pass again, once
            if "registry" not in str(e):
                raise
            image = replay(True)
        if not np.isfinite(image).all():
            # a replay of a recording made before the scene changed gave
            # non-finite samples (seen with stock volpath on an XML scene
            # after a camera and TF change, one pass in 16; the same state
            # and seed rendered plainly or by a new recording give none):
            # record this pass again, once
            image = replay(True)
        if image.shape[:2] != (size[1], size[0]):
            raise RuntimeError(f"rendered {image.shape[:2]}, expected {(size[1], size[0])}")
        return image

    @staticmethod
    def _record(integrator, sensor=None):
        if integrator is None:
            return dr.freeze(lambda scene, seed: mi.render(scene, spp=1, seed=seed))
        if sensor is not None:
            return dr.freeze(lambda scene, seed: mi.render(scene, sensor=sensor, integrator=integrator, spp=1,
                                                           seed=seed))
        return dr.freeze(lambda scene, seed: mi.render(scene, integrator=integrator, spp=1, seed=seed))

    def clear(self):
        """Drop every recording (the set of live Dr.Jit instances changed)."""
        self._frozen.clear()

    def recorded(self, size, key=None) -> bool:
        """Whether a recording for ``size`` and ``key`` exists."""
        return (tuple(size), key) in self._frozen

    def forget(self, size, key=None):
        """Drop the recording for ``size`` and ``key`` (after a failed pass)."""
        self._frozen.pop((tuple(size), key), None)


@dataclass
class LoadedScene:
    """One loaded source (see the module docstring). ``size``: the film,
    [width, height] pixels; ``stored_log``: the medium holds log10 values
    (then, and only then, the log10 display is offered); ``scene_rgb``
    (N, 3) and ``scene_tf``: an XML scene's own TF colours and table;
    ``plan``: the autoscene plan of data (None for XML scenes). The Mitsuba
    objects are None only for a scene built by hand that never renders."""
    source: object
    field: str | None
    description: str
    size: list
    initial_camera: OrbitCamera
    initial_spec: TFSpec
    colormaps: tuple
    stored_log: bool
    scene_rgb: np.ndarray | None = None
    scene_tf: TransferFunction | None = None
    plan: object = None
    fields: tuple = ()                          # the fields a view may switch to (yt data)
    field_note: str = ""                        # why there is no choice of field
    units: str = ""                             # the values' units ("": unknown)
    scene: object = None                        # mi.Scene
    medium: object = None                       # its first amr medium
    params: object = None                       # mi.traverse(scene)
    keys: dict = field(default_factory=dict)    # the sensor's "to_world" and "size" parameter keys
    passes: FrozenPasses = field(default_factory=FrozenPasses)
    applied: dict = field(default_factory=dict)  # the camera, size and spec the scene holds now
    histogram: Histogram | None = None
    integrators: dict = field(default_factory=dict)  # lighting mode -> amrvolpath integrator ({}: none)
    steps: dict = field(default_factory=dict)   # lighting mode -> its integrator's own step_scale
    centre: object = None                       # `centre_sensor` (None: the scene's camera is not perspective)
    centre_params: object = None                # mi.traverse(centre)
    scene_mode: str | None = None               # the scene's own integrator's mode
    mode_note: str = ""                         # why there are no modes
    initial_iso: tuple = ()                     # a view's start: iso values (field units), `isosurfaces`
    initial_iso_only: bool = False              # ... and whether the surfaces are drawn alone

    @property
    def modes(self) -> tuple:
        """The lighting modes the scene renders in (`MODES`; () when its
        integrator is not ``amrvolpath``)."""
        return tuple(m for m in MODES if m in self.integrators)

    @property
    def log_available(self) -> bool:
        return self.stored_log

    @property
    def log_note(self) -> str:
        """Why the log10 display is off ("" when it is offered)."""
        if self.stored_log:
            return ""
        if self.plan is None:
            return "log10 is off: the scene's medium holds its values linearly (value_transform none)"
        return "log10 is off: values <= 0 fill over 10% of the volume"

    def table(self, spec: TFSpec) -> TransferFunction:
        """The medium's TF for ``spec``: the scene's own table while the
        spec's curve, colours, units and range are the scene's (the density
        scale is no part of the table), else ``spec.table``."""
        first = self.initial_spec
        if self.scene_tf is not None and (spec.points, spec.colormap, spec.log, spec.range) == \
                (first.points, first.colormap, first.log, first.range):
            return self.scene_tf
        return spec.table(self.stored_log, self.scene_rgb)

    def replanned(self, spec: TFSpec) -> TFSpec:
        """``spec`` with the range and density scale the plan chooses for its
        log10 or linear display (`planned_display`): what the log10 toggle
        gets for data (an XML scene's spec is returned as it is)."""
        if self.plan is None:
            return spec
        if spec.log == self.initial_spec.log:      # the plan's own units: its range and density (a layered
            return replace(spec, range=self.initial_spec.range, density=self.initial_spec.density)   # plan's too)
        value_range, density = planned_display(
            self.plan.data, self.medium.volume, spec.log,
            lambda r: replace(spec, range=tuple(r)).table(self.stored_log, self.scene_rgb))
        return replace(spec, range=tuple(float(x) for x in value_range), density=float(density))

    def check(self, spec: TFSpec):
        """A `ValueError` naming why ``spec`` cannot render (a TF domain
        float32 cannot hold, a density scale out of range); nothing changes."""
        try:
            self.table(spec)
            check_density_scale(spec.density)
        except ValueError as e:
            raise ValueError(f"tf: cannot be rendered: {e}") from None

    def apply(self, camera: OrbitCamera, spec: TFSpec, size):
        """Put a view's state into the scene (only what differs); under `JIT_LOCK`."""
        moved = self.applied.get("camera") != camera
        resized = self.applied.get("size") != size
        if moved:
            self.params[self.keys["to_world"]] = camera.transform()
            if self.keys.get("fov") in self.params.keys():     # the view's field of view (a widget sets it)
                self.params[self.keys["fov"]] = camera.fov
        if resized:
            self.params[self.keys["size"]] = size
        if moved or resized:
            self.params.update()
            self.applied.update(camera=camera, size=size)
            if self.centre is not None:              # the centred sensor mirrors the scene's
                mirror(self.params, self.keys["to_world"][:-len("to_world")], self.centre_params)
        if self.applied.get("spec") != spec:
            self.medium.set_transfer_function(self.table(spec), spec.density)
            self.applied["spec"] = spec

    def render(self, seed: int, size, mode: str | None = None, step_scale: float | None = None,
               centred: bool = False) -> np.ndarray:
        """One 1-spp pass of what `apply` put in, [width, height] = ``size``,
        in the lighting ``mode`` (None: the scene's integrator as it is);
        ``step_scale``: the ray marcher's step for this pass (None: its
        integrator's own), set as an opaque value (the recording replays);
        ``centred``: through `centre_sensor` (the module docstring; where
        the scene has one)."""
        if mode is None:
            return self.passes.render(self.scene, seed, size)
        if mode not in self.integrators:
            raise ValueError(f"mode {mode}: {self.mode_note or 'not one of ' + ', '.join(self.modes)}")
        integrator = self.integrators[mode]
        step = self.steps.get(mode) if step_scale is None else float(step_scale)
        if step is not None and self.applied.get(("step", mode)) != step:
            integrator.step_scale = dr.opaque(mi.Float, step)
            self.applied[("step", mode)] = step
        if centred and self.centre is not None:
            return self.passes.render(self.scene, seed, size, integrator, (mode, "centred"), self.centre)
        return self.passes.render(self.scene, seed, size, integrator, mode)

    def _key(self, mode, centred: bool):
        return (mode, "centred") if centred and mode is not None and self.centre is not None else mode

    def recorded(self, size, mode: str | None = None, centred: bool = False) -> bool:
        """Whether a pass of ``size`` in ``mode`` (``centred``) is recorded (replays compile nothing)."""
        return self.passes.recorded(size, self._key(mode, centred))

    def forget(self, size, mode: str | None = None, centred: bool = False):
        """After a failed pass: drop its recording, re-apply everything next time."""
        self.passes.forget(size, self._key(mode, centred))
        self.applied.clear()

    def shares(self, spec: TFSpec) -> list[float]:
        """The editor's histogram for ``spec`` (`Histogram`, built on first use)."""
        if self.histogram is None:
            self.histogram = Histogram(self.medium.volume, None if self.plan is None else self.plan.data)
        return self.histogram.shares(spec, self.stored_log)

    def outside(self, spec: TFSpec) -> tuple[float, float]:
        """The shares of the volume below and above ``spec.range`` (`Histogram.outside`)."""
        if self.histogram is None:
            self.histogram = Histogram(self.medium.volume, None if self.plan is None else self.plan.data)
        return self.histogram.outside(spec, self.stored_log)


def scene_spec(tf: TransferFunction, stored_log: bool, density: float) -> TFSpec:
    """The editor's start for a scene's own ``tf`` (stored units; colormap
    "scene"): a point at each entry's opacity, or `EDITOR_POINTS` samples of
    it for a table of more than `MAX_POINTS` entries."""
    alpha = tf.rgba[:, 3].astype(np.float64)
    n = len(tf) if len(tf) <= MAX_POINTS else EDITOR_POINTS
    u = np.linspace(0, 1, n)
    if n != len(tf):
        alpha = np.interp(u, np.linspace(0, 1, len(tf)), alpha)
    return TFSpec([(float(a), float(b)) for a, b in zip(u, alpha)], "scene", stored_log, tuple(tf.domain), density)


def load_scene(source, field, res: int, say, plan=None) -> LoadedScene:
    """``source`` loaded for views ``res`` pixels wide; ``say(desc)``
    reports each step; ``plan``: the `ScenePlan` of data ``source`` made
    already (a notebook's `DataScene`: planned with its options, the data
    read once), else planned here. Under `JIT_LOCK`, with the Mitsuba
    variant set."""
    loaded = _load_xml(mi, source, res, say) if plan is None and str(source).lower().endswith(".xml") \
        else _load_data(mi, source, field, res, say, plan)
    loaded.medium = amr_media(loaded.scene)[0]
    cam = loaded.initial_camera
    loaded.initial_camera = replace(cam, floor=floor_height(ground_boxes(loaded.scene), cam.up))
    loaded.units = loaded.units or str(loaded.medium.volume.meta.get("units") or "")
    loaded.params = params = mi.traverse(loaded.scene)
    # the first sensor's keys (named after its id: "sensor" in planned scenes)
    films = [k[:-len("film.size")] for k in params.keys() if k.endswith("film.size")]
    if not films:
        raise ValueError(f"{source}: the scene's sensor has no film to render into")
    prefix = "sensor." if "sensor.film.size" in params.keys() else films[0]
    loaded.keys = {"to_world": prefix + "to_world", "size": prefix + "film.size", "fov": prefix + "x_fov"}
    params[loaded.keys["size"]] = loaded.size
    params.update()
    loaded.integrators, loaded.scene_mode, loaded.mode_note = mode_integrators(loaded.scene)
    loaded.steps = {m: float(dr.slice(i.step_scale)) for m, i in loaded.integrators.items()}
    if loaded.integrators and loaded.scene.sensors()[0].class_name() == "PerspectiveCamera":
        loaded.centre = centre_sensor(loaded.size)
        loaded.centre_params = mi.traverse(loaded.centre)
        mirror(params, prefix, loaded.centre_params)
    return loaded


#: The scene sensor's parameters `centre_sensor` mirrors (where it has them).
MIRRORED = ("to_world", "x_fov", "near_clip", "far_clip", "principal_point_offset_x", "principal_point_offset_y",
            "film.size")


def centre_sensor(size):
    """A perspective camera of ``size`` = [width, height] pixels whose
    1-spp stratified sampler has no jitter: each pixel's ray through its
    centre, every random number a stratum's midpoint (the module docstring)."""
    return mi.load_dict({"type": "perspective",
                         "sampler": {"type": "stratified", "jitter": False, "sample_count": 1},
                         "film": {"type": "hdrfilm", "width": int(size[0]), "height": int(size[1]),
                                  "pixel_format": "rgb", "rfilter": {"type": "box"}}})


def mirror(params, prefix: str, centre_params):
    """The scene's sensor's (``prefix``) `MIRRORED` parameters into the centred sensor's."""
    for key in MIRRORED:
        if prefix + key in params.keys():
            centre_params[key] = params[prefix + key]
    centre_params.update()


def integrator_props(integrator, mode: str) -> dict:
    """``mi.load_dict`` properties of an ``amrvolpath`` integrator with the
    parameters of ``integrator`` (one) and the lighting ``mode``; its
    ``brightness``, ``step_scale`` and ``shading`` where not the defaults."""
    props = {"type": "amrvolpath", "mode": mode, "rr_depth": int(integrator.rr_depth),
             "max_depth": -1 if integrator.max_depth == 0xFFFFFFFF else int(integrator.max_depth),
             "hide_emitters": bool(integrator.hide_emitters)}
    for name, value, default in (("brightness", float(dr.slice(integrator.brightness)), 1.0),
                                 ("step_scale", float(dr.slice(integrator.step_scale)), DEFAULT_STEP_SCALE),
                                 ("shading", integrator.shading, "flat")):
        if value != default:
            props[name] = value
    for name, value in (("residual_ratio_tracking", integrator.residual),
                        ("decomposition_tracking", integrator.decomposition)):
        if value is not None:                    # None: each medium's own choice
            props[name] = bool(value)
    return props


def mode_integrators(scene) -> tuple[dict, str | None, str]:
    """``(integrators, the scene's mode, note)``: an ``amrvolpath``
    integrator per lighting mode, the scene's own for its mode and copies of
    its parameters for the others; ``({}, None, why)`` for another integrator."""
    own = scene.integrator()
    if not isinstance(own, AMRVolpathIntegrator):
        kind = own.class_name() if own is not None else "none"
        return {}, None, f"the scene's integrator is {kind}: lighting modes need amrvolpath"
    return ({m: own if m == own.mode else mi.load_dict(integrator_props(own, m)) for m in MODES}, own.mode, "")


def ground_boxes(scene) -> np.ndarray:
    """``(n, 2, 3)``: the bounding boxes of the scene's shapes that bound no
    medium (a ground, walls, lights): what the orbit camera stays above."""
    boxes = [(list(b.min), list(b.max)) for b in (s.bbox() for s in scene.shapes()
                                                  if s.interior_medium() is None and s.exterior_medium() is None)
             if all(np.isfinite(list(b.min))) and all(np.isfinite(list(b.max)))]
    return np.asarray(boxes, np.float64).reshape(-1, 2, 3)


def data_fields(source, field) -> tuple[tuple, str, str]:
    """``(fields, note, units)``: the fields of ``source`` the viewer can
    switch between (a yt data set's on-disk fields, ``"type,name"``), or
    ``()`` and why not; the units yt gives ``field`` ("" unknown)."""
    if is_native(source):
        return (), f"{Path(str(source)).suffix} data hold a single field", ""
    if not isinstance(source, (str, Path)):
        return (), "data given as an object: the field is fixed", ""
    ds = load_dataset(source)
    keys = [(t, n) for t, n in ds.field_list if t not in ("all", "io", "nbody") and "particle" not in n]
    names = tuple(f"{t},{n}" for t, n in keys)
    key = next((k for k, name in zip(keys, names) if field in (name, k[1])), None)
    units = str(ds.field_info[key].units) if key is not None and key in ds.field_info else ""
    if not names:
        return (), "yt lists no grid fields for these data", units
    return names, "", units


def _load_data(mi, source, field, res: int, say, plan=None) -> LoadedScene:
    say(f"reading {source}" if plan is None else "planned already")
    plan = plan_scene(source, field) if plan is None else plan
    stored_log = plan.transform == "log10" or positive_share(plan.data) >= MIN_POSITIVE_SHARE
    cmap, points = preset_points(plan.tf)
    spec = TFSpec(points, cmap, plan.transform == "log10", plan.tf_range, plan.density_scale)
    plan = replace(plan, transform="log10" if stored_log else "none")
    d = scene_for(plan, res=res, spp=1)
    medium = d["volume"]["interior"]
    medium.pop("tf_min"), medium.pop("tf_max")
    medium["transfer_function"] = spec.table(stored_log)
    say("building the medium")
    fields, note, units = data_fields(source, field)
    named = str(source) if len(str(source)) <= 200 else type(source).__name__     # an object: its kind
    return LoadedScene(source, field, named + (f" field {field}" if field else ""), [res, res],
                       OrbitCamera.looking(plan.origin, plan.target, world_up(plan.up), plan.fov), spec, COLORMAPS,
                       stored_log, plan=plan, fields=fields, field_note=note, units=units,
                       scene=mi.load_dict(d, parallel=False))


def _load_xml(mi, source, res: int, say) -> LoadedScene:
    say(f"loading {source}")
    scene = mi.load_file(str(source), parallel=False)
    media = amr_media(scene)
    if not media:
        raise ValueError(f"{source}: the scene has no amr medium to explore")
    med = media[0]
    stored_log = med.volume.meta.get("value_transform") == "log10"
    tf = TransferFunction(med.tf.rgba, med.tf.domain)       # a copy: the viewer replaces the medium's
    spec = scene_spec(tf, stored_log, float(med.density_scale))
    sensor = scene.sensors()[0]
    m = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    origin, forward, up = m[:3, 3], m[:3, 2], m[:3, 1]
    bbox = scene.bbox()
    centre = 0.5 * (np.array(bbox.min, np.float64) + np.array(bbox.max, np.float64))
    dist = max(float(np.linalg.norm(centre - origin)), 1e-3)
    sensor_params = mi.traverse(sensor)
    fov = float(np.ravel(sensor_params["x_fov"])[0]) if "x_fov" in sensor_params.keys() else 45.0
    w, h = sensor.film().size()
    return LoadedScene(source, None, str(source), [res, max(16, int(round(res * h / w)))],
                       OrbitCamera.looking(origin, origin + dist * forward, world_up(up), fov), spec,
                       ("scene",) + COLORMAPS, stored_log, scene_rgb=np.asarray(tf.rgba[:, :3], np.float64),
                       scene_tf=tf, field_note="an XML scene's medium holds a single field", scene=scene)

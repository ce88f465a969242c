"""A planned scene (`mi_amr.autoscene.ScenePlan`) as Mitsuba takes it: a
scene dictionary for ``mi.load_dict`` (`scene_for`) and an XML scene that
references the data file, to edit and render again (`write_scene_xml`);
both give the same image.

World space: the domain is centred at the origin, its longest side 1 unit,
and +z is up (the horizon of Mitsuba's ``sunsky`` is the plane z = 0).
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import mitsuba as mi
import numpy as np

from .autoscene import ScenePlan, plan_scene
from .transfer.function import PRESETS

#: Towards the sun: 50 degrees above the horizon, behind the camera's right.
SUN_DIRECTION = [0.5, 0.6, 0.9]


def scene_for(data, field=None, *, res: int = 400, spp: int = 64, integrator: str = "amrvolpath",
              mode: str | None = None, **options) -> dict:
    """A scene dictionary for ``mi.load_dict`` that shows ``data`` (see
    `open_data`) with no scene written by hand; ``options`` go to
    `plan_scene` (``tf``, ``log``, ``value_range``, ``density_scale``);
    ``mode``: the ``amrvolpath`` lighting mode (None: its default)."""
    plan = data if isinstance(data, ScenePlan) else plan_scene(data, field, **options)
    T = mi.ScalarTransform4f

    def matrix(m):       # the numbers `write_scene_xml` writes, so that both render the same image
        return T(mi.ScalarMatrix4f(_as_written(m).reshape(4, 4).astype(np.float32)))
    T4d = getattr(mi, "ScalarTransform4d", T)            # the XML's look-at is computed in double precision
    camera = T4d().look_at(*(_as_written(v).tolist() for v in (plan.origin, plan.target, plan.up)))
    medium = {"type": "amr", "data": plan.data, "transfer_function": plan.tf,
              "tf_min": plan.tf_range[0], "tf_max": plan.tf_range[1], "value_transform": plan.transform,
              "density_scale": plan.density_scale, "to_world": matrix(plan.to_world_matrix())}
    medium.update(emission_parameters(plan))
    medium.update(iso_parameters(plan))
    scene = {
        "type": "scene",
        "integrator": dict({"type": integrator, "max_depth": 64}, **({} if mode is None else {"mode": mode})),
        "sensor": {"type": "perspective", "fov": plan.fov,
                   "to_world": T(mi.ScalarMatrix4f(np.array(camera.matrix, dtype=np.float64).astype(np.float32))),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "volume": {"type": "cube", "to_world": matrix(_cube_matrix(plan)),
                   "bsdf": {"type": "null"}, "interior": medium},
    }
    if plan.lit:
        scene["sky"] = {"type": "sunsky", "sun_direction": SUN_DIRECTION, "turbidity": 3.0,
                        "sun_scale": 2.5, "sky_scale": 6.0}
        scene["floor"] = {"type": "rectangle",
                          "to_world": T().translate([0, 0, float(f"{plan.floor_height():.6g}")]) @ T().scale(1000),
                          "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.45}}}
    return scene


def _as_written(values) -> np.ndarray:
    """``values`` as `write_scene_xml` writes them (9 significant digits)."""
    return np.array([float(f"{float(x):.9g}") for x in np.ravel(values)])


def _cube_matrix(plan: ScenePlan) -> np.ndarray:
    """``to_world`` of the cube that bounds the medium (Mitsuba's cube
    spans -1..1)."""
    return plan.to_world_matrix() @ np.array([[0.5, 0, 0, 0.5], [0, 0.5, 0, 0.5], [0, 0, 0.5, 0.5], [0, 0, 0, 1.0]])


def emission_parameters(plan: ScenePlan) -> dict:
    """The ``amr`` medium's ``emission*`` parameters of a plan ({} for gas
    that does not glow)."""
    e = plan.emission
    if e is None:
        return {}
    if e.model == "blackbody":                   # Planck's law at the field in kelvin: no TF
        out = {"emission_model": "blackbody", "emission_scale": e.scale}
        return out if e.field is None else {**out, "emission_field": e.field}
    out = {"emission": e.tf, "emission_transform": e.transform, "emission_min": e.tf_range[0],
           "emission_max": e.tf_range[1], "emission_scale": e.scale}
    if e.field is not None:
        out["emission_field"] = e.field
    return out


def iso_parameters(plan: ScenePlan) -> dict:
    """The ``amr`` medium's ``iso`` and ``iso_only`` parameters of a plan
    (in the medium's value units; {} without isosurfaces)."""
    if not plan.iso:
        return {}
    out = {"iso": " ".join(f"{v:.9g}" for v in plan.medium_iso())}
    return {**out, "iso_only": True} if plan.iso_only else out


def _tf_reference(tf: str) -> str:
    """How a scene file names a TF: a preset or colormap by its name, a TF
    file by its absolute path (the scene renders from any folder)."""
    return str(Path(tf).resolve()) if tf not in PRESETS and Path(tf).is_file() else str(tf)


def write_scene_xml(plan: ScenePlan, data_file, path, res: int = 400, spp: int = 64,
                    mode: str | None = None, field: str | None = None, checksum: str | None = None) -> Path:
    """Write ``plan`` as an XML scene that loads ``data_file`` (``res`` and
    ``spp`` are its defaults, ``-D res=...`` overrides them; ``mode``: the
    ``amrvolpath`` lighting mode, written unless None). ``field`` and
    ``checksum``: for data yt loads, the field the medium reads from
    ``data_file`` and the checksum of the data it must find there
    (`mi_amr.data.opening.volume_checksum`)."""
    path = Path(path)
    source = "".join(f"\n        <string name=\"{k}\" value={quoteattr(str(v))}/>"
                     for k, v in (("field", field), ("data_checksum", checksum)) if v is not None)
    mode_line = "" if mode is None else f"\n        <string name=\"mode\" value={quoteattr(str(mode))}/>"
    m = plan.to_world_matrix()
    matrix = " ".join(f"{x:.9g}" for x in m.ravel())
    cube_matrix = " ".join(f"{x:.9g}" for x in _cube_matrix(plan).ravel())
    o, t, u = (", ".join(f"{float(x):.9g}" for x in v) for v in (plan.origin, plan.target, plan.up))
    # an XML comment may not hold "--" (the notes name flags such as --log)
    notes = "\n         ".join(n.replace("--", "- -") for n in plan.notes)
    glow_params = {k: _tf_reference(v) if k == "emission" else v for k, v in emission_parameters(plan).items()}
    glow = "".join(f"\n        <{'float' if isinstance(v, float) else 'string'} name=\"{k}\" value="
                   f"{quoteattr(format(v, '.9g') if isinstance(v, float) else str(v))}/>"
                   for k, v in glow_params.items())
    glow += "".join(f"\n        <{'boolean' if isinstance(v, bool) else 'string'} name=\"{k}\" "
                    f"value={quoteattr(str(v).lower() if isinstance(v, bool) else v)}/>"
                    for k, v in iso_parameters(plan).items())
    lights = "" if not plan.lit else f"""
    <emitter type="sunsky">
        <vector name="sun_direction" value="{', '.join(str(x) for x in SUN_DIRECTION)}"/>
        <float name="turbidity" value="3"/>
        <float name="sun_scale" value="2.5"/>
        <float name="sky_scale" value="6"/>
    </emitter>

    <shape type="rectangle">  <!-- the ground, just below the domain -->
        <transform name="to_world">
            <scale value="1000"/>
            <translate z="{plan.floor_height():.6g}"/>
        </transform>
        <bsdf type="diffuse">
            <rgb name="reflectance" value="0.45"/>
        </bsdf>
    </shape>
"""
    text = f"""<scene version="3.0.0">
    <!-- made by mi-amr from the data alone; edit and re-render with
         mi-amr render {path.name} -o OUT.exr
         {notes} -->
    <default name="spp" value="{spp}"/>
    <default name="res" value="{res}"/>

    <integrator type="amrvolpath">
        <integer name="max_depth" value="64"/>{mode_line}
    </integrator>

    <sensor type="perspective">
        <float name="fov" value="{plan.fov}"/>
        <transform name="to_world">
            <lookat origin="{o}" target="{t}" up="{u}"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="$res"/>
            <integer name="height" value="$res"/>
            <rfilter type="box"/>
        </film>
    </sensor>
{lights}
    <medium type="amr" id="volume">
        <string name="filename" value={quoteattr(str(data_file))}/>{source}
        <string name="transfer_function" value={quoteattr(_tf_reference(plan.tf))}/>
        <float name="tf_min" value="{plan.tf_range[0]:.9g}"/>
        <float name="tf_max" value="{plan.tf_range[1]:.9g}"/>
        <string name="value_transform" value="{plan.transform}"/>
        <float name="density_scale" value="{plan.density_scale:.9g}"/>{glow}
        <transform name="to_world">
            <matrix value="{matrix}"/>
        </transform>
    </medium>

    <shape type="cube">
        <transform name="to_world">
            <matrix value="{cube_matrix}"/>
        </transform>
        <bsdf type="null"/>
        <ref name="interior" id="volume"/>
    </shape>
</scene>
"""
    path.write_text(text)
    return path

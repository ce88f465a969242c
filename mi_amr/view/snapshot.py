"""A view written to files: ``NAME.exr`` (the accumulated image, linear),
``NAME.png`` (what the page shows), ``NAME.tf.json`` (the medium's TF) and
``NAME.xml``, the scene with the view's camera and TF, which ``mi-amr
render`` renders to the same picture: for data the planned scene
(`mi_amr.autoscene.write_scene_xml`), for an XML scene the source rewritten
(`mi_amr.scene_xml`). An XML scene's TF left as it was is written with
the scene's own table values (`LoadedScene.table`).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from .camera import OrbitCamera
from .protocol import safe_name
from .scene import LoadedScene
from .tf_spec import TFSpec


def write_snapshot(loaded: LoadedScene, out_dir, name: str, image: np.ndarray, shown: np.ndarray,
                   camera: OrbitCamera, spec: TFSpec, spp: int) -> list[Path]:
    """The four files of a view (module docstring) in ``out_dir``: ``image``
    the accumulation's mean (linear RGB, ``spp`` samples per pixel),
    ``shown`` what the page shows; [exr, png, xml, tf.json] paths."""
    from ..images import write_exr, write_png
    out_dir = Path(out_dir).resolve()
    stem = safe_name(name)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / f"{stem}{ext}" for ext in (".exr", ".png", ".xml", ".tf.json")]
    write_exr(paths[0], image)
    write_png(paths[1], shown)
    tf = loaded.table(spec)
    tf.to_json(paths[3])
    if loaded.plan is not None:
        _data_xml(loaded, paths[2], paths[3], camera, spec, tf, spp)
    else:
        _scene_xml(loaded, paths[2], paths[3], camera, spec, spp)
    return paths


def _data_file(loaded: LoadedScene, out_dir: Path) -> Path:
    """A file the XML can load: the source itself, or (yt data, a field's
    own .scalars) the data written once as ``.amrb``."""
    from ..autoscene import field_scalars
    src, field = Path(str(loaded.source)), loaded.field
    if src.suffix in (".cells", ".npz", ".amrb") and src.is_file() and field_scalars(src, field) is None:
        return src.resolve()
    target = out_dir / f"{src.stem or 'data'}{'-' + str(field).replace(',', '-') if field else ''}.amrb"
    if not target.exists():
        from ..native_file import save_native
        save_native(loaded.plan.data, target)
    return target


def _data_xml(loaded: LoadedScene, path: Path, tf_path: Path, camera: OrbitCamera, spec: TFSpec, tf, spp: int):
    """The planned scene of data with the view's camera, TF and density scale."""
    from ..autoscene import write_scene_xml
    plan = replace(loaded.plan, tf=str(tf_path), tf_range=tf.domain, density_scale=spec.density,
                   origin=camera.origin, target=camera.target, up=camera.up, fov=camera.fov,
                   notes=[f"data: {loaded.description}", f"a snapshot of mi-amr view at {spp} spp: TF "
                          f"{tf_path.name} ({'log10' if spec.log else 'linear'} display over "
                          f"[{spec.range[0]:.4g}, {spec.range[1]:.4g}], colormap {spec.colormap}), "
                          f"density_scale {spec.density:.4g}"])
    write_scene_xml(plan, _data_file(loaded, path.parent), path, res=loaded.size[0], spp=spp)


def _scene_xml(loaded: LoadedScene, path: Path, tf_path: Path, camera: OrbitCamera, spec: TFSpec, spp: int):
    """The source XML with the view's camera (a lookat), film size, sample
    count, TF (the .json) and density scale on its first amr medium;
    relative paths still resolve (a <path> to the source's folder)."""
    import xml.etree.ElementTree as ET

    from ..scene_xml import amr_elements, parse_scene, set_parameters
    src = Path(str(loaded.source)).resolve()
    tree = parse_scene(src)
    root = tree.getroot()
    root.insert(0, ET.Element("path", value=str(src.parent)))
    sensor = root.find("sensor")
    for t in sensor.findall("transform"):
        if t.get("name") == "to_world":
            sensor.remove(t)
    t = ET.SubElement(sensor, "transform", name="to_world")
    fmt = lambda v: ", ".join(f"{float(x):.9g}" for x in v)     # noqa: E731
    ET.SubElement(t, "lookat", origin=fmt(camera.origin), target=fmt(camera.target), up=fmt(camera.up))
    for child, values in (("sampler", {"sample_count": int(spp)}),
                          ("film", {"width": int(loaded.size[0]), "height": int(loaded.size[1])})):
        if sensor.find(child) is not None:
            set_parameters(sensor.find(child), values)
    set_parameters(amr_elements(root)[0], {"transfer_function": str(tf_path), "density_scale": float(spec.density)},
                   drop=("tf_min", "tf_max"))
    tree.write(path)

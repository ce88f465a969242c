"""Rewriting XML scenes that use ``amr`` media.

* `reference_scene`: every ``<medium type="amr">`` becomes Mitsuba's own
  ``heterogeneous`` medium with ``gridvolume`` sigma_t and albedo resampled
  on a dense grid (written as ``.vol`` files), placed by the same
  ``to_world``, with the same phase function and ``sample_emitters``.
* `with_amr_parameters`: override parameters of every ``amr`` medium
  (e.g. ``majorant="global"``) without editing the file.
* `parse_scene`, `amr_elements`, `set_parameters`: the pieces, shared with
  the viewer's snapshots (`mi_amr.view.snapshot`).

Both return a scene loaded with the original file's directory on Mitsuba's
file resolver, so relative paths in the scene keep working.
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

import mitsuba as mi
import numpy as np

_TYPE_TAGS = {bool: "boolean", int: "integer", float: "float", str: "string"}
_PASS_THROUGH = {"phase", "sample_emitters"}      # kept on the reference medium


def amr_elements(root) -> list:
    """Every ``<medium type="amr">`` element under ``root``, in file order."""
    return [e for e in root.iter("medium") if e.get("type") == "amr"]


def set_parameters(element, values: dict, drop=()):
    """Replace the parameters of ``element`` (a plugin's XML element) named
    in ``values`` by one typed child each (bool, int, float or str), and
    remove those named in ``drop``."""
    for child in list(element):
        if child.get("name") in values or child.get("name") in drop:
            element.remove(child)
    for name, value in values.items():
        ET.SubElement(element, _TYPE_TAGS[type(value)], name=name,
                      value=str(value).lower() if isinstance(value, bool) else str(value))


def parse_scene(path, params=None) -> ET.ElementTree:
    """The XML of the scene at ``path`` (a `ValueError` if it does not
    parse, or lacks one of the ``$`` parameters named in ``params``)."""
    try:
        tree = ET.parse(path)
    except (ET.ParseError, OSError) as e:
        raise ValueError(f"{path}: cannot parse scene XML ({e})") from e
    text = ET.tostring(tree.getroot(), encoding="unicode")
    unknown = [k for k in (params or {}) if f"${k}" not in text]
    if unknown:
        raise ValueError(f"{path}: the scene has no parameter(s) {', '.join(unknown)}")
    return tree


def _load(root, scene_path: Path, params: dict):
    resolver = mi.file_resolver()
    scene_dir = str(Path(scene_path).resolve().parent)
    resolver.prepend(scene_dir)
    text = ET.tostring(root, encoding="unicode")
    # parameters the rewrite made unused (e.g. $majorant) are dropped
    used = {k: v for k, v in params.items() if f"${k}" in text}
    try:
        return mi.load_string(text, **used)
    finally:
        # restore the resolver: drop the directory we added
        paths = [str(resolver[i]) for i in range(len(resolver))]
        resolver.clear()
        removed = False
        for p in paths:
            if p == scene_dir and not removed:
                removed = True
                continue
            resolver.append(p)


def with_amr_parameters(scene_path, overrides: dict, **params):
    """Load an XML scene with ``overrides`` set on every ``amr`` medium."""
    tree = parse_scene(scene_path, params)
    root = tree.getroot()
    for med in amr_elements(root):
        set_parameters(med, overrides)
    return _load(root, scene_path, params)


def reference_scene(scene_path, work_dir, resolution=None, memory_limit=None, **params):
    """Load an XML scene with every ``amr`` medium replaced by its
    ``heterogeneous`` + ``gridvolume`` equivalent. Grids are written as
    ``.vol`` files into ``work_dir``. Returns ``(scene, media)`` where
    ``media`` lists the AMR media that were replaced."""
    from ..plugins.medium import AMRMedium
    from .reference import DEFAULT_MEMORY_LIMIT, reference_medium

    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    tree = parse_scene(scene_path, params)
    root = tree.getroot()
    defaults = [e for e in root if e.tag == "default"]
    media = []
    for k, med in enumerate(amr_elements(root)):
        # Instantiate the amr medium alone (with the scene's defaults).
        alone = copy.deepcopy(med)
        alone.set("version", root.get("version", "3.0.0"))
        alone.attrib.pop("id", None)
        for i, d in enumerate(defaults):
            alone.insert(i, copy.deepcopy(d))
        amr = _load(alone, scene_path, params)
        if not isinstance(amr, AMRMedium):
            raise ValueError(f"{scene_path}: could not instantiate amr medium #{k}")
        media.append(amr)
        ref = reference_medium(amr.cells, amr.tf, amr.density_scale, amr.reconstruction,
                               amr.options.to_world, resolution,
                               memory_limit or DEFAULT_MEMORY_LIMIT)
        new = ET.Element("medium", type="heterogeneous")
        if med.get("id"):
            new.set("id", med.get("id"))
        if med.get("name"):
            new.set("name", med.get("name"))
        for channel in ("sigma_t", "albedo"):
            path = work_dir / f"amr{k}_{channel}.vol"
            data = np.asarray(ref[channel]["data"].numpy(), dtype=np.float32)
            mi.VolumeGrid(np.ascontiguousarray(data)).write(str(path))
            vol = ET.SubElement(new, "volume", type="gridvolume", name=channel)
            ET.SubElement(vol, "string", name="filename", value=str(path.resolve()))
            ET.SubElement(vol, "string", name="filter_type", value=ref[channel]["filter_type"])
            m = np.array(amr.options.to_world.matrix, dtype=np.float64).ravel()
            tr = ET.SubElement(vol, "transform", name="to_world")
            ET.SubElement(tr, "matrix", value=" ".join(repr(float(x)) for x in m))
        ET.SubElement(new, "float", name="scale", value=repr(ref["scale"]))
        for child in med:
            if child.tag == "phase" or child.get("name") in _PASS_THROUGH:
                new.append(copy.deepcopy(child))
        parent = next(p for p in root.iter() if med in list(p))
        idx = list(parent).index(med)
        parent.remove(med)
        parent.insert(idx, new)
    if not media:
        raise ValueError(f"{scene_path}: the scene has no <medium type=\"amr\">")
    return _load(root, scene_path, params), media

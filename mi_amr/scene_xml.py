"""Rewriting XML scenes that use ``amr`` media.

* `with_amr_parameters`: override parameters of every ``amr`` medium
  (e.g. ``majorant="global"``) without editing the file.
* `with_integrator_parameters` (an XML scene) and `dict_with_integrator_parameters`
  (a scene dictionary): override parameters of the ``amrvolpath``
  integrator (``mi-amr render --mode``).
* `parse_scene`, `amr_elements`, `set_parameters`, `load_root`: the
  pieces, shared with the viewer's snapshots (`mi_amr.view.snapshot`) and
  the reference scenes of `mi_amr.reference.reference_scene` (every
  ``amr`` medium as Mitsuba's own ``heterogeneous`` medium).

Scenes are loaded with the original file's directory on Mitsuba's
file resolver, so relative paths in the scene keep working.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import mitsuba as mi

_TYPE_TAGS = {bool: "boolean", int: "integer", float: "float", str: "string"}
PASS_THROUGH = {"phase", "sample_emitters"}      # kept on the reference medium


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


def integrator_elements(root, plugin: str = "amrvolpath") -> list:
    """Every ``<integrator type="amrvolpath">`` element under ``root`` (nested
    ones, e.g. inside an ``aov`` integrator, included), in file order."""
    return [e for e in root.iter("integrator") if e.get("type") == plugin]


def load_root(root, scene_path: Path, params: dict, parallel: bool = True):
    resolver = mi.file_resolver()
    scene_dir = str(Path(scene_path).resolve().parent)
    resolver.prepend(scene_dir)
    text = ET.tostring(root, encoding="unicode")
    # parameters the rewrite made unused (e.g. $majorant) are dropped
    used = {k: v for k, v in params.items() if f"${k}" in text}
    try:
        return mi.load_string(text, parallel=parallel, **used)
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
    return load_root(root, scene_path, params)


def _no_amrvolpath(where, overrides, kinds) -> ValueError:
    return ValueError(f"{where}: {', '.join(overrides)} is a parameter of the amrvolpath integrator, and the "
                      f"scene's integrator is {', '.join(repr(k) for k in kinds) or 'the default (path)'}")


def with_integrator_parameters(scene_path, overrides: dict, parallel: bool = True, **params):
    """Load an XML scene with ``overrides`` (e.g. ``{"mode": "single"}``) set
    on its ``amrvolpath`` integrator; a `ValueError` naming the scene's
    integrator where it has none."""
    tree = parse_scene(scene_path, params)
    root = tree.getroot()
    found = integrator_elements(root)
    if not found:
        raise _no_amrvolpath(scene_path, overrides, [e.get("type") for e in root.iter("integrator")])
    for element in found:
        set_parameters(element, overrides)
    return load_root(root, scene_path, params, parallel=parallel)


def dict_with_integrator_parameters(scene: dict, overrides: dict) -> dict:
    """A copy of the scene dictionary ``scene`` with ``overrides`` set on its
    ``amrvolpath`` integrator (the caller's dictionaries are left as they
    are); a `ValueError` naming the scene's integrator where it has none."""
    out = dict(scene)
    kinds, found = [], False
    for key, value in scene.items():
        if isinstance(value, dict) and value.get("type") == "amrvolpath":
            out[key] = dict(value, **overrides)
            found = True
        elif key == "integrator" and isinstance(value, dict):
            kinds.append(value.get("type"))
    if not found:
        raise _no_amrvolpath("the scene", overrides, kinds)
    return out

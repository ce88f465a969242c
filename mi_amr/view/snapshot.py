"""A view written to files: ``NAME.exr`` (the accumulated image, linear),
``NAME.png`` (what the page shows), ``NAME.tf.json`` (the medium's TF) and
``NAME.xml``, the scene with the view's camera, TF, lighting mode, clip
plane and isosurfaces, which
``mi-amr render`` renders to the same picture: for data the planned scene
(`mi_amr.scene_writer.write_scene_xml`), for an XML scene the source rewritten
(`mi_amr.scene_xml`). An XML scene's TF left as it was is written with
the scene's own table values (`LoadedScene.table`).

Snapshots never overwrite: a taken name becomes ``NAME-1``, ``NAME-2``, ...;
each file is written in a private folder, then copied to its name opened
with ``O_CREAT | O_EXCL | O_NOFOLLOW`` (a file or link planted there is
never written through: a link is refused). What else a snapshot writes
(the data of yt, once, as ``.amrb``) is announced in its ``notes``; a
`SnapshotBudget` bounds how many snapshots and bytes one viewer writes.

`ViewSnapshots` takes a snapshot of an engine's view (a part of
`engine.ViewEngine`): the accumulation's mean and what the page shows
(denoised, with the annotations burnt in where asked), from the same
samples; asked for while a field reloads, it waits for the new field's
first full frame (`SNAPSHOT_WAIT`).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import threading
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..scene_writer import write_scene_xml
from ..data.opening import field_scalars, is_native, volume_checksum
from ..data.volume import as_volume
from ..annotations import write_srgb_png
from ..images import write_exr, write_png
from ..native_file import save_native
from ..scene_xml import amr_elements, integrator_elements, parse_scene, set_parameters
from .camera import OrbitCamera
from .isosurfaces import medium_values
from .protocol import safe_name
from .scene import LoadedScene
from .tf_spec import TFSpec
from .view_annotations import burnt_in
from .views import View


#: Snapshots one viewer may write, and their bytes in all (`SnapshotBudget`).
MAX_SNAPSHOTS = 500
MAX_SNAPSHOT_BYTES = 4 << 30
#: Seconds a snapshot asked for during a field reload waits for the new field's first full frame.
SNAPSHOT_WAIT = 120.0
#: The file kinds of a snapshot, in the order of `Snapshot.files`.
EXTENSIONS = (".exr", ".png", ".xml", ".tf.json")


@dataclass
class Snapshot:
    """What a snapshot wrote: ``files`` [exr, png, xml, tf.json, then side
    files (the data, once)], its ``spp``, ``notes`` for the person."""
    files: list
    spp: int
    notes: list = field(default_factory=list)


class SnapshotBudget:
    """At most ``count`` snapshots and ``nbytes`` bytes written by one
    viewer (a token holder cannot fill the disk); thread-safe."""

    def __init__(self, count: int = MAX_SNAPSHOTS, nbytes: int = MAX_SNAPSHOT_BYTES):
        self.count, self.nbytes = int(count), int(nbytes)
        self.used_count = self.used_bytes = 0
        self._lock = threading.Lock()

    def reserve(self):
        """Count one snapshot more, or a `ValueError` when the budget is spent."""
        with self._lock:
            if self.used_count >= self.count:
                raise ValueError(f"snapshot refused: this viewer has written its {self.count} snapshots "
                                 "(restart it for more)")
            if self.used_bytes >= self.nbytes:
                raise ValueError(f"snapshot refused: this viewer has written {self.used_bytes / 1e6:.0f} MB of "
                                 f"snapshots, its budget of {self.nbytes / 1e6:.0f} MB (restart it for more)")
            self.used_count += 1

    def spend(self, nbytes: int):
        with self._lock:
            self.used_bytes += int(nbytes)


def free_stem(out_dir: Path, stem: str) -> str:
    """``stem``, or ``stem-1``, ``stem-2``, ...: the first whose files are
    all free in ``out_dir``; a `ValueError` when one of them is a symbolic link."""
    for k in range(10000):
        name = stem if k == 0 else f"{stem}-{k}"
        paths = [out_dir / f"{name}{ext}" for ext in EXTENSIONS]
        links = [q for q in paths if q.is_symlink()]
        if links:
            raise ValueError(f"snapshot refused: {links[0]} is a symbolic link (snapshots never write through links)")
        if not any(os.path.lexists(q) for q in paths):
            return name
    raise ValueError(f"snapshot refused: {stem} and 9999 numbered names are taken in {out_dir}")


def place(written: Path, target: Path):
    """Copy the private file ``written`` to ``target``, a name that must be
    free: opened with ``O_EXCL | O_NOFOLLOW`` (never through a link, never
    over a file); a `ValueError` names it otherwise."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(target, flags, 0o644)
    except FileExistsError:
        what = "a symbolic link" if target.is_symlink() else "taken meanwhile"
        raise ValueError(f"snapshot refused: {target} is {what} (snapshots never overwrite)") from None
    with os.fdopen(fd, "wb") as out, open(written, "rb") as src:
        shutil.copyfileobj(src, out, 1 << 20)


def write_snapshot(loaded: LoadedScene, out_dir, name: str, image: np.ndarray, shown: np.ndarray,
                   camera: OrbitCamera, spec: TFSpec, spp: int, budget: SnapshotBudget | None = None,
                   mode: str | None = None, embed_data: bool = False, clip=None, iso=((), False)) -> Snapshot:
    """The files of a view (module docstring) in ``out_dir``: ``image`` the
    accumulation's mean (linear RGB, ``spp`` samples per pixel, rendered in
    the lighting ``mode``; None: the scene's integrator as it is), ``shown``
    what the page shows (from the same samples; sRGB uint8 pixels when the
    annotations are burnt in: never into the EXR). Data yt loads are named by
    path, field and checksum in the XML, not copied, unless ``embed_data``
    (then written once as ``.amrb`` beside the snapshots). ``clip``: the
    view's clip plane ``(normal, offset)``, written onto the XML's ``amr``
    medium (``clip_normal``, ``clip_offset``); ``iso``: the view's
    ``(values, only)`` (field units), written onto it as ``iso`` (the
    medium's value units) and ``iso_only``. Nothing is
    overwritten; what was placed is removed again when a later file fails."""
    out_dir = Path(out_dir).resolve()
    safe_name(name)
    out_dir.mkdir(parents=True, exist_ok=True)
    if budget is not None:
        budget.reserve()
    stem = free_stem(out_dir, name)
    paths = [out_dir / f"{stem}{ext}" for ext in EXTENSIONS]
    notes = [] if stem == name else [f"{name}.* exist: written as {stem}.*"]
    placed = []
    with tempfile.TemporaryDirectory(prefix=".mi-amr-snapshot-", dir=out_dir) as tmp:
        private = [Path(tmp) / q.name for q in paths]
        write_exr(private[0], image)
        if np.asarray(shown).dtype == np.uint8:          # sRGB pixels: the annotations burnt in
            write_srgb_png(private[1], shown)
        else:
            write_png(private[1], shown)
        tf = loaded.table(spec)
        tf.to_json(private[3])
        side = []
        if loaded.plan is not None:
            source = None if embed_data else _source_reference(loaded)
            if source is None:
                data = _data_file(loaded, out_dir, Path(tmp))
                if data.parent == Path(tmp):          # written now: placed beside the snapshot
                    side = [(data, out_dir / data.name)]
                    data = out_dir / data.name
                source = (data, None, None)
            _data_xml(loaded, private[2], paths[3], source, camera, spec, tf, spp, mode)
        else:
            _scene_xml(loaded, private[2], paths[3], camera, spec, spp, mode)
        if clip is not None:
            _with_clip(private[2], clip)
        _with_iso(private[2], medium_values(loaded, iso[0]), iso[1])
        try:
            for src, target in list(zip(private, paths)) + side:
                place(src, target)
                placed.append(target)
        except BaseException:
            for q in placed:
                q.unlink(missing_ok=True)
            raise
    size = sum(q.stat().st_size for q in placed)
    if budget is not None:
        budget.spend(size)
    for _, target in side:
        notes.append(f"also wrote {target.name} ({target.stat().st_size / 1e6:.1f} MB): the data the XML "
                     "loads, written once for this folder")
    return Snapshot(placed, spp, notes)


class ViewSnapshots:
    """Snapshots of the views of `engine.ViewEngine` (module docstring); a
    mixin over the engine's state (its views, ``loaded``, the denoiser,
    ``_reloads``)."""

    def take_snapshot(self, view: View, out_dir, name: str, budget: SnapshotBudget | None = None,
                      wait: float = SNAPSHOT_WAIT) -> Snapshot:
        """The view's files (`write_snapshot`): ``NAME.exr``,
        ``.png``, ``.xml``, ``.tf.json`` in ``out_dir`` (a numbered name when
        one is taken), the PNG and EXR from the same samples; ``name`` must
        be a plain file name. A `ValueError` before the first full frame,
        or beyond ``budget``. Asked for while a field reloads, it waits for
        the reload and the new field's first full frame (at most
        ``wait`` seconds, then refused with a message). With the
        view's annotations' ``burn_in`` on, its PNG has them drawn in."""
        with self._wake:
            if self._reloads:                    # passes do not notify: look again every 20 ms
                deadline = time.monotonic() + wait
                while not (view.closed or not self._reloads and view.accum_epoch == view.epoch) \
                        and time.monotonic() < deadline:
                    self._wake.wait(min(0.02, max(0.0, deadline - time.monotonic())))
                if view.closed or self._reloads or view.accum_epoch != view.epoch:
                    raise ValueError(f"snapshot refused: the field was still reloading after {wait:g} s "
                                     "(ask again once the picture shows)")
            if view.accum is None or view.accum_epoch != view.epoch:
                raise ValueError("no image yet: wait for the first full frame")
            image = (view.accum / view.spp).astype(np.float32)
            camera, spec, spp, mode = view.camera, view.spec, view.spp, view.mode
            loaded, annotate, clip, iso = self.loaded, view.annotate, view.clip, (view.iso, view.iso_only)
            denoise = view.denoise and self._denoise is not None
            shown = view.denoised if denoise and view.denoised_spp == spp else None
        if shown is None:
            shown = self._denoised(image) if denoise else image
        if annotate is not None and annotate.burn_in:
            shown = burnt_in(loaded, shown, camera, loaded.table(spec), loaded.stored_log, annotate)
        return write_snapshot(loaded, out_dir, name, image, shown, camera, spec, spp, budget, mode=mode,
                              embed_data=self.embed_data, clip=clip, iso=iso)

    def snapshot(self, view: View, out_dir, name: str) -> list[Path]:
        """`take_snapshot`'s four files: [exr, png, xml, tf.json]."""
        return self.take_snapshot(view, out_dir, name).files[:4]



def _source_reference(loaded: LoadedScene):
    """``(path, field, checksum)`` by which the XML names data yt loads
    (the medium reads them again and checks the checksum), or None: native
    files and data given as objects go through `_data_file`."""
    src = loaded.source
    if not isinstance(src, (str, Path)) or is_native(src) or loaded.field is None:
        return None
    return Path(str(src)).resolve(), loaded.field, volume_checksum(as_volume(loaded.plan.data))


def _data_file(loaded: LoadedScene, out_dir: Path, tmp: Path) -> Path:
    """A file the XML can load: the source itself, the data written before
    into ``out_dir``, or (yt data, a field's own .scalars) the data written
    now as ``.amrb`` into the private folder ``tmp``."""
    src, field = Path(str(loaded.source)), loaded.field
    if is_native(src) and src.is_file() and field_scalars(src, field) is None:
        return src.resolve()
    name = f"{src.stem or 'data'}{'-' + str(field).replace(',', '-') if field else ''}.amrb"
    target = out_dir / name
    if target.is_symlink():
        raise ValueError(f"snapshot refused: {target} is a symbolic link (snapshots never write through links)")
    if target.is_file():
        return target
    return save_native(loaded.plan.data, tmp / name)


def _data_xml(loaded: LoadedScene, path: Path, tf_path: Path, source, camera: OrbitCamera, spec: TFSpec, tf,
              spp: int, mode: str | None = None):
    """The planned scene of data with the view's camera, TF, density scale and lighting mode."""
    plan = replace(loaded.plan, tf=str(tf_path), tf_range=tf.domain, density_scale=spec.density,
                   origin=camera.origin, target=camera.target, up=camera.up, fov=camera.fov,
                   notes=[f"data: {loaded.description}", f"a snapshot of mi-amr view at {spp} spp: TF "
                          f"{tf_path.name} ({'log10' if spec.log else 'linear'} display over "
                          f"[{spec.range[0]:.4g}, {spec.range[1]:.4g}], colormap {spec.colormap}), "
                          f"density_scale {spec.density:.4g}" + (f", lighting mode {mode}" if mode else "")])
    data, field, checksum = source
    write_scene_xml(plan, data, path, res=loaded.size[0], spp=spp, mode=mode, field=field, checksum=checksum)


def _with_clip(path: Path, clip):
    """The XML at ``path`` with the clip plane on its first ``amr`` medium."""
    tree = parse_scene(path)
    medium = amr_elements(tree.getroot())[0]
    for child in list(medium):
        if child.get("name") in ("clip_normal", "clip_offset"):
            medium.remove(child)
    ET.SubElement(medium, "vector", name="clip_normal", value=", ".join(f"{float(x):.9g}" for x in clip[0]))
    ET.SubElement(medium, "float", name="clip_offset", value=f"{float(clip[1]):.9g}")
    tree.write(path)


def _with_iso(path: Path, values, only: bool):
    """The XML at ``path`` with the iso ``values`` (the medium's value units)
    and ``iso_only`` on its first ``amr`` medium, as the view has them (none:
    neither); nested BSDFs beyond the values' count are dropped (one per
    value, in order: the medium refuses more)."""
    tree = parse_scene(path)
    medium = amr_elements(tree.getroot())[0]
    for child in list(medium):
        if child.get("name") in ("iso", "iso_only"):
            medium.remove(child)
    for extra in [c for c in medium if c.tag == "bsdf"][len(values):]:
        medium.remove(extra)
    if values:
        ET.SubElement(medium, "string", name="iso", value=" ".join(f"{float(v):.9g}" for v in values))
        if only:
            ET.SubElement(medium, "boolean", name="iso_only", value="true")
    tree.write(path)


def _scene_xml(loaded: LoadedScene, path: Path, tf_path: Path, camera: OrbitCamera, spec: TFSpec, spp: int,
               mode: str | None = None):
    """The source XML with the view's camera (a lookat), film size, sample
    count, TF (the .json) and density scale on its first amr medium, and
    the lighting ``mode`` on its amrvolpath integrators; relative paths
    still resolve (a <path> to the source's folder)."""

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
    if mode is not None:
        for element in integrator_elements(root):
            set_parameters(element, {"mode": mode})
    tree.write(path)

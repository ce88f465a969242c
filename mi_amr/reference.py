"""Mitsuba's own ``heterogeneous`` + ``gridvolume`` medium on the same data.

The AMR field is resampled at the centres of a dense grid (finest
resolution by default) with the chosen reconstruction, the TF is applied per
voxel, and the result becomes two ``gridvolume`` textures: ``sigma_t``
(opacity, scaled by ``density_scale`` through the medium's ``scale``) and
``albedo`` (rgb). With ``nearest`` reconstruction this is exactly the field
of the ``amr`` medium for any TF; with ``tent`` on single-level data and a TF
whose opacity is linear in value, ``gridvolume``'s trilinear filter makes it
exact too. `reference_scene` does it to every ``amr`` medium of an XML scene
(same ``to_world``, phase function and ``sample_emitters``), the grids
written as ``.vol`` files.
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

import mitsuba as mi
import numpy as np

from .data.cells import AMRCells
from .data.volume import as_method, as_volume
from .device.hash_sampler import DeviceReconstruction
from .plugins.medium import AMRMedium
from .plugins.options import as_transform4f
from .reconstruction import Reconstruction
from .scene_xml import PASS_THROUGH, amr_elements, load_root, parse_scene
from .structures.host_reconstruction import HostReconstruction
from .transfer.function import TransferFunction
from .visibility import box_chords

#: Default memory limit of the dense reference (sigma_t + albedo), bytes.
DEFAULT_MEMORY_LIMIT = 4 << 30


def dense_shape(cells: AMRCells, resolution=None) -> tuple[int, int, int]:
    """``(nz, ny, nx)`` of the dense grid: the finest-level extent, or the
    given per-axis resolution (x, y, z)."""
    lo, hi = cells.bounds
    res = (hi - lo) if resolution is None else np.broadcast_to(np.asarray(resolution, dtype=np.int64), (3,))
    return int(res[2]), int(res[1]), int(res[0])


def dense_bytes(cells: AMRCells, resolution=None) -> int:
    """Memory of the dense reference: 4 float32 channels per voxel."""
    return 16 * int(np.prod(dense_shape(cells, resolution)))


def resample_dense(cells: AMRCells, method: str | Reconstruction = "tent", resolution=None,
                   memory_limit: int = DEFAULT_MEMORY_LIMIT, chunk: int = 1 << 22,
                   device: bool | None = None):
    """Reconstruct the field at the voxel centres of a dense grid covering
    the data bounds. Returns ``(value, found)`` arrays indexed ``[z, y, x]``.

    ``device``: evaluate with the Dr.Jit reconstruction (fast, multi-threaded;
    the default when a JIT variant is active) or with the numpy one."""
    method = as_method(method)
    need = dense_bytes(cells, resolution)
    if need > memory_limit:
        nz, ny, nx = dense_shape(cells, resolution)
        raise MemoryError(
            f"{cells.source}: a dense reference of {nx}x{ny}x{nz} voxels needs "
            f"{need / 2**30:.1f} GiB, above the limit of {memory_limit / 2**30:.1f} GiB; "
            "pass a coarser resolution or a larger memory_limit")
    shape = dense_shape(cells, resolution)
    lo, hi = cells.bounds
    voxel = (hi - lo) / np.array(shape[::-1], dtype=np.float64)   # finest units per voxel (x, y, z)
    if device is None:
        device = mi.variant() is not None and not mi.variant().startswith("scalar")
    volume = as_volume(cells, method)
    if device:
        dev = DeviceReconstruction(volume, method)
        bits = mi.UInt32(dev.hash.level_bits)

        def rec(x, method):
            xr = (x - dev.origin).astype(np.float32)
            v, f = dev.eval(mi.Vector3f(np.ascontiguousarray(xr.T)), bits)
            return v.numpy(), f.numpy()
    else:
        rec = HostReconstruction(volume)
    n = int(np.prod(shape))
    value = np.zeros(n, dtype=np.float32)
    found = np.zeros(n, dtype=bool)
    for s in range(0, n, chunk):
        idx = np.arange(s, min(n, s + chunk))
        ijk = np.stack([idx % shape[2], (idx // shape[2]) % shape[1], idx // (shape[2] * shape[1])], axis=1)
        x = lo + (ijk + 0.5) * voxel
        v, f = rec(x, method)
        value[idx], found[idx] = v, f
    return value.reshape(shape), found.reshape(shape)


def reference_medium(cells: AMRCells, tf: TransferFunction, density_scale: float = 1.0,
                     method: str | Reconstruction = "tent", to_world=None, resolution=None,
                     memory_limit: int = DEFAULT_MEMORY_LIMIT) -> dict:
    """A ``heterogeneous`` medium dict equivalent to an ``amr`` medium with
    the same data, TF, scale, reconstruction and ``to_world``.

    The ``gridvolume`` filter is the method's (`Reconstruction.grid_filter`):
    ``nearest`` uses ``filter_type="nearest"``, ``tent`` uses trilinear.
    """
    method = as_method(method)
    sigma_t, albedo = baked_grids(cells, tf, method, resolution, memory_limit)
    filter_type = method.grid_filter
    to_world = as_transform4f(to_world)

    def grid(channels):
        if channels.shape[-1] == 3 and mi.variant().endswith("_spectral"):
            # gridvolume upsamples colours to spectra only from a VolumeGrid
            return {"type": "gridvolume", "grid": mi.VolumeGrid(np.ascontiguousarray(channels)),
                    "filter_type": filter_type, "to_world": to_world}
        return {"type": "gridvolume", "data": mi.TensorXf(np.ascontiguousarray(channels)),
                "filter_type": filter_type, "to_world": to_world}

    return {"type": "heterogeneous",
            "sigma_t": grid(sigma_t),
            "albedo": grid(albedo),
            "scale": float(density_scale)}


def baked_grids(cells: AMRCells, tf: TransferFunction, method: str | Reconstruction = "tent",
                resolution=None, memory_limit: int = DEFAULT_MEMORY_LIMIT):
    """The dense grids of `reference_medium` as numpy arrays, the TF applied
    per voxel (zero where no cell covers the voxel centre): ``(sigma_t,
    albedo)``, float32, ``[nz, ny, nx, 1]`` (opacity, before
    ``density_scale``) and ``[nz, ny, nx, 3]``."""
    value, found = resample_dense(cells, as_method(method), resolution, memory_limit)
    rgba = tf(value)
    rgba[~found] = 0.0
    return (np.ascontiguousarray(rgba[..., 3:4], dtype=np.float32),
            np.ascontiguousarray(rgba[..., 0:3], dtype=np.float32))


# ---- Image statistics ----------------------------------------------------


def reference_scene(scene_path, work_dir, resolution=None, memory_limit=None, **params):
    """Load an XML scene with every ``amr`` medium replaced by its
    ``heterogeneous`` + ``gridvolume`` equivalent. Grids are written as
    ``.vol`` files into ``work_dir``. Returns ``(scene, media)`` where
    ``media`` lists the AMR media that were replaced."""
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
        amr = load_root(alone, scene_path, params)
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
            if child.tag == "phase" or child.get("name") in PASS_THROUGH:
                new.append(copy.deepcopy(child))
        parent = next(p for p in root.iter() if med in list(p))
        idx = list(parent).index(med)
        parent.remove(med)
        parent.insert(idx, new)
    if not media:
        raise ValueError(f"{scene_path}: the scene has no <medium type=\"amr\">")
    return load_root(root, scene_path, params), media


def emission_absorption_march(cells: AMRCells, tf: TransferFunction, density_scale: float, origins, dirs,
                              background=0.0, brightness: float = 1.0, steps: int | None = 2048) -> np.ndarray:
    """Max's emission-absorption integral of an ``amr`` medium with nearest
    reconstruction, by a dense ray march: what ``amrvolpath``'s
    ``emission_absorption`` mode estimates (docs/design.md section 6d).

    The field is resampled at finest resolution (`resample_dense`, exact for
    nearest), the TF gives ``sigma_t = density_scale * alpha`` and the colour
    ``brightness * rgb`` per voxel, and each ray (``origins``, unit
    ``dirs``, (n, 3), in the medium's unit cube: data bounds -> [0, 1]^3)
    is marched in ``steps`` equal steps over its chord of the cube, each
    step adding ``T (1 - e^(-sigma_t dt)) colour`` (exact within a step of
    one voxel; the error is of the order of the steps that straddle voxel
    faces). ``steps=None`` walks the voxels exactly instead: each ray's
    steps end where it crosses a voxel face (every face plane's crossing,
    sorted per ray), so each step lies in one voxel and the integral is
    exact up to rounding (memory: rays times voxel faces along the axes).
    A ray that leaves sees ``background`` (rgb, or (n, 3)) times the
    transmittance. Returns (n, 3) radiance."""
    value, found = resample_dense(cells, "nearest")                 # [z, y, x]
    shape = np.array(value.shape[::-1])                              # (nx, ny, nz)
    rgba = tf(np.where(found, value, tf.domain[0]).ravel()).reshape(*value.shape, 4)
    sigma = (density_scale * rgba[..., 3] * found).transpose(2, 1, 0)          # [x, y, z]
    colour = (brightness * rgba[..., :3]).transpose(2, 1, 0, 3)
    o, d = np.asarray(origins, np.float64), np.asarray(dirs, np.float64)
    t0, t1 = box_chords(o, d, 0.0, 1.0)
    t1 = np.maximum(t1, t0)
    if steps is None:
        L, T = _exact_voxel_walk(sigma, colour, o, d, t0, t1)
        return L + T[:, None] * np.broadcast_to(np.asarray(background, np.float64), (len(o), 3))
    dt = (t1 - t0) / steps
    L = np.zeros((len(o), 3))
    T = np.ones(len(o))
    for k in range(steps):
        p = o + (t0 + (k + 0.5) * dt)[:, None] * d
        i = np.clip((p * shape).astype(np.int64), 0, shape - 1)
        s = sigma[i[:, 0], i[:, 1], i[:, 2]]
        absorbed = -np.expm1(-s * dt)
        L += (T * absorbed)[:, None] * colour[i[:, 0], i[:, 1], i[:, 2]]
        T *= 1.0 - absorbed
    return L + T[:, None] * np.broadcast_to(np.asarray(background, np.float64), (len(o), 3))


def _exact_voxel_walk(sigma, colour, o, d, t0, t1):
    """``(L, T)`` of Max's integral through the voxels ``sigma`` ([x, y, z])
    and ``colour`` ([x, y, z, 3]) of the unit cube along ``o + t d`` over
    ``[t0, t1]``: steps between consecutive crossings of voxel face planes,
    each in one voxel (sampled at its midpoint), composited with its exact
    absorption."""
    shape = np.array(sigma.shape)
    ts = [t0[:, None], t1[:, None]]
    for axis in range(3):
        planes = np.arange(shape[axis] + 1) / shape[axis]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (planes[None, :] - o[:, axis:axis + 1]) / d[:, axis:axis + 1]
        ts.append(np.where(np.isfinite(t), t, t0[:, None]))
    t = np.sort(np.clip(np.concatenate(ts, axis=1), t0[:, None], t1[:, None]), axis=1)
    dt = np.diff(t, axis=1)
    mid = 0.5 * (t[:, 1:] + t[:, :-1])
    p = o[:, None, :] + mid[..., None] * d[:, None, :]
    i = np.clip((p * shape).astype(np.int64), 0, shape - 1)
    tau = sigma[i[..., 0], i[..., 1], i[..., 2]] * dt
    absorbed = -np.expm1(-tau)
    before = np.exp(-(np.cumsum(tau, axis=1) - tau))                  # T at each step's start
    L = ((before * absorbed)[..., None] * colour[i[..., 0], i[..., 1], i[..., 2]]).sum(axis=1)
    return L, np.exp(-tau.sum(axis=1))

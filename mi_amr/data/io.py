"""Readers and writers for AMR cell files.

* ExaBricks raw pair: ``NAME.cells`` (little-endian ``int32 x, y, z, level``
  records, 16 bytes each) and ``NAME.scalars`` (little-endian float32, one
  per cell, same order).
* ``.npz`` archives with arrays ``pos`` (N,3), ``level`` (N,), ``value`` (N,);
  loaded with ``allow_pickle=False``.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Callable
import json
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..memory import CHUNK, load_bytes, require, structure_bytes
from . import metadata
from .amrb import read_amrb, save_amrb
from .blocks import BlockVolume, DeferredChunk, sample_runs
from .cells import AMRCells
CELL_DTYPE = np.dtype([("x", "<i4"), ("y", "<i4"), ("z", "<i4"), ("level", "<i4")])


def scalars_path_for(cells_path: str | os.PathLike) -> Path:
    """The default scalars file of a ``.cells`` file: same stem, ``.scalars``."""
    p = Path(cells_path)
    return p.with_suffix(".scalars")


def _exabricks_pair(cells_path, scalars_path):
    """Check an ExaBricks pair's sizes; returns the two paths and the cell count."""
    cells_path = Path(cells_path)
    scalars_path = Path(scalars_path) if scalars_path else scalars_path_for(cells_path)
    for p in (cells_path, scalars_path):
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such file")
    nc_bytes = cells_path.stat().st_size
    ns_bytes = scalars_path.stat().st_size
    if nc_bytes % 16:
        raise ValueError(f"{cells_path}: size {nc_bytes} bytes is not a multiple of 16 "
                         "(truncated or not a .cells file)")
    if ns_bytes % 4:
        raise ValueError(f"{scalars_path}: size {ns_bytes} bytes is not a multiple of 4 "
                         "(truncated or not a .scalars file)")
    if nc_bytes // 16 != ns_bytes // 4:
        raise ValueError(f"{cells_path} has {nc_bytes // 16} cells but {scalars_path} has "
                         f"{ns_bytes // 4} values: the files do not belong together or one "
                         "is truncated")
    return cells_path, scalars_path, nc_bytes // 16


def read_exabricks(cells_path, scalars_path=None, *, overlap: str = "error") -> AMRCells:
    """Read an ExaBricks ``.cells`` / ``.scalars`` pair into per-cell records.

    Raises ``ValueError`` naming the file when a size is not a whole number
    of records, when the two files disagree on the cell count, or when the
    content is invalid (see `AMRCells`). For large data use
    `read_exabricks_blocks`, which streams into the compact form.
    """
    cells_path, scalars_path, n = _exabricks_pair(cells_path, scalars_path)
    require(structure_bytes("cells", n), f"{cells_path} ({n} cells)", hint="raise the limit to load it")
    rec = np.fromfile(cells_path, dtype=CELL_DTYPE)
    val = np.fromfile(scalars_path, dtype="<f4")
    pos = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
    cells = AMRCells(pos, rec["level"], val, overlap=overlap, source=str(cells_path))
    cells.meta = metadata.read_sidecar(cells_path)
    return cells


def read_exabricks_blocks(cells_path, scalars_path=None, *, overlap: str = "error",
                          block: int | None = None, chunk: int = CHUNK, method: str = "tent") -> BlockVolume:
    """Stream an ExaBricks pair into a `BlockVolume`: both files are read
    ``chunk`` cells at a time (three passes), validated as strictly as
    `read_exabricks`; no per-cell array of the whole file is made.
    ``method``: the reconstruction the blocks will serve (it weighs the
    block size)."""
    cells_path, scalars_path, n = _exabricks_pair(cells_path, scalars_path)
    if n == 0:
        raise ValueError(f"{cells_path}: contains no cells")
    require(load_bytes(n, chunk), f"{cells_path} ({n} cells)", hint="raise the limit to load it")
    # chunks are read with plain file reads, not a memory map: mapped pages
    # of a 2 GB file would count as the process's memory until unmapped

    def read(s, e, values=True):
        r = np.fromfile(cells_path, dtype="<i4", count=4 * (e - s), offset=16 * s).reshape(-1, 4)
        v = np.fromfile(scalars_path, dtype="<f4", count=e - s, offset=4 * s) if values else None
        return r[:, :3], r[:, 3], v

    def chunks(values=True):                   # read by the worker threads
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            yield DeferredChunk(e - s, lambda s=s, e=e: read(s, e, values))
    meta = metadata.read_sidecar(cells_path)
    vol = BlockVolume.from_chunks(chunks, str(cells_path), overlap=overlap, block=block,
                                  sample=lambda: sample_runs(n, lambda s, e: read(s, e, False)),
                                  method=method, total=n, positions=lambda: chunks(False))
    vol.meta = meta
    return vol


def write_exabricks(cells: AMRCells, cells_path, scalars_path=None) -> tuple[Path, Path]:
    """Write ``cells`` as an ExaBricks pair; returns the two paths."""
    cells_path = Path(cells_path)
    scalars_path = Path(scalars_path) if scalars_path else scalars_path_for(cells_path)
    if np.any(np.abs(cells.pos) > np.iinfo(np.int32).max):
        raise ValueError(f"{cells_path}: positions do not fit in int32")
    rec = np.empty(len(cells), dtype=CELL_DTYPE)
    rec["x"], rec["y"], rec["z"] = cells.pos.T
    rec["level"] = cells.level
    rec.tofile(cells_path)
    cells.values.astype("<f4").tofile(scalars_path)
    side = metadata.sidecar_path(cells_path)
    if getattr(cells, "meta", None):
        side.write_text(json.dumps(cells.meta, indent=1) + "\n")
    elif side.is_file():
        side.unlink()                       # no stale metadata from an earlier file of this name
    return cells_path, scalars_path


#: Prefix of the ``.npz`` members that hold further fields on the cells
#: (``field_temperature``: the field ``temperature``).
FIELD_PREFIX = "field_"


def read_npz(path, *, overlap: str = "error") -> AMRCells:
    """Read an ``.npz`` archive with ``pos``, ``level`` and ``value`` arrays
    (and further fields as ``field_<name>`` arrays, one value per cell)."""
    path = Path(path)
    with _npz_errors(path), np.load(path, allow_pickle=False) as z:
        missing = {"pos", "level", "value"} - set(z.files)
        if missing:
            raise ValueError(f"{path}: missing arrays {sorted(missing)}")
        n = max(int(np.prod(_npy_shape(z, name), dtype=np.float64)) for name in ("pos", "level", "value"))
        require(structure_bytes("cells", n), f"{path} ({n} values per array)",
                hint="raise the limit to load it")
        pos, level, value = z["pos"], z["level"], z["value"]
        fields = {name.removeprefix(FIELD_PREFIX): z[name] for name in z.files if name.startswith(FIELD_PREFIX)}
        meta = _npz_meta(z, path)
    for name, arr in (("pos", pos), ("level", level)):
        if not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"{path}: array '{name}' must be integer, got {arr.dtype}")
    cells = AMRCells(pos, level, value, overlap=overlap, source=str(path), fields=fields)
    cells.meta = meta
    return cells


def _npz_meta(z, path) -> dict:
    """The ``meta`` member of an open ``.npz`` (a JSON string), or {}."""
    if "meta" not in z.files:
        return {}
    try:
        return metadata.check(json.loads(str(z["meta"])), str(path))
    except ValueError as e:
        raise ValueError(f"{path}: bad 'meta' member ({e})") from e


def read_npz_blocks(path, *, overlap: str = "error", method: str = "tent",
                    chunk: int = CHUNK) -> BlockVolume:
    """Stream an ``.npz`` archive into a `BlockVolume`: the three members are
    decompressed side by side, ``chunk`` cells at a time (no whole-data
    array is made); validated as strictly as `read_npz`."""
    path = Path(path)
    with _npz_errors(path), zipfile.ZipFile(path) as z:
        names = {n.removesuffix(".npy") for n in z.namelist()}
        missing = {"pos", "level", "value"} - names
        if missing:
            raise ValueError(f"{path}: missing arrays {sorted(missing)}")
        headers = {}
        for name in ("pos", "level", "value"):
            with z.open(f"{name}.npy") as f:
                headers[name] = _npy_header(f)
    (ps, pfo, pdt), (ls, lfo, ldt), (vs, vfo, vdt) = headers["pos"], headers["level"], headers["value"]
    if len(ps) != 2 or ps[1] != 3:
        raise ValueError(f"{path}: pos must have shape (N, 3), got {ps}")
    n = ps[0]
    if ls != (n,) or vs != (n,):
        raise ValueError(f"{path}: inconsistent sizes: pos has {n} cells, level has {ls}, value has {vs}")
    for name, dt in (("pos", pdt), ("level", ldt)):
        if not np.issubdtype(dt, np.integer):
            raise ValueError(f"{path}: array '{name}' must be integer, got {dt}")
    if pfo or lfo or vfo or _has_objects(pdt, ldt, vdt):     # not streamable: read whole
        return BlockVolume.from_cells(read_npz(path, overlap=overlap), method=method)
    if n == 0:
        raise ValueError(f"{path}: contains no cells")
    require(load_bytes(n, chunk), f"{path} ({n} cells)", hint="raise the limit to load it")

    field_names = sorted(name for name in names if name.startswith(FIELD_PREFIX))
    for name in field_names:
        with _npz_errors(path), zipfile.ZipFile(path) as z, z.open(f"{name}.npy") as f:
            fs, ffo, fdt = _npy_header(f)
        if fs != (n,) or ffo or _has_objects(fdt):
            raise ValueError(f"{path}: field array {name!r} must hold one number per cell ({n}), got {fs} {fdt}")

    def chunks(value_member="value", value_dtype=vdt):
        with _npz_errors(path), zipfile.ZipFile(path) as z:
            members = [z.open(f"{name}.npy") for name in ("pos", "level", value_member)]
            for f in members:                     # skip the headers
                _npy_header(f)
            for s in range(0, n, chunk):
                m = min(chunk, n - s)
                out = []
                for f, dt, shape in zip(members, (pdt, ldt, value_dtype), ((m, 3), (m,), (m,))):
                    nbytes = int(np.prod(shape)) * dt.itemsize
                    buf = f.read(nbytes)
                    if len(buf) != nbytes:
                        raise EOFError("archive member ends early")
                    out.append(np.frombuffer(buf, dtype=dt).reshape(shape))
                yield out[0], out[1], out[2]
            for f in members:
                f.close()
    with _npz_errors(path), np.load(path, allow_pickle=False) as z:
        meta = _npz_meta(z, path)
    vol = BlockVolume.from_chunks(chunks, str(path), overlap=overlap, method=method, total=n)
    vol.meta = meta
    for name in field_names:                      # streamed too, onto the blocks just built
        with _npz_errors(path), zipfile.ZipFile(path) as z, z.open(f"{name}.npy") as f:
            fdt = _npy_header(f)[2]
        with _npz_errors(path):
            vol.add_field(name.removeprefix(FIELD_PREFIX), lambda name=name, fdt=fdt: chunks(name, fdt),
                          skip_missing=overlap == "finest")
    return vol


def _has_objects(*dtypes) -> bool:
    """Whether any dtype holds Python objects (never streamed)."""
    return any(np.dtype(d).hasobject for d in dtypes)


@contextlib.contextmanager
def _npz_errors(path: Path):
    """Errors of a damaged or foreign ``.npz`` as ``ValueError`` naming the file."""
    try:
        yield
    except ValueError as e:
        if str(path) in str(e):
            raise
        raise ValueError(f"{path}: not a valid AMR .npz archive ({e})") from e
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        raise ValueError(f"{path}: cannot read .npz archive ({type(e).__name__}: {e})") from e


def _npy_shape(archive, name: str) -> tuple:
    """Shape of array ``name`` of an open ``.npz`` from its header alone
    (before the data are read: a damaged header must not allocate)."""
    with archive.zip.open(f"{name}.npy") as f:
        return _npy_header(f)[0]


def _npy_header(f) -> tuple:
    """``(shape, fortran_order, dtype)`` of an open ``.npy`` stream, leaving
    it at the start of the data."""
    version = np.lib.format.read_magic(f)
    return (np.lib.format.read_array_header_1_0(f) if version == (1, 0)
            else np.lib.format.read_array_header_2_0(f))


def write_npz(cells: AMRCells, path) -> Path:
    path = Path(path)
    extra = {"meta": np.array(json.dumps(cells.meta))} if getattr(cells, "meta", None) else {}
    extra.update({f"{FIELD_PREFIX}{name}": f for name, f in getattr(cells, "fields", {}).items()})
    np.savez_compressed(path, pos=cells.pos.astype(np.int32 if np.abs(cells.pos).max() < 2**31 else np.int64),
                        level=cells.level, value=cells.values, **extra)
    return path


@dataclass(frozen=True)
class NativeFormat:
    """A format mi-amr reads and writes itself: what it is (for messages and
    the manual), and its readers and writer (``scalars``: the values file
    of an ExaBricks pair; ``overlap``: what to do with overlapping cells;
    ``method``: the reconstruction the blocks are made for)."""
    description: str
    read_cells: Callable        # (path, scalars, overlap) -> AMRCells
    read_volume: Callable       # (path, scalars, overlap, method) -> BlockVolume
    write: Callable             # (AMRCells | BlockVolume, path) -> Path


def _as_cells(data) -> AMRCells:
    return data.to_cells() if isinstance(data, BlockVolume) else data


#: The formats mi-amr reads and writes itself, by suffix: the one table of
#: them (`mi_amr.data.opening` asks it what a path is; docs/manual/data.md).
NATIVE_FORMATS = {
    ".cells": NativeFormat(
        "ExaBricks cells (+ NAME.scalars or NAME-FIELD.scalars)",
        lambda path, scalars, overlap: read_exabricks(path, scalars, overlap=overlap),
        lambda path, scalars, overlap, method: read_exabricks_blocks(path, scalars, overlap=overlap,
                                                                      method=method),
        lambda data, path: write_exabricks(_as_cells(data), path)[0]),
    ".npz": NativeFormat(
        "numpy archive of cells (pos, level, value)",
        lambda path, scalars, overlap: read_npz(path, overlap=overlap),
        lambda path, scalars, overlap, method: read_npz_blocks(path, overlap=overlap, method=method),
        lambda data, path: write_npz(_as_cells(data), path)),
    ".amrb": NativeFormat(                      # the resident form itself (`mi_amr.data.amrb`)
        "mi-amr's native blocks (opens at disk speed)",
        lambda path, scalars, overlap: read_amrb(path).to_cells(),
        lambda path, scalars, overlap, method: read_amrb(path),
        lambda data, path: save_amrb(data, path)),
}


def native_format(path) -> NativeFormat:
    """The `NativeFormat` of ``path`` by its suffix; a ValueError naming
    the suffixes mi-amr reads where it is none of them."""
    path = Path(path)
    fmt = NATIVE_FORMATS.get(path.suffix)
    if fmt is None:
        names = [*NATIVE_FORMATS]
        raise ValueError(f"{path}: unknown AMR file type '{path.suffix}' "
                         f"(expected {', '.join(names[:-1])} or {names[-1]})")
    return fmt


def load_cells(path, scalars=None, *, overlap: str = "error") -> AMRCells:
    """Load AMR cells from any native format (`NATIVE_FORMATS`) by its suffix."""
    return native_format(path).read_cells(Path(path), scalars, overlap)


def load_volume(path, scalars=None, *, overlap: str = "error", method: str = "tent") -> BlockVolume:
    """Load AMR data into its compact resident form (``.cells`` and
    ``.npz`` files are streamed: `read_exabricks_blocks`, `read_npz_blocks`)."""
    return native_format(path).read_volume(Path(path), scalars, overlap, method)


def save_cells(cells: AMRCells | BlockVolume, path) -> Path:
    """Write AMR data to ``.cells`` (+ ``.scalars``), ``.npz`` or ``.amrb``
    (the resident blocks alone: `mi_amr.data.amrb.save_amrb`; with the
    macrocell grids and planning statistics that a medium and a plan read
    first: `mi_amr.native_file.save_data`, which ``mi_amr.save_cells`` is)
    by its suffix; returns the path (of the ``.cells`` file for a pair)."""
    return native_format(path).write(cells, Path(path))

"""The native ``.amrb`` file: a `BlockVolume` as it lies in memory, checksummed.

Loading ``.cells`` data builds the blocks (sorting, hashing, overlap checks);
an ``.amrb`` file keeps the result, so opening it is reading three arrays and
verifying their checksums, at disk speed (docs/design.md section 9b has the
layout, for other tools). Little-endian throughout:

* bytes 0-31, the preamble: magic ``b"MIAMRB\\r\\n"`` (the CR LF catches a
  text-mode copy), ``uint32`` format version (`VERSION`), ``uint32`` header
  length, ``uint32`` CRC-32 of the header, 12 zero bytes;
* the header, UTF-8 JSON: block size, counts, bounds, value range, the
  cell counts the builds need (`BlockVolume.covers_bounds`,
  `BlockVolume.partial_block_cells`), source name, physical metadata, and
  one record per section (name, dtype, shape, offset, bytes, the CRC-32 of
  each `CHUNK_BYTES` chunk);
* the sections, each at a 64-byte aligned offset: ``level`` (uint8, one per
  block), ``coord`` (int32, 3 per block), ``values`` (float32, B^3 per
  block, NaN where a level has no cell); then ``field.NAME`` for every
  further field the header's ``fields`` names (float32, laid out as
  ``values``); then (version 2, optional) the
  macrocell grids that a medium would build first, one per reconstruction
  method named in the header's ``grids``: ``grid.M.vmin``, ``grid.M.vmax``
  (float32), ``grid.M.bits`` (uint32 level masks) and ``grid.M.masks``
  (uint64 value masks, where the method uses them), one entry per
  macrocell, x fastest; the file ends where the last section does.

The header's optional ``stats`` object holds what a scene planned from the
values reads of them (`mi_amr.autoscene.file_stats`, passed by
`mi_amr.native_file.save_native`): ``values``, JSON numbers, and
``arrays``, each ``{"dtype": "<f8", "size": N, "base64": ...}`` (a few
hundred kB at most: histograms), covered by the header's checksum. Readers
that do not know it skip it.

Writing goes to a temporary name beside the target, renamed over it only
once complete and flushed: an interrupted write leaves nothing under the
target name. Reading checks everything it reads and names the file and the
problem in one line (`AmrbError`).
"""

from __future__ import annotations

import base64
import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np

from ..parallel import ordered_map
from ..progress import progress
from .blocks import BlockVolume
from .volume import as_volume

MAGIC = b"MIAMRB\r\n"
#: Format version written; a reader refuses any not in `READ_VERSIONS`.
VERSION = 2
#: Versions this reader opens (version 1 has no stored grids).
READ_VERSIONS = (1, 2)
PREAMBLE = struct.Struct("<8sIII12x")
ALIGN = 64
#: Largest header a reader accepts (a 26 GB file's is a few kB).
MAX_HEADER_BYTES = 1 << 26
#: Bytes per checksummed chunk (chunks are read and verified in parallel).
CHUNK_BYTES = 1 << 24
SECTIONS = (("level", "<u1"), ("coord", "<i4"), ("values", "<f4"))
#: Arrays of a stored macrocell grid (``masks`` optional), one entry per macrocell.
GRID_ARRAYS = (("vmin", "<f4"), ("vmax", "<f4"), ("bits", "<u4"), ("masks", "<u8"))


class AmrbError(ValueError):
    """An ``.amrb`` file that cannot be read as written: the message names
    the file and what is wrong."""


def _aligned(n: int) -> int:
    return -(-n // ALIGN) * ALIGN


def _bytes(a: np.ndarray) -> memoryview:
    """The bytes of a C-contiguous array, writable where it is (empty ones too)."""
    return memoryview(a.reshape(-1).view(np.uint8))


def _chunks(nbytes: int, chunk: int):
    """``(start, length)`` of the checksummed chunks of ``nbytes`` bytes."""
    return [(s, min(chunk, nbytes - s)) for s in range(0, nbytes, chunk)]


def save_amrb(data, path, grids: dict | None = None, stats: dict | None = None) -> Path:
    """The one writer of ``.amrb`` files: ``data`` (an `AMRCells` or a
    `BlockVolume`) as blocks, with ``grids`` (the macrocell grids of every
    reconstruction method, so that a medium opened from the file builds
    none) and ``stats`` (what a planned scene reads of the values) when
    given: both are made floors above the data, and
    `mi_amr.native_file.save_native` passes them; without them the file
    holds the blocks alone. Returns the path."""
    return write_amrb(as_volume(data), path, grids=grids, stats=stats)


def write_amrb(volume: BlockVolume, path, grids: dict | None = None, stats: dict | None = None) -> Path:
    """Write ``volume`` to ``path`` (``.amrb``) atomically: streamed chunk by
    chunk into ``path.tmp-PID``, flushed, then renamed over ``path``.
    ``grids``: macrocell grids to store, by reconstruction method name:
    ``{"res": (3,), "vmin", "vmax", "bits", "masks" (or None), "bins":
    (lo, hi) of the masks' value bins (or None)}`` (made by
    `mi_amr.structures.cost_model.file_grids`); ``stats``: ``{name: JSON
    value or array}``, arrays stored as float64 in the header (made by
    `mi_amr.autoscene.file_stats`)."""
    path = Path(path)
    arrays = {"level": np.ascontiguousarray(volume.level, dtype="<u1"),
              "coord": np.ascontiguousarray(volume.coord, dtype="<i4"),
              "values": np.ascontiguousarray(volume.values, dtype="<f4")}
    order = list(SECTIONS)
    for name, a in volume.fields.items():            # further fields, laid out as the values
        arrays[f"field.{name}"] = np.ascontiguousarray(a, dtype="<f4")
        order.append((f"field.{name}", "<f4"))
    stored = []
    for method, g in (grids or {}).items():
        res = [int(r) for r in g["res"]]
        names = []
        for field, dtype in GRID_ARRAYS:
            if g.get(field) is None:
                continue
            a = np.ascontiguousarray(g[field], dtype=dtype).reshape(-1)
            if a.size != int(np.prod(res)):
                raise ValueError(f"{path}: grid {method!r} {field} has {a.size} entries for {res} macrocells")
            arrays[f"grid.{method}.{field}"] = a
            order.append((f"grid.{method}.{field}", dtype))
            names.append(field)
        stored.append({"method": str(method), "res": res, "arrays": names,
                       "bins": None if g.get("bins") is None else [float(b) for b in g["bins"]]})
    stats_header = None
    if stats is not None:
        stats_header = {"values": {}, "arrays": {}}
        for name, v in stats.items():
            if isinstance(v, np.ndarray):
                a = np.ascontiguousarray(v, dtype="<f8").reshape(-1)
                stats_header["arrays"][str(name)] = {"dtype": "<f8", "size": int(a.size),
                                                     "base64": base64.b64encode(a.tobytes()).decode()}
            else:
                stats_header["values"][str(name)] = v
    covers, partial = volume._cell_counts()
    sections, offset = [], 0
    for name, dtype in order:
        a = arrays[name]
        sections.append({"name": name, "dtype": dtype, "shape": list(a.shape), "nbytes": int(a.nbytes)})
    header = {"block": volume.block, "n_blocks": int(len(volume.level)), "n_cells": volume.n_cells,
              "origin": [int(x) for x in volume.origin], "lo": [int(x) for x in volume.lo],
              "hi": [int(x) for x in volume.hi], "value_range": list(map(float, volume.value_range)),
              "covers_bounds": bool(covers), "partial_block_cells": int(partial),
              "source": str(volume.source), "meta": volume.meta, "chunk_bytes": CHUNK_BYTES,
              "fields": list(volume.fields), "grids": stored, "stats": stats_header}
    # the checksums go into the header, so they are computed first (one pass
    # over memory, in parallel: zlib releases the GIL), then the bytes written
    for s in sections:
        raw = _bytes(arrays[s["name"]])
        s["crc32"] = list(ordered_map(lambda c: zlib.crc32(raw[c[0]:c[0] + c[1]]),
                                      _chunks(s["nbytes"], CHUNK_BYTES)))
    # offsets depend on the header's length, which depends on the offsets' digits: settle it
    data_start = 0
    for _ in range(4):
        offset = data_start
        for s in sections:
            s["offset"] = offset
            offset = _aligned(offset + s["nbytes"])
        text = json.dumps(dict(header, sections=sections), separators=(",", ":")).encode()
        start = _aligned(PREAMBLE.size + len(text))
        if start == data_start:
            break
        data_start = start
    end = sections[-1]["offset"] + sections[-1]["nbytes"]
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f, progress(end, f"writing {path.name}", unit="B") as bar:
            f.write(PREAMBLE.pack(MAGIC, VERSION, len(text), zlib.crc32(text)))
            f.write(text)
            bar.update(f.tell())                   # the header and the padding count too
            for s in sections:
                pad = s["offset"] - f.tell()
                f.write(b"\0" * pad)
                bar.update(pad)
                raw = _bytes(arrays[s["name"]])
                for a, n in _chunks(s["nbytes"], CHUNK_BYTES):
                    f.write(raw[a:a + n])
                    bar.update(n)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def _fail(path, what):
    raise AmrbError(f"{path}: {what}")


def read_header(path) -> dict:
    """The validated header of an ``.amrb`` file (no section is read)."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        pre = f.read(PREAMBLE.size)
        if len(pre) < PREAMBLE.size or not pre.startswith(MAGIC[:6]):
            _fail(path, "not an mi-amr .amrb file (no MIAMRB signature)")
        magic, version, n, crc = PREAMBLE.unpack(pre)
        if magic != MAGIC:
            _fail(path, "damaged signature (copied as text?)")
        if version not in READ_VERSIONS:
            _fail(path, f"format version {version}, this mi-amr reads versions "
                        f"{', '.join(map(str, READ_VERSIONS))}")
        if n > min(size - PREAMBLE.size, MAX_HEADER_BYTES):
            _fail(path, f"truncated in the header ({size} bytes) or a damaged header length ({n})")
        text = f.read(n)
    if len(text) < n:
        _fail(path, f"truncated in the header ({size} bytes)")
    if zlib.crc32(text) != crc:
        _fail(path, "the header is corrupted (checksum mismatch)")
    try:
        header = json.loads(text)
        sections = {s["name"]: s for s in header["sections"]}
        expected = list(SECTIONS)
        for name in header.setdefault("fields", []):
            if not isinstance(name, str) or not name:
                _fail(path, f"field name {name!r} is not a name")
            expected.append((f"field.{name}", "<f4"))
            if sections[f"field.{name}"]["shape"] != sections["values"]["shape"]:
                _fail(path, f"field {name!r} does not hold one value per value slot")
        grid_dtypes = dict(GRID_ARRAYS)
        for g in header.setdefault("grids", []):
            n_cells = int(np.prod([int(r) for r in g["res"]]))
            if len(g["res"]) != 3 or n_cells < 1 or not {"vmin", "vmax", "bits"} <= set(g["arrays"]):
                _fail(path, f"grid {g['method']!r} is inconsistent (resolution {g['res']}, arrays {g['arrays']})")
            for field in g["arrays"]:
                name = f"grid.{g['method']}.{field}"
                expected.append((name, grid_dtypes[field]))
                if sections[name]["shape"] != [n_cells]:
                    _fail(path, f"section {name!r} does not hold one entry per macrocell of {g['res']}")
        stats = header.setdefault("stats", None)
        if stats is not None:
            if not isinstance(stats.get("values"), dict) or not isinstance(stats.get("arrays"), dict):
                _fail(path, "the statistics are malformed")
            for name, a in stats["arrays"].items():
                raw = base64.b64decode(a["base64"], validate=True)
                if a["dtype"] != "<f8" or len(raw) != 8 * int(a["size"]):
                    _fail(path, f"statistic {name!r} is inconsistent")
                a["array"] = np.frombuffer(raw, "<f8").copy()
        if len(expected) != len(sections):
            _fail(path, f"sections {sorted(sections)} are not those the header describes")
        for name, dtype in expected:
            s = sections[name]
            if s["dtype"] != dtype or int(np.prod(s["shape"])) * np.dtype(dtype).itemsize != s["nbytes"]:
                _fail(path, f"section {name!r} is inconsistent ({s['dtype']}, shape {s['shape']}, "
                            f"{s['nbytes']} bytes)")
            chunk = int(header["chunk_bytes"])
            if chunk <= 0 or len(s["crc32"]) != len(_chunks(s["nbytes"], chunk)):
                _fail(path, f"section {name!r} has {len(s['crc32'])} checksums for {s['nbytes']} bytes")
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, AmrbError):
            raise
        _fail(path, f"the header is malformed ({type(e).__name__}: {e})")
    b3, k = int(header["block"]) ** 3, int(header["n_blocks"])
    if (sections["level"]["shape"] != [k] or sections["coord"]["shape"] != [k, 3]
            or sections["values"]["shape"] != [k * b3]):
        _fail(path, f"section shapes do not match {k} blocks of {header['block']}^3 cells")
    at = PREAMBLE.size + n                     # sections: aligned, in order, after the header, apart
    for name, _ in expected:
        off = sections[name]["offset"]
        if not isinstance(off, int) or off < at or off % ALIGN:
            _fail(path, f"section {name!r} has a bad offset {off!r}")
        at = off + sections[name]["nbytes"]
    end = max(s["offset"] + s["nbytes"] for s in sections.values())
    if size < end:
        _fail(path, f"truncated: {size} bytes, the sections end at {end}")
    if size > end:
        _fail(path, f"{size - end} bytes of trailing data after the last section")
    header["sections"] = sections
    header["section_order"] = expected
    return header


def read_amrb(path) -> BlockVolume:
    """The `BlockVolume` stored in ``path``, every byte checked against its
    checksum (chunks read and verified in parallel threads)."""
    path = Path(path)
    header = read_header(path)
    arrays = {}
    fd = os.open(path, os.O_RDONLY)
    try:
        jobs = []
        for name, dtype in header["section_order"]:
            s = header["sections"][name]
            a = np.empty(s["shape"], dtype=dtype)
            arrays[name] = a
            raw = _bytes(a)
            for (start, n), crc in zip(_chunks(s["nbytes"], int(header["chunk_bytes"])), s["crc32"]):
                jobs.append((name, s["offset"] + start, raw[start:start + n], crc))

        def load(job):
            name, at, buf, crc = job
            got = os.preadv(fd, [buf], at) if len(buf) else 0
            if got != len(buf):
                _fail(path, f"truncated in section {name!r}")
            if zlib.crc32(buf) != crc:
                _fail(path, f"section {name!r} is corrupted at byte {at} (checksum mismatch)")
            return len(buf)

        total = sum(len(j[2]) for j in jobs)
        with progress(total, f"reading {path.name}", unit="B") as bar:
            for n in ordered_map(load, jobs):
                bar.update(n)
    finally:
        os.close(fd)
    volume = BlockVolume(header["block"], arrays["level"], arrays["coord"], arrays["values"],
                         np.array(header["origin"], np.int64), np.array(header["lo"], np.int64),
                         np.array(header["hi"], np.int64), header["n_cells"], header.get("source") or str(path),
                         header.get("meta") or {}, value_range=tuple(header["value_range"]),
                         cell_counts=(bool(header["covers_bounds"]), int(header["partial_block_cells"])),
                         fields={name: arrays[f"field.{name}"] for name in header["fields"]})
    for g in header["grids"]:
        grid = {field: arrays.get(f"grid.{g['method']}.{field}") for field, _ in GRID_ARRAYS}
        volume.stored_grids[g["method"]] = dict(grid, res=np.array(g["res"], np.int64),
                                                bins=None if g["bins"] is None else tuple(g["bins"]))
    st = header["stats"]
    # what a planned scene reads of the values (`mi_amr.autoscene.stored_stats`)
    volume.stored_stats = {} if st is None else dict(st["values"], **{n: a["array"] for n, a in st["arrays"].items()})
    return volume

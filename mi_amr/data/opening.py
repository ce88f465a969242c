"""What a user names as data, opened once: the one table of the formats
mi-amr reads itself and the one function that turns a path, a yt data set,
an `AMRCells` or a `BlockVolume` into volume data with its physical extent.

Every entry point (``mi-amr render``, ``info``, ``convert``, ``view``, a run's
outputs, the Python API) asks this module what a path is. The native formats
are one table, `mi_amr.data.io.NATIVE_FORMATS` (suffix -> description,
readers, writer); anything else is handed to yt (`mi_amr.data.yt_import`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from .blocks import BlockVolume
from .cells import AMRCells
from .io import NATIVE_FORMATS, load_volume
from .metadata import physical_box
from .yt_import import from_yt_blocks, load_dataset

#: The suffixes of `NATIVE_FORMATS`, for ``str.endswith`` and ``in``.
NATIVE_SUFFIXES = tuple(NATIVE_FORMATS)


def is_native(path) -> bool:
    """Whether ``path`` names a file of a native format (by its suffix):
    read by mi-amr itself (`mi_amr.data.io`), not by yt."""
    return Path(str(path)).suffix in NATIVE_FORMATS


def is_yt_dataset(data) -> bool:
    """Whether ``data`` is a loaded yt data set (its index is built later)."""
    return hasattr(data, "domain_left_edge") and hasattr(type(data), "index")


def yt_field(field):
    """A field as the user typed it (``"gas,density"``) as yt takes it."""
    return tuple(field.split(",")) if isinstance(field, str) and "," in field else field


def field_scalars(path, field) -> Path | None:
    """The ``NAME-FIELD.scalars`` file of a ``.cells`` file for ``field``
    (ExaBricks' naming for several fields), or None (then ``NAME.scalars``)."""
    path = Path(path)
    if field is None or path.suffix != ".cells":
        return None
    candidate = path.with_suffix("").parent / f"{path.stem}-{field}.scalars"
    return candidate if candidate.is_file() else None


def open_dataset(path, must_exist: bool = True):
    """A path that is not a native file, loaded by yt (`load_dataset`: a
    missing reader package or a damaged file is one line); ``must_exist``:
    a missing path is a `FileNotFoundError` before yt is asked."""
    path = Path(str(path))
    if must_exist and not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    return load_dataset(path)


def open_data(data, field=None, fields=()):
    """``(volume or cells, physical extent (3,), description)`` of ``data``:
    an `AMRCells`, a `BlockVolume`, a native file (`NATIVE_FORMATS`), a
    loaded yt data set, or any path yt can load (then ``field`` names the
    field, and ``fields`` further fields to read onto the same cells). The
    extent is in the data's physical units where their metadata give them
    (else finest cells)."""
    if isinstance(data, (AMRCells, BlockVolume)):
        return data, _extent(data), data.source
    if is_yt_dataset(data):
        return _from_yt(data, field, fields)
    path = Path(str(data))
    if is_native(path):
        scalars = field_scalars(path, field)
        volume = load_volume(path, None if scalars is None else str(scalars))
        return volume, _extent(volume), str(path)
    return _from_yt(open_dataset(path), field, fields)


def volume_checksum(volume: BlockVolume) -> str:
    """A checksum of what a `BlockVolume` holds (blake2b, 128 bits, hex):
    its block size, origin, block levels and coordinates and every value
    slot (empty ones included). A snapshot of data it does not copy records
    it, and a medium loading those data again checks it (``data_checksum``):
    one pass over the values, about 1 GB/s."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.asarray([volume.block], np.int64).tobytes())
    h.update(np.asarray(volume.origin, np.int64).tobytes())
    for a in (volume.level, volume.coord, volume.values):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _extent(data) -> np.ndarray:
    lo, hi = data.bounds
    box = physical_box(data)
    return (hi - lo).astype(np.float64) if box is None else box[1]


def _from_yt(ds, field, fields=()):
    if field is None:
        raise ValueError(f"{ds}: give the field to render (--field NAME), e.g. density "
                         "(mi-amr info DATA lists the fields)")
    volume = from_yt_blocks(ds, yt_field(field), fields=[yt_field(f) for f in fields])
    ext = np.asarray((ds.domain_right_edge - ds.domain_left_edge).to("code_length").d, dtype=np.float64)
    return volume, ext, f"{ds} field {field}"

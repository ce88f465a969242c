"""yt data sets -> AMRCells or the compact BlockVolume.

Grid hierarchies (Enzo, AMReX/BoxLib, FLASH, Athena++, Chombo,
``yt.load_amr_grids``...): yt numbers levels from the coarsest (0) and keeps
every grid's cells, also those covered by finer grids; AMRCells number
levels from the finest (0) and hold leaf cells only. `from_yt` keeps the
cells each grid's ``child_mask`` marks as not covered, inverts the level
numbering and places every cell in finest-level units from the domain's
left edge.

Octrees (RAMSES, ART, ARTIO, ``yt.load_octree``): yt selects the leaf cells
itself; their centres and widths (``fcoords``/``fwidth``, code units) are
rounded to finest-level units and checked to be aligned cells.

One level (uniform grids, single-level outputs) is AMR too, whatever
``refine_by`` says; more than one level needs a refinement ratio of 2.

`load_dataset` wraps ``yt.load``; a package that yt's reader needs and does
not find is one line naming it (`MissingDependency`), while loading and
while reading fields. A field is what a user types (`resolve_field`: yt's
own names, ``TYPE,NAME``, any case), else one line with the closest names
(`FieldNotFound`); whatever yt raises while it opens, indexes or reads an
output (a damaged file's IndexError, or a TypeError of its index parser)
is one line naming the output or its file and what yt said
(`DamagedFile`); a 2-D output is refused before its files are read
(`require_3d`).
"""

from __future__ import annotations

import contextlib
import difflib
import gc
import os
import re
import struct
import sys
import warnings

import mitsuba as mi
import numpy as np

from ..parallel import ordered_map
from .blocks import BlockVolume
from .cells import AMRCells

#: Cells per piece handed to the block builder (an octree's io chunk, e.g. a
#: RAMSES domain or a whole ``yt.load_octree`` data set, is cut into these,
#: converted in threads).
PIECE = 1 << 20

#: Python packages that yt's readers import on demand and the ``yt`` extra
#: of mi-amr brings (import name -> what pip installs).
EXTRA_PACKAGES = {"h5py": "h5py", "libconf": "libconf", "f90nml": "f90nml", "netCDF4": "netCDF4",
                  "astropy": "astropy", "scipy": "scipy", "pandas": "pandas"}

#: yt frontend (its folder in yt/frontends) -> the code's name.
CODE_NAMES = {"enzo": "Enzo", "enzo_e": "Enzo-E", "ramses": "RAMSES", "amrex": "AMReX/BoxLib",
              "boxlib": "AMReX/BoxLib", "athena": "Athena", "athena_pp": "Athena++", "flash": "FLASH",
              "chombo": "Chombo", "gamer": "GAMER", "amrvac": "MPI-AMRVAC", "nc4_cm1": "CM1", "fits": "FITS",
              "art": "ART", "artio": "ARTIO", "cholla": "Cholla", "gdf": "GDF", "parthenon": "Parthenon",
              "open_pmd": "openPMD", "exodus_ii": "Exodus II"}


class MissingDependency(ImportError, ValueError):
    """A Python package that yt needs to read a data set is not installed
    (a ValueError too, so that the command line prints it as one line)."""


class FieldNotFound(ValueError):
    """A field the data set does not have; the message names the closest
    ones and the fields on disk (`resolve_field`)."""


class DamagedFile(ValueError):
    """A file of a simulation output that yt's reader fails on (truncated,
    damaged or missing); ``path`` is the file, when it could be told."""

    def __init__(self, message: str, path=None):
        super().__init__(message)
        self.path = path


def from_yt(ds, field, *, overlap: str = "error") -> AMRCells:
    """Leaf cells of a grid- or octree-based yt data set (Enzo, FLASH,
    AMReX/BoxLib, Athena++, RAMSES, ``yt.load_amr_grids``,
    ``yt.load_octree``...) with the values of ``field`` (a name or a
    ``(type, name)`` tuple), as per-cell records. For large data
    `from_yt_blocks` goes straight to the compact form."""
    with _reading(ds):
        layout = _layout(ds)
        key = resolve_field(ds, field)
        parts = list(_source(ds, layout).cells(key))
    if not parts:
        raise ValueError(f"{ds}: no leaf cells found")
    cells = AMRCells(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                     np.concatenate([p[2] for p in parts]), overlap=overlap,
                     source=f"yt dataset {ds} field {field}")
    cells.meta = _metadata(ds, key, layout)
    return cells


def from_yt_blocks(ds, field, *, overlap: str = "error", method: str = "tent", fields=()):
    """`from_yt` straight into a `BlockVolume`: the leaf cells stream into
    the blocks a grid (uncovered cells by ``child_mask``) or an octree
    piece (at most `PIECE` cells) at a time, with the same validation and
    no per-cell array of the whole data set (an octree's integer positions
    are kept between the passes, 13 bytes per cell, rather than asked of yt
    three times). ``fields``: further fields to read onto the same cells
    (names or ``(type, name)`` tuples; stored under their last name, e.g.
    ``temperature``, `BlockVolume.add_field`). Every field is resolved
    (`resolve_field`) before any value is read."""
    with _reading(ds):
        layout = _layout(ds)
        key = resolve_field(ds, field)
        extras = [(field_key(extra), resolve_field(ds, extra)) for extra in fields]
        src = _source(ds, layout)
        vol = BlockVolume.from_chunks(lambda: src.cells(key), f"yt dataset {ds} field {field}",
                                      overlap=overlap, method=method, positions=src.positions, sample=src.sample)
        vol.meta = _metadata(ds, key, layout)
        for name, extra in extras:
            vol.add_field(name, lambda extra=extra: src.cells(extra))
    return vol


def resolve_field(ds, field) -> tuple:
    """The yt field ``(type, name)`` that ``field`` means: a yt field tuple,
    ``"TYPE,NAME"``, or a bare name as yt resolves it (``density`` ->
    ``("gas", "density")``); failing those, the one field whose name (and
    type, when given) matches in any case (``temperature`` ->
    ``("enzo", "Temperature")``). Else a one-line `FieldNotFound` with
    the closest names and the fields on disk."""
    want = _field_tuple(field)
    known = list(dict.fromkeys([tuple(f) for f in ds.field_list] + [tuple(f) for f in ds.derived_field_list]))
    if isinstance(want, tuple) and want in known:
        return want
    if isinstance(want, str):
        from yt.utilities.exceptions import YTException
        try:
            return tuple(ds._get_field_info(want).name)      # yt's rule for bare names (gas first)
        except (YTException, KeyError):
            pass
    fold = want.lower() if isinstance(want, str) else tuple(s.lower() for s in want)
    same = [f for f in known if (f[1].lower() if isinstance(want, str) else tuple(s.lower() for s in f)) == fold]
    gas = [f for f in same if f[0] == "gas"]
    if len(same) == 1 or len(gas) == 1:
        return (same if len(same) == 1 else gas)[0]
    raise FieldNotFound(_field_message(ds, field, want, known, same))


def _field_tuple(field):
    """``"TYPE,NAME"`` -> ``(TYPE, NAME)``; a bare name stays a string."""
    if isinstance(field, (tuple, list)):
        parts = tuple(str(s).strip() for s in field)
    elif isinstance(field, str):
        parts = tuple(s.strip() for s in field.split(","))
    else:
        raise FieldNotFound(f"field {field!r}: a yt field is a name, 'TYPE,NAME' or a (type, name) tuple")
    if not all(parts) or len(parts) > 2:
        raise FieldNotFound(f"field {_shown(field)!r}: a yt field is NAME or TYPE,NAME (e.g. density or gas,density)")
    return parts[0] if len(parts) == 1 else parts


def _shown(f) -> str:
    """A field as users type it: ``gas,density``."""
    return ",".join(str(s) for s in f) if isinstance(f, (tuple, list)) else str(f)


def _field_message(ds, field, want, known, same) -> str:
    """``DATA: no field 'x' (did you mean A or B?); on disk: ...; yt derives N more``."""
    where = _where(ds)
    if len(same) > 1:
        return (f"{where}: field {_shown(field)!r} could be any of {', '.join(_shown(f) for f in same)}: "
                f"give one as TYPE,NAME")
    names = {}
    for f in known:                       # one spelling per field: the bare name when it is unique
        names.setdefault(f[1], []).append(f)
    typed = _shown(want).lower()
    spelled = {(_shown(f) if isinstance(want, tuple) or len(names[f[1]]) > 1 else f[1]): f for f in known}
    by_fold = {}
    for s in spelled:
        by_fold.setdefault(s.lower(), s)
    close = difflib.get_close_matches(typed, list(by_fold), n=3, cutoff=0.6)
    hint = f" (did you mean {' or '.join(by_fold[c] for c in close)}?)" if close else ""
    disk = [tuple(f) for f in ds.field_list]
    more = len([f for f in known if f not in disk])
    return (f"{where}: no field {_shown(field)!r}{hint}; on disk: {', '.join(_shown(f) for f in disk) or 'none'}"
            + (f"; yt derives {more} more (mi-amr info DATA lists them all)" if more else ""))


def _where(ds) -> str:
    """The path of a data set for messages (its name when it has none)."""
    return str(getattr(ds, "parameter_filename", None) or ds)


def field_key(field) -> str:
    """The name a yt field is stored under beside the main one: its last
    part (``("gas", "temperature")`` -> ``temperature``)."""
    return str(field[-1] if isinstance(field, tuple) else field).split(",")[-1].strip()


# ---- Layout ----------------------------------------------------------------
def _is_octree(index) -> bool:
    from yt.geometry.oct_geometry_handler import OctreeIndex
    return isinstance(index, OctreeIndex) or type(index).__name__ == "ARTIOIndex"


def _layout(ds):
    """``(max_level, left edge, right edge, root cells, finest cell size)``
    of a grid- or octree-based 3D data set (edges and sizes in code
    units, levels counted as yt does: 0 = root), or a ValueError naming
    what is not supported."""
    require_3d(ds)
    index = ds.index
    octree = _is_octree(index)
    if not octree and not hasattr(index, "grids"):
        kind = type(index).__name__
        raise ValueError(f"{ds}: its index ({kind}) has neither grid patches nor an octree: particle-only "
                         f"data and unstructured meshes are not supported; mi-amr reads grid-based AMR (Enzo, "
                         f"AMReX/BoxLib, FLASH, Athena++, Chombo) and octree AMR (RAMSES, ART)")
    if octree:
        max_level = getattr(index, "max_level", None)
        max_level = int(ds.max_level if max_level is None else max_level)
    else:
        max_level = int(index.max_level)
    ratio = getattr(ds, "refine_by", None)
    ratios = np.atleast_1d(np.asarray(2 if ratio is None else ratio, dtype=np.float64))
    if max_level > 0 and not octree and np.any(ratios != 2):
        shown = ", ".join(f"{r:g}" for r in np.unique(ratios))
        raise ValueError(f"{ds}: refine_by = {shown} with {max_level + 1} levels; mi-amr's AMR cells need a "
                         f"refinement ratio of 2 between levels (one level loads with any refine_by)")
    dle = np.asarray(ds.domain_left_edge.to("code_length").d, dtype=np.float64)
    dre = np.asarray(ds.domain_right_edge.to("code_length").d, dtype=np.float64)
    dims0 = np.asarray(ds.domain_dimensions, dtype=np.int64)
    return max_level, dle, dre, dims0, (dre - dle) / (dims0 * (1 << max_level))


def _source(ds, layout):
    return _OctreeLeaves(ds, layout) if _is_octree(ds.index) else _GridLeaves(ds, layout)


class _GridLeaves:
    """Leaf cells of a grid hierarchy, grid by grid."""

    def __init__(self, ds, layout):
        self.ds, self.layout = ds, layout

    def cells(self, field):
        """Per grid: ``(pos (m, 3), level (m,), value (m,))`` of its cells
        not covered by a finer grid, in finest-level units from the domain's
        left edge (levels inverted: 0 = finest)."""
        max_level, dle, _, _, dx_finest = self.layout
        for g in self.ds.index.grids:
            mask = np.asarray(g.child_mask, dtype=bool)
            if not mask.any():
                continue
            amr_level = max_level - int(g.Level)
            start = np.rint((np.asarray(g.LeftEdge.to("code_length").d) - dle) / dx_finest).astype(np.int64)
            ijk = np.argwhere(mask)
            with np.errstate(over="ignore"):       # beyond float32: inf, refused as non-finite later
                values = np.asarray(g[field], dtype=np.float64)[mask].astype(np.float32)
            yield start + ijk * (1 << amr_level), np.full(len(ijk), amr_level, dtype=np.int32), values

    positions = sample = None          # the blocks pass reads the grids as the others do


class _OctreeLeaves:
    """Leaf cells of an octree-indexed data set, one yt ``io`` chunk (a
    RAMSES domain, the whole of a ``yt.load_octree`` data set) at a time, cut
    into pieces of at most `PIECE` cells. Positions (int32, finest-level
    units from the domain's left edge) and levels (uint8, 0 = finest) come
    from yt's ``fcoords``/``fwidth`` on the first pass and are kept for the
    next; values are read from yt on each pass that needs them, in yt's
    order of the cells (the same on every pass)."""

    def __init__(self, ds, layout):
        self.ds, self.layout = ds, layout
        self._pieces: dict[int, list] = {}      # chunk number -> [(pos, level), ...]
        self._complete = False

    def positions(self):
        """The pieces with ``value`` None (no field read once they are known)."""
        if not self._complete:
            yield from self.cells(None)
            return
        for k in sorted(self._pieces):
            for pos, level in self._pieces[k]:
                yield pos, level, None

    def sample(self, runs: int = 8, run: int = 1 << 17):
        """``runs`` runs of ``run`` cells spread over the data (value None),
        for the choice of block size, from the positions known by then."""
        pieces = [p for k in sorted(self._pieces) for p in self._pieces[k]]
        if not self._complete or not pieces:
            yield next(iter(self.positions()))
            return
        ends = np.cumsum([len(lv) for _, lv in pieces])
        for start in np.unique(np.linspace(0, max(int(ends[-1]) - run, 0), runs).astype(np.int64)):
            i = int(np.searchsorted(ends, start, side="right"))
            s = int(start - (ends[i - 1] if i else 0))
            yield pieces[i][0][s:s + run], pieces[i][1][s:s + run], None

    def cells(self, field):
        """``(pos int32 (m, 3), level uint8 (m,), value float32 (m,) or None)``
        per piece of the leaf cells."""
        for k, chunk in enumerate(self.ds.all_data().chunks([], "io")):
            pieces = self._pieces.get(k)
            if pieces is None:
                pieces = self._pieces[k] = list(self._convert(chunk))
            if field is None:
                values = None
            else:
                values = np.asarray(chunk[field], dtype=np.float64).ravel()
                n = sum(len(lv) for _, lv in pieces)
                if len(values) != n:
                    raise ValueError(f"{self.ds}: field {field} has {len(values)} values in yt's chunk {k}, "
                                     f"which holds {n} leaf cells")
            s = 0
            for pos, level in pieces:
                with np.errstate(over="ignore"):   # beyond float32: inf, refused as non-finite later
                    piece = None if values is None else values[s:s + len(level)].astype(np.float32)
                yield pos, level, piece
                s += len(level)
        self._complete = True

    def _convert(self, chunk):
        """The chunk's leaf cells as ``(pos, level)`` pieces (`octree_cells`)."""
        max_level, dle, _, _, dxf = self.layout
        centres = chunk.fcoords.to("code_length").d
        widths = chunk.fwidth.to("code_length").d
        yield from ordered_map(lambda s: octree_cells(centres[s:s + PIECE], widths[s:s + PIECE], dle, dxf,
                                                      max_level, self.ds), range(0, len(centres), PIECE))


def octree_cells(centres, widths, left_edge, finest, max_level: int, what="octree data"):
    """Cells given by centre and width (``(m, 3)`` each, code units) ->
    ``(pos int32 (m, 3), level uint8 (m,))``: corners in finest-level units
    from ``left_edge``, level ``log2(width / finest)`` (0 = finest, at most
    ``max_level``), rounded. A width that is not a power-of-two multiple of
    ``finest`` (within 1e-6), a corner further than 1e-3 finest cells from
    an integer or not a multiple of the cell's width is a ValueError naming
    the cell."""
    centres, widths = np.asarray(centres, np.float64), np.asarray(widths, np.float64)
    left_edge, inv = np.asarray(left_edge, np.float64), 1.0 / np.asarray(finest, np.float64)
    mant, exp = np.frexp(widths[:, 0] * inv[0])
    level = (exp - 1 + (mant >= 0.7071067811865476)).astype(np.int32)     # the nearest power of two
    size = np.ldexp(1.0, level)
    pos = np.empty(centres.shape, np.int32)
    off = wrong = 0.0
    ok = len(level) == 0 or (level.min() >= 0 and level.max() <= max_level)
    for a in range(3):                     # column by column: no (m, 3) temporaries
        x = (centres[:, a] - left_edge[a]) * inv[a]
        x -= 0.5 * size
        p = np.rint(x)
        x -= p
        off = max(off, float(np.abs(x).max(initial=0.0)))
        w = widths[:, a] * inv[a]
        w /= size
        wrong = max(wrong, float(np.abs(w - 1.0).max(initial=0.0)))
        ok = ok and p.min(initial=0) >= 0 and p.max(initial=0) < 2**31
        if ok:
            pos[:, a] = p
    ok = ok and off <= 1e-3 and wrong <= 1e-6
    if ok and len(level):
        ok = not np.any((pos[:, 0] | pos[:, 1] | pos[:, 2]) & ((np.int32(1) << level) - 1))
    if not ok:
        i = _first_bad_cell(centres, widths, left_edge, inv, max_level)
        raise ValueError(f"{what}: the cell with centre {centres[i].tolist()} and width {widths[i].tolist()} "
                         f"(code units) is not an aligned cell of a level 0..{max_level} (cell size "
                         f"{(1.0 / inv).tolist()} times a power of two, corner a multiple of its width)")
    return pos, level.astype(np.uint8)


def _first_bad_cell(centres, widths, left_edge, inv, max_level) -> int:
    """Index of the first cell `octree_cells` refuses (the slow, per-cell check)."""
    w = widths * inv
    level = np.rint(np.log2(np.maximum(w[:, 0], 1e-300)))
    size = np.exp2(level)[:, None]
    corner = (centres - left_edge) * inv - 0.5 * size
    pos = np.rint(corner)
    ok = ((level >= 0) & (level <= max_level) & np.all(np.abs(w / size - 1) <= 1e-6, 1)
          & np.all(np.abs(corner - pos) <= 1e-3, 1) & np.all(np.mod(pos, size) == 0, 1) & np.all(pos >= 0, 1))
    return int(np.argmin(ok))


# ---- yt.load and missing packages -------------------------------------------
def load_dataset(path):
    """``yt.load(path)``, or one line saying what is missing: yt itself, a
    package that yt's reader for this format imports (`MissingDependency`),
    or a format yt does not recognise (ValueError)."""
    try:
        import yt
    except ImportError as e:
        raise MissingDependency(f"{path}: reading this data needs yt: pip install 'mi-amr[yt]' ({e})",
                                name="yt") from e
    from yt.utilities.exceptions import YTAmbiguousDataType, YTUnidentifiedDataType
    with _reading(None, path), warnings.catch_warnings():
        # yt's warning that a reader lacks a package: the error that follows (now or when
        # fields are read) names it in one line
        warnings.filterwarnings("ignore", message="This dataset appears to be of type")
        try:
            ds = require_3d(yt.load(str(path)))
        except YTAmbiguousDataType as e:
            names = ", ".join(c.__name__ for c in e.candidates)
            raise ValueError(f"{path}: yt finds it could be any of {names}") from e
        except YTUnidentifiedDataType as e:
            raise ValueError(f"{path}: {_unidentified(path)}") from e
    with _reading(ds, path):
        ds.index                      # built here, so that a damaged index is one line too
    return ds


def _unidentified(path) -> str:
    """Why yt did not recognise ``path``, in one line: the readers it could
    not try for want of a package, if any."""
    from yt.utilities.hierarchy_inspection import get_classes_with_missing_requirements
    missing = {}
    for cls, packages in get_classes_with_missing_requirements().items():
        for p in packages:
            missing.setdefault(p, []).append(cls.__name__.removesuffix("Dataset"))
    if not missing:
        return "yt does not recognise this as a data set of any format it reads"
    ours = [p for p in missing if p in EXTRA_PACKAGES]
    told = "; ".join(f"'{p}' for {', '.join(missing[p])}" for p in missing)
    hint = "pip install 'mi-amr[yt]'" if ours else f"pip install {' '.join(sorted(missing))}"
    return (f"yt does not recognise this as a data set of any format it could try; readers it could not "
            f"try for want of a Python package: {told} ({hint})")


def require_3d(ds):
    """``ds`` if it is 3-D, else a one-line ValueError saying it is 2-D (or
    1-D). RAMSES: yt says 3 whatever the output holds, so the ``ndim`` of
    the info file decides, before yt reads a record of its files."""
    dim = int(getattr(ds, "dimensionality", 3))
    if _code_name(ds, ValueError()) == "RAMSES":
        dim = int(getattr(ds, "parameters", {}).get("ndim", dim))
    if dim < 3:
        code = _code_name(ds, ValueError())
        raise ValueError(f"{_where(ds)}: a {dim}-D {code + ' ' if code else ''}output; mi-amr renders 3-D "
                         f"volumes only")
    return ds


#: What yt's readers raise on a truncated or damaged file (a numpy reshape of
#: too few bytes, an HDF5 file cut short, a Fortran record whose lengths
#: disagree, a header that no longer parses). Any other exception raised
#: inside yt is one `DamagedFile` line too (a header line replaced by another
#: ends in a TypeError of yt's Enzo index parser), worded as yt failing on
#: the output rather than as damage for sure.
DAMAGE_ERRORS = (OSError, ValueError, EOFError, struct.error, IndexError, KeyError, AttributeError)


@contextlib.contextmanager
def _reading(ds, path=None):
    """An ImportError raised by yt while it loads, indexes or reads ``ds``
    (or the data at ``path``) becomes one `MissingDependency` line naming
    the package and how to install it; any other exception raised inside yt
    (not in mi-amr's own code) but a MemoryError one `DamagedFile` line
    naming the output, or the file of it, and what yt said
    (`_damage_message`). The original stays the `DamagedFile`'s cause
    (``mi-amr --traceback`` shows it)."""
    try:
        yield
    except (MissingDependency, FieldNotFound, DamagedFile):
        raise
    except ImportError as e:
        raise MissingDependency(_missing_message(e, ds, path), name=_package(e)) from e
    except MemoryError:                          # data too large, not damaged: the command line says so
        raise
    except Exception as e:
        if not _raised_in_yt(e):
            raise
        file = _file_of(e, ds, path)
        message = _damage_message(e, ds, path, file)
        _release_quietly(e)
        raise DamagedFile(message, file) from e


def _release_quietly(e: BaseException):
    """Free the objects yt had half built when ``e`` was raised (an index
    whose ``__init__`` failed), which the traceback's frames hold: their
    ``__del__`` fails on the missing attributes, and Python would print that
    as an 'Exception ignored' traceback whenever they are collected. Done
    here, with those reports from yt's own code silenced; the traceback
    keeps its lines (``--traceback``), not the frames' local variables."""
    tb, frames = e.__traceback__, []
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    hook = sys.unraisablehook

    def quiet(report):
        where = getattr(report.object, "__module__", None) or type(report.object).__module__ or ""
        if not where.startswith("yt."):
            hook(report)
    sys.unraisablehook = quiet
    try:
        while frames:
            frame = frames.pop()
            if frame.f_code.co_filename != __file__:
                try:
                    frame.clear()
                    frame.f_locals                     # drops the snapshot `_file_of` read (Python < 3.13)
                except RuntimeError:                   # a frame still running (ours, or a caller's)
                    pass
            del frame
        gc.collect()
    finally:
        sys.unraisablehook = hook


def _raised_in_yt(e: BaseException) -> bool:
    """Whether the innermost frame of yt or mi-amr that ``e`` went through
    is yt's (h5py's and numpy's frames below yt's count as yt's)."""
    owner, tb = None, e.__traceback__
    ours = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    while tb is not None:
        name = tb.tb_frame.f_code.co_filename
        if os.path.abspath(name).startswith(ours + os.sep):
            owner = "mi_amr"
        elif re.search(r"(^|[/\\])yt[/\\]", name):
            owner = "yt"
        tb = tb.tb_next
    return owner == "yt"


def _file_of(e: BaseException, ds, path) -> str | None:
    """The data file the reader was at when ``e`` was raised: the innermost
    frame's local naming an existing file of the output (a path, an open
    file, or an object's ``fname``/``filename``; a RAMSES domain's
    ``amr_fn``, whose reader is Cython; an index's ``index_filename``, e.g.
    Enzo's ``.hierarchy``), else the file of a
    FileNotFoundError, else None."""
    if isinstance(e, FileNotFoundError) and e.filename:
        return os.fsdecode(e.filename)
    origin = getattr(ds, "parameter_filename", None) or path
    folder = os.path.dirname(os.path.abspath(str(origin))) if origin is not None else None
    frames, tb = [], e.__traceback__
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    for frame in reversed(frames):
        for value in list(frame.f_locals.values()):
            attrs = getattr(value, "__dict__", None) or {}
            for c in (value, getattr(value, "name", None) if hasattr(value, "read") else None,
                      attrs.get("fname"), attrs.get("filename"), attrs.get("amr_fn"),
                      attrs.get("index_filename")):
                if isinstance(c, (str, bytes, os.PathLike)):
                    try:
                        c = os.path.abspath(os.fsdecode(c))
                    except (TypeError, ValueError):
                        continue
                    if (os.path.isfile(c) and not c.endswith((".py", ".pyx", ".so"))
                            and (folder is None or c.startswith(folder + os.sep))):
                        return c
    return None


def _damage_message(e: BaseException, ds, path, file) -> str:
    """``FILE: truncated or damaged (what the reader said)``, one line; for
    an exception that is not one of `DAMAGE_ERRORS`, ``OUTPUT: yt failed
    reading ... (what yt said)``."""
    code = _code_name(ds, e)
    what = f"this {code} output" if code else "this output"
    said = " ".join(str(e).split()) or type(e).__name__
    yt_said = f"(yt: {type(e).__name__}: {said})"[:600]
    if isinstance(e, FileNotFoundError):
        return f"{file or path or _where(ds)}: missing, and {what} needs it"
    if not isinstance(e, DAMAGE_ERRORS):
        return (f"{file or path or _where(ds)}: yt failed reading {what}; a file of it may be truncated or "
                f"damaged {yt_said}")
    if file is None:
        return f"{path or _where(ds)}: a file of {what} is truncated or damaged {yt_said}"
    return f"{file}: truncated or damaged file of {what} {yt_said}"


def _package(e: ImportError) -> str | None:
    """The top-level package an ImportError is about (yt's on-demand imports
    raise the original ModuleNotFoundError, or an ImportError saying
    'lazy-import NAME')."""
    name = getattr(e, "name", None)
    if not name:
        m = re.search(r"lazy-import (\S+?)\.?(\s|$)", str(e)) or re.search(r"No module named '([^']+)'", str(e))
        name = m.group(1) if m else None
    return name.split(".")[0] if name else None


def _missing_message(e: ImportError, ds, path) -> str:
    pkg = _package(e)
    code = _code_name(ds, e)
    what = f"this {code} output" if code else "this data"
    where = path if path is not None else ds
    if pkg is None:
        first = str(e).splitlines()[0] if str(e) else type(e).__name__
        return f"{where}: yt could not import what it needs to read {what}: {first}"
    pip = EXTRA_PACKAGES.get(pkg)
    hint = "pip install 'mi-amr[yt]'" if pip else f"pip install {pkg}"
    return f"{where}: reading {what} needs the Python package '{pip or pkg}': {hint}"


def _code_name(ds, e: BaseException) -> str | None:
    """The simulation code of a data set (from its yt frontend), or of the
    yt frontend the error was raised in."""
    module = type(ds).__module__ if ds is not None else ""
    if not module.startswith("yt.frontends."):
        module = ""
        tb = e.__traceback__
        while tb is not None:                      # the innermost frame in a frontend
            m = re.search(r"[/\\]yt[/\\]frontends[/\\](\w+)[/\\]", tb.tb_frame.f_code.co_filename)
            if m:
                module = f"yt.frontends.{m.group(1)}"
            tb = tb.tb_next
    if not module:
        return None
    frontend = module.split(".")[2]
    return None if frontend == "stream" else CODE_NAMES.get(frontend, frontend)


def _metadata(ds, field, layout) -> dict:
    max_level, dle, dre, dims0, _ = layout
    try:
        units = str(ds.field_info[field].units) if field in ds.field_info else ""
    except Exception:          # yt's field lookup varies by frontend: units are informative only
        units = ""
    return {"domain_left_edge": dle.tolist(), "domain_right_edge": dre.tolist(),
            "domain_cells": (dims0 * (1 << max_level)).tolist(), "length_unit": "code_length",
            "field": str(field), "units": units, "code": str(getattr(ds, "dataset_type", type(ds).__name__))}


def world_transform(ds):
    """``to_world`` that maps the unit cube onto the dataset's domain (code
    units), for an ``amr`` medium built from `from_yt` data that covers the
    whole domain."""
    dle = [float(x) for x in ds.domain_left_edge.to("code_length").d]
    ext = [float(b - a) for a, b in zip(ds.domain_left_edge.to("code_length").d,
                                        ds.domain_right_edge.to("code_length").d)]
    return mi.ScalarTransform4f().translate(dle) @ mi.ScalarTransform4f().scale(ext)

"""The compact resident form of AMR data: aligned blocks of same-level cells.

Each level's index space is cut into aligned blocks of ``B x B x B`` cells
(``B`` a power of two, chosen per data set by memory, see `choose_block_size`).
A block that holds at least one cell stores all ``B^3`` values, x fastest,
with NaN where the level has no cell; nothing else is kept per cell (about
4 bytes per cell on block-structured data, where boxes fill whole blocks).
Point location hashes the block coordinate of a level (docs/design.md
section 9); builders read the data back block by block (`BlockVolume.block_chunks`)
or as cell records chunk by chunk (`BlockVolume.cell_chunks`).

Coordinates: finest-level cell units, as in `mi_amr.data.cells`. ``origin``
is the lower data corner aligned to the coarsest level, so that level and
block coordinates ``((pos - origin) >> L) >> log2(B)`` are never negative.
"""

from __future__ import annotations

import numpy as np
import mitsuba as mi

from ..memory import CHUNK
from ..parallel import ordered_map
from ..progress import progress
from ..reconstruction import Reconstruction, reconstruction_method
from ..core.block_keys import (KEY_AXIS_BITS, UPPER_OFFSETS, block_keys, block_offsets, distinct_keys, fits_packed,
                         ghost_blocks, key_offset, level_coords, packed_keys, slot_index, unpack_keys)
from .cells import MAX_LEVEL, AMRCells, check_cells

#: Block sizes tried by `choose_block_size` (cells per side).
BLOCK_SIZES = (2, 4, 8, 16)
#: Bytes of one entry in the point-location hash: key 8 B and payload 4 B at
#: a load factor of at most 0.35, tables rounded up to powers of two (x1.4).
HASH_BYTES_PER_BLOCK = 12 / 0.35 * 1.4
#: Bytes per block of the tent stencil index: 7 neighbour indices.
NEIGHBOUR_BYTES_PER_BLOCK = 28
#: Cells per contiguous run of the sample that chooses the block size.
SAMPLE = 1 << 17


class DeferredChunk:
    """A chunk of raw cells read by the worker thread that takes it (so
    reading a file overlaps the work on other chunks): ``n`` cells, ``read()``
    returns ``(pos, level, value)``. Chunk sources may yield these or plain
    triples."""

    __slots__ = ("n", "read")

    def __init__(self, n: int, read):
        self.n, self.read = int(n), read


def _resolve(chunk):
    """The ``(pos, level, value)`` of a chunk, read now if it is deferred."""
    return chunk.read() if isinstance(chunk, DeferredChunk) else chunk


class BlockVolume(mi.Object):
    """AMR cells stored as aligned same-level blocks (see module docstring).

    Attributes (numpy)
    ------------------
    block : int                  cells per block side ``B``
    level : uint8 (K,)           level of each block
    coord : int32 (K, 3)         block coordinate at that level (x, y, z)
    values : float32 (K * B^3,)  cell values, NaN where no cell
    origin, lo, hi : int64 (3,)  key origin and data bounds (finest units)
    n_cells : int                cells present
    source : str                 name used in error messages
    """

    def __init__(self, block, level, coord, values, origin, lo, hi, n_cells, source, meta=None,
                 value_range=None, cell_counts=None, fields=None):
        """``value_range`` and ``cell_counts`` (``(covers_bounds,
        partial_block_cells)``): known already (a native file stores them);
        else computed here (value range) or on first use (cell counts).
        ``fields``: further named fields on the same cells, each laid out
        as ``values`` (`add_field`)."""
        super().__init__()
        self.block = int(block)
        self.log2_block = int(self.block).bit_length() - 1
        self.level = level
        self.coord = coord
        self.values = values
        self.origin, self.lo, self.hi = origin, lo, hi
        self.n_cells = int(n_cells)
        self.source = source
        self.meta = dict(meta or {})         # physical metadata (`mi_amr.data.metadata`)
        # macrocell grids read from a native file, by reconstruction method
        # (`mi_amr.data.amrb`), used by `MacrocellGrid` instead of a build
        self.stored_grids = {}
        #: further named fields on the same cells (float32, laid out as
        #: ``values``, NaN where no cell): e.g. a temperature beside the
        #: density that ``values`` holds (`add_field`)
        self.fields = {}
        for name, a in (fields or {}).items():
            a = np.asarray(a, dtype=np.float32)
            if a.shape != self.values.shape:
                raise ValueError(f"{source}: field {name!r} has {a.size} values for {self.values.size}")
            self.fields[str(name)] = a
        self._covers = None if cell_counts is None else tuple(cell_counts)
        if value_range is None:
            self._update_range()
        else:
            self._range = (float(value_range[0]), float(value_range[1]))

    def __reduce__(self):
        return (BlockVolume, (self.block, self.level, self.coord, self.values, self.origin, self.lo,
                              self.hi, self.n_cells, self.source, self.meta, None, None, self.fields))

    def _update_range(self):
        self._range = scan_values(self.values, self.level, self.block)[1]

    # ---- Construction --------------------------------------------------
    @classmethod
    def from_dense(cls, values: np.ndarray, block: int = 16, source: str = "dense volume") -> "BlockVolume":
        """One level of unit cells from a dense array indexed ``[z, y, x]``
        (NaN: no cell), cut into ``block^3`` blocks; blocks with no cell
        are left out. Bounds: ``[0, (nx, ny, nz)]``."""
        v = np.asarray(values, dtype=np.float32)
        if v.ndim != 3:
            raise ValueError(f"{source}: a dense volume must be 3-D, got shape {v.shape}")
        if block not in BLOCK_SIZES:
            raise ValueError(f"{source}: block must be one of {BLOCK_SIZES}, got {block}")
        nz, ny, nx = v.shape
        pad = [(0, (-n) % block) for n in v.shape]
        v = np.pad(v, pad, constant_values=np.nan)
        bz, by, bx = (n // block for n in v.shape)
        blocks = v.reshape(bz, block, by, block, bx, block).transpose(0, 2, 4, 1, 3, 5).reshape(-1, block ** 3)
        keep = ~np.isnan(blocks).all(axis=1)
        k = np.nonzero(keep)[0]
        coord = np.stack([k % bx, (k // bx) % by, k // (bx * by)], axis=1).astype(np.int32)
        return cls(block, np.zeros(len(k), np.uint8), coord, np.ascontiguousarray(blocks[keep]).reshape(-1),
                   np.zeros(3, np.int64), np.zeros(3, np.int64), np.array([nx, ny, nz], np.int64),
                   int(np.count_nonzero(~np.isnan(blocks[keep]))), source)

    @classmethod
    def from_cells(cls, cells: AMRCells, block: int | None = None,
                   method: str | Reconstruction = "tent") -> "BlockVolume":
        """Blocks of validated ``cells`` (in memory); ``method``: the
        reconstruction they will serve (it weighs the block size)."""
        lo, hi = cells.bounds
        chunks = lambda: ((cells.pos[s:s + CHUNK], cells.level[s:s + CHUNK], cells.values[s:s + CHUNK])  # noqa: E731
                          for s in range(0, len(cells), CHUNK))
        vol = _build(chunks, lo, hi, int(cells.level.max()), cells.source, "error", block,
                     lambda: sample_runs(len(cells), lambda s, e: (cells.pos[s:e], cells.level[s:e], None)),
                     method, n_cells=len(cells))
        vol.meta = dict(getattr(cells, "meta", {}))
        for name, f in getattr(cells, "fields", {}).items():
            vol.add_field(name, lambda f=f: ((cells.pos[s:s + CHUNK], cells.level[s:s + CHUNK], f[s:s + CHUNK])
                                             for s in range(0, len(cells), CHUNK)))
        return vol

    @classmethod
    def from_chunks(cls, chunks, source: str, overlap: str = "error", block: int | None = None,
                    sample=None, method: str | Reconstruction = "tent", total: int | None = None,
                    positions=None):
        """Blocks from a re-iterable source of raw cells: ``chunks()`` yields
        ``(pos (m, 3) ints, level (m,), value (m,))``, read three times
        (validation and bounds, blocks, values). Each chunk is validated as
        `AMRCells` validates; overlaps across chunks are found from the
        blocks. ``sample()`` yields a few contiguous runs of cells from
        across the data, from which the block size is chosen (default: the
        first chunk). ``positions()``, when given, yields the same chunks
        with ``value`` None, for the pass that needs no values."""
        lo = np.full(3, np.iinfo(np.int64).max)
        hi = np.full(3, np.iinfo(np.int64).min)
        lmax, n = 0, 0
        bar = progress(3 * total if total else None, f"loading {source}")

        def numbered():                          # each chunk with the index of its first cell
            start = 0
            for chunk in chunks():
                yield start, chunk
                start += chunk.n if isinstance(chunk, DeferredChunk) else len(chunk[1])

        def check(item):                         # validated and measured in threads, in order
            start, chunk = item
            pos, level, value = _resolve(chunk)
            if not len(value):
                check_cells(pos, level, value, source, start)
                return 0, None, None, 0
            measured = _check_and_measure(pos, level, value)
            if measured is None:                 # something is wrong (or unusual dtypes): the full check
                check_cells(pos, level, value, source, start)
                w = np.int64(1) << np.asarray(level).astype(np.int64)
                measured = pos.min(axis=0), (pos + w[:, None]).max(axis=0), int(np.max(level))
            return (len(value),) + tuple(measured)

        for m, clo, chi, cmax in ordered_map(check, numbered()):
            bar.update(m)
            if m:
                lo, hi, lmax, n = np.minimum(lo, clo), np.maximum(hi, chi), max(lmax, cmax), n + m
        if n == 0:
            bar.close()
            raise ValueError(f"{source}: contains no cells")
        if np.any(hi - lo > 2**31 - 1):
            bar.close()
            raise ValueError(f"{source}: bounding box {lo.tolist()}..{hi.tolist()} exceeds 2**31 finest cells")
        with bar:
            return _build(chunks, lo, hi, lmax, source, overlap, block, sample, method, bar, positions, n)

    # ---- Properties ----------------------------------------------------
    def __len__(self):
        return self.n_cells

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.lo, self.hi

    @property
    def levels(self) -> np.ndarray:
        return np.unique(self.level).astype(np.int32)

    @property
    def value_range(self) -> tuple[float, float]:
        return self._range

    @property
    def covers_bounds(self) -> bool:
        """Whether the cells fill their bounding box (no holes): their
        volumes add up to the box's (cells never overlap here), so every
        point of it has a value."""
        return self._cell_counts()[0]

    @property
    def partial_block_cells(self) -> int:
        """Cells in blocks that are not full (where bricks are found cell by
        cell rather than cut from whole blocks)."""
        return self._cell_counts()[1]

    def _cell_counts(self):
        """``(covers_bounds, partial_block_cells)``, counted block by block, once."""
        if self._covers is None:
            _, _, volume, partial = scan_values(self.values, self.level, self.block)
            self._covers = (volume == int(np.prod((self.hi - self.lo).astype(np.int64))), partial)
        return self._covers

    @property
    def nbytes(self) -> int:
        """Resident host bytes: values, further fields and per-block headers."""
        return (self.values.nbytes + sum(a.nbytes for a in self.fields.values())
                + self.level.nbytes + self.coord.nbytes)

    # ---- Further fields on the same cells ---------------------------------
    def field(self, name: str | None) -> np.ndarray:
        """The values of field ``name`` in block layout: ``values`` for None,
        else `fields` (a ValueError naming the fields there are otherwise)."""
        if name is None:
            return self.values
        if name not in self.fields:
            have = ", ".join(repr(n) for n in sorted(self.fields)) or "none"
            raise ValueError(f"{self.source}: no field {name!r} (further fields: {have})")
        return self.fields[name]

    def weighted_values(self, field: str | None = None, max_cells: int = 1 << 22):
        """Yield ``(values float64, volume weights)`` of the present cells, a
        few blocks at a time (weights in finest-cell volumes, 8^level);
        ``field``: a further field (None: the values)."""
        values = self.field(field)
        b3 = self.block ** 3
        step = max(1, max_cells // b3)
        for s in range(0, len(self.level), step):
            v = values[s * b3:(s + step) * b3].reshape(-1, b3)
            w = np.broadcast_to(np.exp2(3.0 * self.level[s:s + step].astype(np.float64))[:, None], v.shape)
            ok = ~np.isnan(v)
            yield v[ok].astype(np.float64), w[ok]

    def field_range(self, name: str | None) -> tuple[float, float]:
        """``(min, max)`` of field ``name`` over the cells."""
        if name is None:
            return self.value_range
        return scan_values(self.field(name), self.level, self.block)[1]

    def add_field(self, name: str, chunks, skip_missing: bool = False) -> np.ndarray:
        """Place a further per-cell field ``name`` on this volume's cells, laid
        out as ``values``: ``chunks()`` yields ``(pos (m, 3), level (m,),
        value (m,))`` of exactly this volume's cells, in any order and
        chunking. A cell that is not one of the volume's, a cell given twice
        or left out, or a value that is not finite is a ValueError naming
        the field; memory grows by the field alone. ``skip_missing``: cells
        the volume does not have are passed over (data loaded with
        ``overlap='finest'``, which dropped covered cells)."""
        name = str(name)
        if not name or name in self.fields:
            raise ValueError(f"{self.source}: field name {name!r} is empty or used already")
        out = np.full(self.values.shape, np.nan, dtype=np.float32)
        packed = fits_packed(self.coord)
        keys = block_keys(self.coord, self.level, packed)
        order = np.argsort(keys)
        placed = 0
        for pos, level, value in chunks():
            pos, level = np.asarray(pos), np.asarray(level)
            value = np.asarray(value, dtype=np.float32)
            if not np.all(np.isfinite(value)):
                raise ValueError(f"{self.source}: field {name!r} has NaN or Inf values")
            q = np.stack(level_coords(pos, level, self.origin), axis=1).astype(np.int64)
            k = block_keys(q >> self.log2_block, level, packed)
            i = np.minimum(np.searchsorted(keys, k, sorter=order), len(keys) - 1)
            hit = (keys[order[i]] == k) & np.all(q >= 0, axis=1)
            slot = slot_index(order[i], q, self.block)
            hit[hit] &= ~np.isnan(self.values[slot[hit]])
            if skip_missing:
                slot, value = slot[hit], value[hit]
            elif not hit.all():
                j = int(np.argmin(hit))
                raise ValueError(f"{self.source}: field {name!r} has a value for a cell the data do not have "
                                 f"(position {np.asarray(pos[j]).tolist()}, level {int(level[j])})")
            out[slot] = value
            placed += len(value)
        filled = int(np.count_nonzero(~np.isnan(out)))
        if placed != self.n_cells or filled != self.n_cells:
            raise ValueError(f"{self.source}: field {name!r} gives {placed} values for {filled} of the "
                             f"{self.n_cells} cells (each cell needs exactly one)")
        self.fields[name] = out
        return out

    def __repr__(self):
        return (f"BlockVolume[{self.n_cells} cells in {len(self.level)} blocks of {self.block}^3, "
                f"levels {self.levels.tolist()}, {self.nbytes / max(self.n_cells, 1):.1f} B/cell]")

    # ---- Reading cells back ----------------------------------------------
    def cell_chunks(self, max_cells: int = CHUNK):
        """Yield ``(pos int64 (m, 3), level int32 (m,), value float32 (m,))``
        of the present cells, a few blocks at a time (about ``max_cells``
        cells per chunk), in block order."""
        b3 = self.block ** 3
        step = max(1, max_cells // b3)
        local = block_offsets(self.block)
        for s in range(0, len(self.level), step):
            v = self.values[s * b3:(s + step) * b3].reshape(-1, b3)
            blk, cell = np.nonzero(~np.isnan(v))
            L = self.level[s:s + step][blk].astype(np.int64)
            q = (self.coord[s:s + step][blk].astype(np.int64) << self.log2_block) + local[cell]
            yield (q << L[:, None]) + self.origin, L.astype(np.int32), v[blk, cell]

    def block_chunks(self, max_cells: int = CHUNK):
        """Yield ``(level (k,), coord (k, 3), values (k, B, B, B))`` for a few
        blocks at a time (about ``max_cells`` values), values indexed
        [block, z, y, x] with NaN where there is no cell."""
        b3 = self.block ** 3
        step = max(1, max_cells // b3)
        for s in range(0, len(self.level), step):
            yield (self.level[s:s + step], self.coord[s:s + step],
                   self.values[s * b3:(s + step) * b3].reshape(-1, self.block, self.block, self.block))

    def to_cells(self) -> AMRCells:
        """All cells as an `AMRCells` (per-cell records: for small data and for
        builders that still need them)."""
        parts = list(self.cell_chunks())
        present = ~np.isnan(self.values)          # the cells in the order cell_chunks gives them
        cells = AMRCells(np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]),
                         np.concatenate([p[2] for p in parts]), source=self.source, validate=False,
                         fields={n: a[present] for n, a in self.fields.items()})
        cells.meta = dict(self.meta)
        return cells

    def with_values(self, values) -> "BlockVolume":
        """A volume of the same blocks with other cell ``values`` (laid out
        as ``values``: NaN in the same empty slots, finite elsewhere; the
        caller checks that): what an ``amr`` medium's ``values`` parameter
        builds its structures on after ``params.update()``. Further fields
        and metadata are kept; stored macrocell grids (of the old values)
        are not."""
        values = np.asarray(values, dtype=np.float32)
        if values.shape != self.values.shape:
            raise ValueError(f"{self.source}: {values.size} values for {self.values.size} slots")
        return BlockVolume(self.block, self.level, self.coord, values, self.origin, self.lo, self.hi,
                           self.n_cells, self.source, self.meta, fields=self.fields)

    def value_index(self, pos, level) -> np.ndarray:
        """For each cell ``(pos (N, 3) finest units, level (N,))`` its index
        in ``values`` (int64, -1 for a cell these blocks do not hold, e.g.
        one dropped by ``overlap="finest"``): block ``b``, slot ``s = x + B
        (y + B z)`` of the cell in its block is index ``b B^3 + s``. With
        an `AMRCells` ``c`` from which the volume was made,
        ``values[value_index(c.pos, c.level)] == c.values``."""
        pos = np.asarray(pos, dtype=np.int64).reshape(-1, 3)
        level = np.asarray(level, dtype=np.int64).ravel()
        out = np.full(len(level), -1, dtype=np.int64)
        if not len(level) or not len(self.level):
            return out
        q = (pos - self.origin) >> level[:, None]
        ok = np.all(q >= 0, axis=1) & np.all(((q << level[:, None]) + self.origin) == pos, axis=1)
        qb = np.where(ok[:, None], q, 0) >> self.log2_block
        packed = fits_packed(np.concatenate([self.coord.astype(np.int64), qb]))
        keys = block_keys(self.coord, self.level, packed)
        order = np.argsort(keys)
        k = block_keys(qb, level, packed)
        i = np.minimum(np.searchsorted(keys, k, sorter=order), len(keys) - 1)
        hit = ok & (keys[order[i]] == k)
        slot = slot_index(order[i], np.where(hit[:, None], q, 0), self.block)
        hit &= ~np.isnan(self.values[np.where(hit, slot, 0)])
        out[hit] = slot[hit]
        return out

    def stencil_index(self):
        """Tables for one-probe tent stencils (docs/design.md section 9).

        A stencil ``b + {0,1}^3`` has its cells in the blocks ``block(b) +
        {0,1}^3``. Returns ``(ghost_coord (G, 3), ghost_level (G,),
        neighbours uint32 (K + G, 7))``: *ghosts* are the missing blocks at
        ``coord - d`` (d in {0,1}^3 \\ 0) of every block, so that the block of
        any stencil base with a cell is present or a ghost; ``neighbours[k,
        d - 1]`` is the block at ``coord + d`` (``d = dx + 2 dy + 4 dz``) of
        block k (ghosts numbered after the K blocks), or ``0xFFFFFFFF``."""
        ghost_coord, ghost_level = ghost_blocks(self.coord, self.level)
        coord = self.coord.astype(np.int64)
        packed = fits_packed(coord, 1)
        keys = block_keys(coord, self.level, packed)
        order = np.argsort(keys)
        sorted_keys = keys[order]
        neighbours = np.full((len(self.level) + len(ghost_level), 7), 0xFFFFFFFF, dtype=np.uint32)
        if packed:                                 # (with a margin of one block): an offset adds a constant
            all_keys = np.concatenate([keys, block_keys(ghost_coord, ghost_level, True)])
        else:
            all_coord = np.concatenate([coord, ghost_coord])
            all_level = np.concatenate([self.level, ghost_level])

        def find(d):                               # one column per thread
            k = all_keys + key_offset(UPPER_OFFSETS[d]) if packed else \
                block_keys(all_coord + UPPER_OFFSETS[d], all_level, packed)
            i = np.minimum(np.searchsorted(sorted_keys, k), len(keys) - 1)
            hit = sorted_keys[i] == k
            neighbours[hit, d] = order[i[hit]]
        for _ in ordered_map(find, range(len(UPPER_OFFSETS))):
            pass
        return ghost_coord.astype(np.int32), ghost_level, neighbours

    def lookup(self, level: int, q: np.ndarray):
        """Host point location: ``(value, found)`` of the level-``level``
        cells at level coordinates ``q`` (int (M, 3), relative to ``origin``)."""
        q = np.asarray(q, dtype=np.int64)
        sel = np.nonzero(self.level == level)[0]
        found = np.zeros(len(q), dtype=bool)
        value = np.zeros(len(q), dtype=np.float32)
        if not len(sel):
            return value, found
        keys = block_keys(self.coord[sel], np.full(len(sel), level), False)
        order = np.argsort(keys)
        ok = np.all(q >= 0, axis=1)
        qk = block_keys(np.where(ok[:, None], q, 0) >> self.log2_block, np.full(len(q), level), False)
        i = np.minimum(np.searchsorted(keys, qk, sorter=order), len(sel) - 1)
        hit = ok & (keys[order[i]] == qk)
        blk = sel[order[i]]
        slot = slot_index(blk, q, self.block)
        v = self.values[np.where(hit, slot, 0)]
        found = hit & ~np.isnan(v)
        value[found] = v[found]
        return value, found


def sample_runs(n: int, read):
    """Eight contiguous runs of `SAMPLE` cells spread over ``n`` cells (all of
    them when that is fewer); ``read(start, stop)`` returns one run."""
    if n <= 8 * SAMPLE:
        yield read(0, n)
        return
    for s in np.linspace(0, n - SAMPLE, 8).astype(np.int64):
        yield read(int(s), int(s) + SAMPLE)


def choose_block_size(block_counts: dict, ghost_counts: dict | None = None) -> int:
    """Block size with the fewest resident bytes: for ``K(B)`` blocks,
    ``K (4 B^3 + hash)``, plus, for a reconstruction whose hash needs ghost
    blocks (tent; ``ghost_counts`` given: ``G(B)`` of them), ``(K + G)``
    neighbour rows and ``G`` hash entries (see `BlockVolume.stencil_index`)."""
    cost = {}
    for b, k in block_counts.items():
        cost[b] = k * (4.0 * b ** 3 + HASH_BYTES_PER_BLOCK)
        if ghost_counts is not None:
            g = ghost_counts[b]
            cost[b] += g * HASH_BYTES_PER_BLOCK + (k + g) * NEIGHBOUR_BYTES_PER_BLOCK
    return min(cost, key=cost.get)


def _check_and_measure(pos, level, value):
    """Fast validation of one chunk (levels in range, finite values, corners
    aligned) and its measures ``(lo (3,), hi (3,), max level)``; ``None``
    when anything is wrong (then `check_cells` names the first bad cell).
    Works in the file's int32 where it can: a corner aligned to its width
    ``w`` has ``pos + w - 1 == pos | (w - 1)``, which cannot overflow."""
    level = np.asarray(level)
    if level.dtype.kind not in "iu" or not np.isfinite(value).all():
        return None
    if level.min() < 0 or level.max() > MAX_LEVEL:
        return None
    lv = level.astype(np.int32, copy=False)
    mask = (np.int32(1) << lv) - np.int32(1)
    lo, hi = np.empty(3, np.int64), np.empty(3, np.int64)
    for a in range(3):
        c = pos[:, a]
        if c.dtype.itemsize > 4:
            if np.any((c & mask) != 0):
                return None
            lo[a], hi[a] = c.min(), (c | mask).max() + 1
            continue
        if np.bitwise_and(c, mask).any():
            return None
        lo[a], hi[a] = int(c.min()), int(np.bitwise_or(c, mask).max()) + 1
    return lo, hi, int(lv.max())


def scan_values(values: np.ndarray, level: np.ndarray, block: int, bar=None):
    """One pass over the values of blocks (in threads): ``(present cells,
    (min, max) of the values, present cells weighted by their volume in
    finest cells, cells in blocks that are not full)``."""
    b3 = block ** 3
    step = max(1, CHUNK // b3)

    def scan(s):
        v = values[s * b3:(s + step) * b3].reshape(-1, b3)
        present = np.count_nonzero(v == v, axis=1)               # NaN != NaN
        volume = int((present.astype(np.int64) << (3 * level[s:s + step].astype(np.int64))).sum())
        lo, hi = np.fmin.reduce(v, axis=None), np.fmax.reduce(v, axis=None)   # NaN only if all are
        return int(present.sum()), lo, hi, volume, int(present[present < b3].sum()), len(present) * b3
    n, lo, hi, volume, partial = 0, np.inf, -np.inf, 0, 0
    for m, clo, chi, cvol, cpart, slots in ordered_map(scan, range(0, len(level), step)):
        n, volume, partial = n + m, volume + cvol, partial + cpart
        if m:
            lo, hi = min(lo, float(clo)), max(hi, float(chi))
        if bar is not None:
            bar.update(slots)
    return n, (lo, hi), volume, partial


def _place_checked(chunks, values, keys, origin, packed, b, source, overlap, cell_block_keys) -> int:
    """Place the values chunk by chunk in stream order, finding repeated
    cells: with ``overlap == "error"`` the first one is named, else the
    first cell of a slot is kept. Returns the cells placed."""
    n, start = 0, 0
    for chunk in chunks():
        pos, level, value = _resolve(chunk)
        L = level.astype(np.int64)
        q = (pos.astype(np.int64) - origin) >> L[:, None]
        slot = slot_index(np.searchsorted(keys, cell_block_keys(pos, level, b)), q, b)
        m = len(slot)
        taken = ~np.isnan(values[slot])           # placed by an earlier chunk
        free = np.nonzero(~taken)[0]
        fslot = slot[free]
        _, first = np.unique(fslot, return_index=True)
        lost = np.ones(len(free), dtype=bool)
        lost[first] = False
        if taken.any() or lost.any():
            if overlap == "error":
                dup = taken.copy()
                dup[free[lost]] = True
                i = int(np.argmax(dup))
                raise ValueError(
                    f"{source}: cell {start + i} at {np.asarray(pos[i]).tolist()} (level {int(level[i])}) "
                    "duplicates another cell: cells overlap finer or duplicate cells; pass "
                    "overlap='finest' to keep the finer ones")
            free = free[first]                    # duplicates at one level: keep the first
        values[slot[free]] = np.asarray(value, dtype=np.float32)[free]
        n += len(free)
        start += m
    return n


#: Cells per side of the coarse tiles that `TileIndex` numbers densely: the
#: largest block size, so that every block lies in one tile.
TILE = max(BLOCK_SIZES)
#: A dense tile index holds at most this many tiles, or one per four cells
#: if there are more (its tables take 13 bytes a tile while loading); the
#: per-tile occupancy of the finest candidate blocks at most this many bytes,
#: or four per cell. Beyond that, blocks are found by sorting their keys.
DENSE_ENTRIES = 1 << 24


class TileIndex:
    """A dense numbering of the aligned ``TILE^3``-cell tiles of every level
    over the data's bounding box, to find a cell's block by arithmetic and
    two table reads, in any cell order (docs/design.md section 9, "Loading
    in any order").

    Tile ``t`` of level L at tile coordinate ``(tx, ty, tz)`` (level
    coordinates ``(pos - origin) >> L``, divided by TILE) has the index
    ``offset[L] + (tz * ny[L] + ty) * nx[L] + tx``; ``rank`` maps an index
    to the tile's number among the occupied tiles (-1: none), in index
    order."""

    def __init__(self, lo, hi, origin, lmax: int):
        ext = np.asarray(hi, np.int64) - np.asarray(origin, np.int64)
        self.dims = np.array([np.maximum(1, -(-((ext + (1 << L) - 1) >> L) // TILE)) for L in range(lmax + 1)],
                             dtype=np.int64)                                       # (levels, 3) x, y, z
        sizes = np.prod(self.dims, axis=1)
        self.offset = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        self.total = int(self.offset[-1])
        self.origin = np.asarray(origin, np.int64)
        #: index arithmetic in int32 where the indices fit (half the memory traffic)
        self.itype = np.int32 if self.total < 2**31 else np.int64
        self.offset_t = self.offset[:-1].astype(self.itype)
        self.stride_y = self.dims[:, 0].astype(self.itype)
        self.stride_z = (self.dims[:, 0] * self.dims[:, 1]).astype(self.itype)
        self.rank = None
        self.count = 0

    def index(self, q, level):
        """Tile indices (`itype`) of cells at level coordinates ``q`` (three
        int32 columns) and levels ``level``."""
        lv = np.asarray(level)
        lt = TILE.bit_length() - 1
        i = np.take(self.offset_t, lv)
        i += (q[2] >> lt).astype(self.itype, copy=False) * np.take(self.stride_z, lv)
        i += (q[1] >> lt).astype(self.itype, copy=False) * np.take(self.stride_y, lv)
        i += q[0] >> lt
        return i

    def set_occupied(self, occupied: np.ndarray):
        """``rank`` from a 0/1 array over the tile indices."""
        self.count = int(np.count_nonzero(occupied))
        rank = np.cumsum(occupied, dtype=np.int32)
        rank -= 1
        rank[occupied == 0] = -1
        self.rank = rank

    def coords(self, tiles: np.ndarray):
        """``(coord int64 (m, 3) x y z, level int64 (m,))`` of tile indices."""
        L = np.searchsorted(self.offset, tiles, side="right") - 1
        local = tiles - self.offset[L]
        nx, ny = self.dims[L, 0], self.dims[L, 1]
        return np.stack([local % nx, (local // nx) % ny, local // (nx * ny)], axis=1), L

    def neighbour(self, tiles: np.ndarray, d) -> np.ndarray:
        """Index of the tile at ``coord + d`` (same level) of each tile, or -1
        outside the bounding box."""
        c, L = self.coords(tiles)
        c = c + np.asarray(d, np.int64)
        ok = np.all((c >= 0) & (c < self.dims[L]), axis=1)
        out = self.offset[L] + (c[:, 2] * self.dims[L, 1] + c[:, 1]) * self.dims[L, 0] + c[:, 0]
        return np.where(ok, out, -1)


def _pool(occupied: np.ndarray, s: int) -> np.ndarray:
    """Per-tile occupancy grids (m, s0, s0, s0) [z, y, x] pooled (any) to
    ``s`` sub-blocks per side."""
    m, s0 = occupied.shape[0], occupied.shape[1]
    f = s0 // s
    if f == 1:
        return occupied
    return occupied.reshape(m, s, f, s, f, s, f).any(axis=(2, 4, 6))


def _dense_ghosts(tiles: TileIndex, occupied: np.ndarray) -> int:
    """Ghost blocks (`ghost_blocks`: missing blocks at ``coord - d`` of a
    block, d in {0,1}^3 \\ 0) of the blocks whose per-tile occupancy is
    ``occupied`` (K tiles, s^3 sub-blocks each), counted exactly on dense
    grids: each candidate tile (an occupied tile or a lower neighbour of
    one) is extended by one layer of sub-blocks from its upper neighbours."""
    s = occupied.shape[1]
    occ_tiles = np.flatnonzero(tiles.rank >= 0)
    cand = [occ_tiles]
    for d in UPPER_OFFSETS:
        n = tiles.neighbour(occ_tiles, -d)
        cand.append(n[n >= 0])
    cand = np.unique(np.concatenate(cand))
    padded = np.concatenate([occupied, np.zeros((1, s, s, s), bool)])      # row K: an empty tile
    count = 0
    step = max(1, (1 << 21) // (s + 1) ** 3)
    for a in range(0, len(cand), step):
        c = cand[a:a + step]
        ext = np.zeros((len(c), s + 1, s + 1, s + 1), bool)
        for e in [np.zeros(3, np.int64)] + UPPER_OFFSETS:
            n = tiles.neighbour(c, e)
            r = np.where(n >= 0, tiles.rank[np.maximum(n, 0)], -1)
            r[r < 0] = len(occupied)
            dst = tuple(slice(0, s) if e[a_] == 0 else slice(s, s + 1) for a_ in (2, 1, 0))
            src = tuple(slice(0, s) if e[a_] == 0 else slice(0, 1) for a_ in (2, 1, 0))
            ext[(slice(None),) + dst] = padded[r][(slice(None),) + src]
        up = np.zeros((len(c), s, s, s), bool)
        for d in UPPER_OFFSETS:
            up |= ext[:, d[2]:d[2] + s, d[1]:d[1] + s, d[0]:d[0] + s]
        count += int(np.count_nonzero(up & ~ext[:, :s, :s, :s]))
    return count


def _dense_blocks(tiles: TileIndex, positions, sizes, with_ghosts: bool, n: int, bar=None):
    """Blocks found on the dense tile index, independent of cell order: one
    pass marks the occupied octants (sub-blocks of ``TILE / 2`` cells) of
    each tile; when those are not all full (block-structured data fill
    them, and then no smaller block can hold fewer bytes), one more pass
    marks the occupied sub-blocks of the finest candidate size in each
    tile. Every candidate's block and ghost counts follow exactly. Returns
    ``(B, sub-block occupancy (K, s, s, s) [z, y, x] of the chosen size)``,
    or None when the occupancy grids would exceed `DENSE_ENTRIES`."""
    half = TILE // 2
    lh = half.bit_length() - 1
    octants = np.zeros(tiles.total * 8, np.uint8)
    otype = np.int32 if len(octants) < 2**31 else np.int64
    one = np.int32(1)

    def mark(chunk):
        pos, level, _ = _resolve(chunk)
        q = level_coords(pos, level, tiles.origin)
        i = tiles.index(q, level).astype(otype, copy=False)
        i <<= 3
        i |= (((q[2] >> lh) & one) << 2) | (((q[1] >> lh) & one) << 1) | ((q[0] >> lh) & one)
        octants[i] = 1
        return len(level)
    for m in ordered_map(mark, positions()):
        if bar is not None:
            bar.update(m)
    octants = octants.reshape(tiles.total, 8).view(bool)
    occupied = octants.any(axis=1)
    tiles.set_occupied(occupied.view(np.uint8))
    coarse = octants[occupied].reshape(tiles.count, 2, 2, 2)      # [z, y, x] octants of each occupied tile
    del octants, occupied
    exact = [b for b in sizes if b in (TILE, half)]
    if exact and (len(exact) == len(sizes) or n == np.count_nonzero(coarse) * half ** 3):
        # the octants hold every candidate (or are full: smaller blocks only add headers)
        return _fewest_bytes(tiles, coarse, exact, with_ghosts)
    del coarse
    budget = max(DENSE_ENTRIES, 4 * n)             # bytes of the sub-block occupancy
    usable = [b for b in sorted(sizes) if tiles.count * (TILE // b) ** 3 <= budget]
    if not usable:
        return None
    bmin = usable[0]
    s0 = TILE // bmin
    lb = bmin.bit_length() - 1
    fine = np.zeros(tiles.count * s0 ** 3, np.uint8)
    ftype = np.int32 if len(fine) < 2**31 else np.int64
    mask = np.int32(s0 - 1)

    def mark_fine(chunk):
        pos, level, _ = _resolve(chunk)
        q = level_coords(pos, level, tiles.origin)
        r = tiles.rank[tiles.index(q, level)].astype(ftype, copy=False)
        sub = (((q[2] >> lb) & mask) * np.int32(s0) + ((q[1] >> lb) & mask)) * np.int32(s0) + ((q[0] >> lb) & mask)
        r *= s0 ** 3
        r += sub
        fine[r] = 1
        return len(level)
    if bar is not None and bar.total is not None:
        bar.total += n
    for m in ordered_map(mark_fine, positions()):
        if bar is not None:
            bar.update(m)
    return _fewest_bytes(tiles, fine.reshape(tiles.count, s0, s0, s0).view(bool), usable, with_ghosts)


def _fewest_bytes(tiles: TileIndex, occupied: np.ndarray, sizes, with_ghosts: bool):
    """``(B, occupancy pooled to B)`` for the block size among ``sizes`` with
    the fewest bytes (`choose_block_size`), from per-tile occupancy grids
    ``occupied`` as fine as the smallest size, with exact block (and, when
    ``with_ghosts``, ghost) counts."""
    grids = {b: _pool(occupied, TILE // b) for b in sizes}
    if len(grids) == 1:
        return next(iter(grids.items()))
    counts = {b: int(np.count_nonzero(g)) for b, g in grids.items()}
    ghosts = {b: _dense_ghosts(tiles, g) for b, g in grids.items()} if with_ghosts else None
    b = choose_block_size(counts, ghosts)
    return b, grids[b]


def _build(chunks, lo, hi, lmax, source, overlap, block, sample=None, method="tent", bar=None, positions=None,
           n_cells: int = 0):
    """Choose the block size (from ``sample()``, or the first chunk, for
    the reconstruction ``method``: name or object), then two passes over
    ``chunks()``: the set of blocks (over ``positions()`` when given), then
    the values."""
    origin = (np.asarray(lo, dtype=np.int64) >> lmax) << lmax
    sizes = BLOCK_SIZES if block is None else (int(block),)
    for b in sizes:
        if b < 1 or b & (b - 1):
            raise ValueError(f"{source}: block size must be a power of two, got {b}")
    packed = int(np.max(np.asarray(hi, dtype=np.int64) - origin)) // min(sizes) < (1 << KEY_AXIS_BITS)

    def keys_and_coords(pos, level, b):           # block keys and level coordinates of cells
        q = level_coords(pos, level, origin)
        lb = b.bit_length() - 1
        if packed:
            return packed_keys(q, level, lb), q
        return block_keys(np.stack([c >> lb for c in q], axis=1), level, False), q

    def cell_block_keys(pos, level, b):
        return keys_and_coords(pos, level, b)[0]
    with_ghosts = reconstruction_method(method).needs_ghosts
    dense = None
    tiles = TileIndex(lo, hi, origin, lmax)
    if n_cells and max(sizes) <= TILE and tiles.total <= max(DENSE_ENTRIES, n_cells // 4):
        # ---- Passes 1a, 1b: blocks and block size on the dense tile index (any cell order) ----
        dense = _dense_blocks(tiles, positions or chunks, sizes, with_ghosts, n_cells, bar)
    if dense is not None:
        b, grid = dense
        s = TILE // b
        r, lz, ly, lx = np.nonzero(grid)
        del grid
        tc, tl = tiles.coords(np.flatnonzero(tiles.rank >= 0)[r])
        coord = tc * s + np.stack([lx, ly, lz], axis=1)
        order = np.lexsort((coord[:, 0], coord[:, 1], coord[:, 2], tl)) if packed else \
            np.lexsort((tl, coord[:, 0], coord[:, 1], coord[:, 2]))               # the order of the keys
        coord, blevel = coord[order].astype(np.int32), tl[order].astype(np.uint8)
        keys = block_keys(coord, blevel, packed)
        block_of = np.full(tiles.count * s ** 3, -1, np.int32)                     # (tile, sub-block) -> block
        block_of[((r * s + lz) * s + ly)[order] * s + lx[order]] = np.arange(len(order), dtype=np.int32)
        del r, lz, ly, lx, order, tc, tl
    else:
        # ---- Block size: fewest bytes per cell on the sample ----
        if len(sizes) > 1:
            runs = [_resolve(c) for c in (sample() if sample is not None else [next(iter(chunks()))])]
            counts, ghosts = dict.fromkeys(sizes, 0), dict.fromkeys(sizes, 0)

            def count(job):                           # blocks (and ghosts) of one size on one run, in threads
                b, (p, lv, _) = job
                c, L = unpack_keys(distinct_keys(cell_block_keys(p, lv, b)), packed)
                return b, len(L), len(ghost_blocks(c, L)[1]) if with_ghosts else 0
            for b, k, g in ordered_map(count, [(b, run) for b in sizes for run in runs]):
                counts[b] += k
                ghosts[b] += g
            b = choose_block_size(counts, ghosts if with_ghosts else None)
        else:
            b = sizes[0]
        # ---- Pass 1: the blocks (each chunk's in a thread) ----
        parts = []

        def distinct_blocks(chunk):
            pos, level, _ = _resolve(chunk)
            return distinct_keys(cell_block_keys(pos, level, b)), len(level)
        for part, m in ordered_map(distinct_blocks, (positions or chunks)()):
            parts.append(part)
            if bar is not None:
                bar.update(m)
        keys = distinct_keys(np.concatenate(parts))
        del parts
        coord, blevel = unpack_keys(keys, packed)
        coord, blevel = coord.astype(np.int32), blevel.astype(np.uint8)
    b3 = b ** 3
    if len(keys) * b3 >= 2**32:
        raise ValueError(f"{source}: {len(keys)} blocks of {b}^3 values exceed 2**32 values")
    values = np.full(len(keys) * b3, np.nan, dtype=np.float32)
    # ---- Pass 2: place each cell's value (in threads: a slot is written once
    # unless cells repeat, which the count of placed values reveals) ----
    lb = b.bit_length() - 1
    mask = np.int32(b - 1)

    def place(chunk):
        pos, level, value = _resolve(chunk)
        if dense is not None:                      # block by table reads: no search, any order
            q = level_coords(pos, level, origin)
            r = tiles.rank[tiles.index(q, level)]
            if s == 1 and packed:                  # blocks are the tiles, numbered alike (key order)
                blk = r.astype(np.int64)
            else:
                sm = np.int32(s - 1)
                sub = (((q[2] >> lb) & sm) * np.int32(s) + ((q[1] >> lb) & sm)) * np.int32(s) + ((q[0] >> lb) & sm)
                r = r.astype(np.int32 if len(block_of) < 2**31 else np.int64, copy=False)
                r *= s ** 3
                r += sub
                blk = block_of[r].astype(np.int64)
        else:
            keys_c, q = keys_and_coords(pos, level, b)
            heads = np.flatnonzero(np.r_[True, keys_c[1:] != keys_c[:-1]])     # runs of one block
            blk = np.searchsorted(keys, keys_c[heads])
            blk = np.repeat(blk, np.diff(np.r_[heads, len(keys_c)]))
        local = (q[0] & mask) | ((q[1] & mask) << lb) | ((q[2] & mask) << (2 * lb))
        values[(blk << (3 * lb)) | local] = value
        return len(value)

    n = 0
    for m in ordered_map(place, chunks()):
        n += m
        if bar is not None:
            bar.update(m)
    if bar is not None and bar.total is not None:
        bar.total += len(values)                   # the scan of the values below
    placed, value_range, volume, partial = scan_values(values, blevel, b, bar)
    if placed != n:                               # repeated cells: place again, in order, chunk by chunk
        values[:] = np.nan
        n = _place_checked(chunks, values, keys, origin, packed, b, source, overlap, cell_block_keys)
        placed, value_range, volume, partial = scan_values(values, blevel, b)
    box = int(np.prod(np.asarray(hi, np.int64) - np.asarray(lo, np.int64)))
    vol = BlockVolume(b, blevel, coord, values, origin, np.asarray(lo, np.int64), np.asarray(hi, np.int64),
                      n, source, value_range=value_range, cell_counts=(volume == box, partial))
    removed = _remove_overlaps(vol, overlap)
    if removed:                                   # coarse cells dropped: bounds and range may shrink
        vol.n_cells -= removed
        keep = ~np.isnan(vol.values.reshape(len(vol.level), -1)).all(axis=1)
        if not keep.all():                        # drop blocks left empty
            vol.values = np.ascontiguousarray(vol.values.reshape(len(keep), -1)[keep]).reshape(-1)
            vol.level, vol.coord = vol.level[keep], vol.coord[keep]
        lo, hi = np.full(3, np.iinfo(np.int64).max), np.full(3, np.iinfo(np.int64).min)
        for pos, level, _ in vol.cell_chunks():
            lo = np.minimum(lo, pos.min(axis=0))
            hi = np.maximum(hi, (pos + (np.int64(1) << level.astype(np.int64))[:, None]).max(axis=0))
        vol.lo, vol.hi = lo, hi
        vol._update_range()
        vol._covers = None                        # counted again on first use
    return vol


def _under_coarse_cells(vol: BlockVolume, fine, coarse, k: int):
    """The fine blocks (and their ancestor blocks ``coarse``, ``k`` levels
    up) whose region holds at least one coarse cell: only their cells can
    be covered. A fine block spans ``max(1, B >> k)^3`` cells of its
    ancestor level, looked up in threads."""
    b = vol.block
    s = max(1, b >> k)
    local = block_offsets(s)
    step = max(1, CHUNK // len(local))

    def any_present(start):
        f, c = fine[start:start + step], coarse[start:start + step]
        q = ((vol.coord[f].astype(np.int64) << vol.log2_block) >> k)[:, None, :] + local[None]   # (m, s^3, 3)
        slot = slot_index(np.repeat(c, len(local)), q.reshape(-1, 3), b)
        return (vol.values[slot] == vol.values[slot]).reshape(len(f), -1).any(axis=1)             # not NaN
    keep = np.concatenate([np.zeros(0, bool)] + list(ordered_map(any_present, range(0, len(fine), step))))
    return fine[keep], coarse[keep]


def _remove_overlaps(vol: BlockVolume, overlap: str) -> int:
    """Find coarse cells that cover finer ones, level pair by level pair:
    a fine block whose ancestor block (at the coarse level) does not exist
    cannot overlap; the others are checked cell by cell. With ``overlap ==
    "error"`` raise, else clear the coarse cells. Returns the cells removed."""
    levels = vol.levels
    removed = 0
    b, b3 = vol.block, vol.block ** 3
    local = block_offsets(b)
    for Lc in levels[1:]:
        csel = np.nonzero(vol.level == Lc)[0]
        ckeys = block_keys(vol.coord[csel], np.full(len(csel), Lc), False)
        corder = np.argsort(ckeys)
        for Lf in levels[levels < Lc]:
            k = int(Lc - Lf)
            fsel = np.nonzero(vol.level == Lf)[0]
            anc = block_keys(vol.coord[fsel] >> k, np.full(len(fsel), Lc), False)
            i = np.minimum(np.searchsorted(ckeys, anc, sorter=corder), len(csel) - 1)
            match = ckeys[corder[i]] == anc
            cand, cblock = fsel[match], csel[corder[i[match]]]     # fine blocks and their ancestor block
            cand, cblock = _under_coarse_cells(vol, cand, cblock, k)
            step = max(1, CHUNK // b3)

            def covered(s, k=k, cand=cand, cblock=cblock):          # in threads: nothing is written
                blocks, anc_block = cand[s:s + step], cblock[s:s + step]
                v = vol.values.reshape(-1, b3)[blocks]
                bi, ci = np.nonzero(~np.isnan(v))
                q = (vol.coord[blocks][bi].astype(np.int64) << vol.log2_block) + local[ci]
                slot = slot_index(anc_block[bi], q >> k, b)             # the coarse cell over each fine one
                return q, slot, ~np.isnan(vol.values[slot])
            # tested in threads, removed here in order: a coarse cell that an
            # earlier chunk removed is tested again, so it is counted once
            for q, slot, hit in ordered_map(covered, range(0, len(cand), step)):
                if hit.any():
                    hit &= ~np.isnan(vol.values[slot])
                if not hit.any():
                    continue
                if overlap == "error":
                    j = int(np.argmax(hit))
                    cpos = ((q[j] >> k) << Lc) + vol.origin
                    raise ValueError(
                        f"{vol.source}: cells overlap finer or duplicate cells (first: the level-{int(Lc)} "
                        f"cell at {cpos.tolist()} covers a level-{int(Lf)} cell); pass overlap='finest' "
                        "to keep the finer ones")
                slot = np.unique(slot[hit])
                removed += len(slot)
                vol.values[slot] = np.nan
    return removed


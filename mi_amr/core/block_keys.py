"""Block keys and stencil tables: the integer bookkeeping of aligned blocks.

A cell at level L has level coordinates ``q = (pos - origin) >> L`` (x, y,
z; finest-level units ``pos``, `mi_amr.data.blocks`); its block of ``B^3``
cells is ``q >> log2(B)`` and its slot inside the block ``x + B (y + B z)``.
Blocks are named by sortable keys (`block_keys`): one int64 when every
coordinate fits `KEY_AXIS_BITS` bits, else 16 bytes. The tent
reconstruction's one-probe stencils need each block's upper neighbours
(`UPPER_OFFSETS`) and the missing lower ones (`ghost_blocks`). Nothing here
imports the rest of mi-amr: the blocks, the reconstruction methods and the
estimates of memory all build on it.
"""

from __future__ import annotations

import numpy as np


#: Block offsets d = (dx, dy, dz) for d = dx + 2 dy + 4 dz = 1..7.
UPPER_OFFSETS = [np.array([d & 1, (d >> 1) & 1, (d >> 2) & 1], dtype=np.int64) for d in range(1, 8)]


def ghost_blocks(coord: np.ndarray, level: np.ndarray):
    """The missing blocks at ``coord - d`` (d in `UPPER_OFFSETS`, same level)
    of the given blocks: ``(coord int64 (G, 3), level (G,))``, distinct, in
    key order."""
    coord = np.asarray(coord, dtype=np.int64)
    level = np.asarray(level)
    if not fits_packed(coord):
        keys = np.unique(block_keys(coord, level, False))
        cand_c = np.concatenate([coord - off for off in UPPER_OFFSETS])
        cand_l = np.tile(level, len(UPPER_OFFSETS))
        ok = np.all(cand_c >= 0, axis=1)
        cand_k, first = np.unique(block_keys(cand_c[ok], cand_l[ok], False), return_index=True)
        ghost = ~np.isin(cand_k, keys)
        return cand_c[ok][first[ghost]], cand_l[ok][first[ghost]]
    # packed keys: a same-level offset is a constant in key space, and
    # sorted keys minus a constant stay sorted, so the candidates are seven
    # sorted runs (a stable sort merges them) searched in the sorted keys
    keys = np.sort(block_keys(coord, level, True))
    c, _ = unpack_keys(keys, True)
    runs = [keys[np.all(c >= off, axis=1)] - key_offset(off) for off in UPPER_OFFSETS]
    cand = np.sort(np.concatenate(runs), kind="stable")
    if len(cand):
        cand = cand[np.r_[True, cand[1:] != cand[:-1]]]
    i = np.minimum(np.searchsorted(keys, cand), max(len(keys) - 1, 0))
    ghosts = cand[keys[i] != cand] if len(keys) else cand
    g_coord, g_level = unpack_keys(ghosts, True)
    return g_coord, g_level.astype(level.dtype, copy=False)


def key_offset(off) -> np.int64:
    """What a same-level block offset ``off`` (x, y, z) adds to a packed key."""
    return np.int64(int(off[0]) | (int(off[1]) << KEY_AXIS_BITS) | (int(off[2]) << (2 * KEY_AXIS_BITS)))


def block_offsets(b: int) -> np.ndarray:
    """Cell offsets (x, y, z) inside a ``b^3`` block, in storage order (x fastest)."""
    return np.stack(np.unravel_index(np.arange(b ** 3), (b,) * 3, order="F"), axis=1)


def slot_index(blk, q, b: int):
    """Index in the values of cell ``q`` (level coordinates) of block ``blk``."""
    loc = q & (b - 1)
    return blk * b ** 3 + loc[:, 0] + b * (loc[:, 1] + b * loc[:, 2])


#: Bits per axis of a packed int64 block key (5 bits hold the level).
KEY_AXIS_BITS = 19


def block_keys(coord: np.ndarray, level: np.ndarray, packed: bool = True) -> np.ndarray:
    """One sortable key per (block coordinate, level): packed into int64
    when every coordinate is below ``2**KEY_AXIS_BITS``, else a 16-byte void
    (big-endian rows, so byte order is numeric order)."""
    coord = np.asarray(coord)
    if packed:
        c = coord.astype(np.int64)
        return ((np.asarray(level, dtype=np.int64) << (3 * KEY_AXIS_BITS)) | (c[:, 2] << (2 * KEY_AXIS_BITS))
                | (c[:, 1] << KEY_AXIS_BITS) | c[:, 0])
    rows = np.empty((len(level), 4), dtype=">i4")
    rows[:, :3] = coord[:, ::-1]
    rows[:, 3] = level
    return np.ascontiguousarray(rows).view(np.dtype((np.void, 16))).ravel()


def fits_packed(coord: np.ndarray, margin: int = 0) -> bool:
    """Whether block coordinates (plus ``margin``) fit packed int64 keys
    (sorting and searching those is much faster than 16-byte keys)."""
    return not len(coord) or int(coord.max()) + margin < (1 << KEY_AXIS_BITS)


def unpack_keys(keys: np.ndarray, packed: bool):
    """Inverse of `block_keys`: ``(coord int64 (K, 3), level int64 (K,))``."""
    if packed:
        m = (1 << KEY_AXIS_BITS) - 1
        return (np.stack([keys & m, (keys >> KEY_AXIS_BITS) & m, (keys >> (2 * KEY_AXIS_BITS)) & m], axis=1),
                keys >> (3 * KEY_AXIS_BITS))
    rows = keys.view(">i4").reshape(-1, 4).astype(np.int64)
    return rows[:, 2::-1].copy(), rows[:, 3]


def distinct_keys(keys: np.ndarray) -> np.ndarray:
    """Sorted distinct keys; runs of equal neighbours (cells of one block
    stored together, as codes write them) are collapsed before sorting."""
    if len(keys) > 1:
        keys = keys[np.r_[True, keys[1:] != keys[:-1]]]
    return np.unique(keys)


def level_coords(pos, level, origin):
    """Level coordinates ``(pos - origin) >> level`` as three int32 columns
    (x, y, z). The differences lie in [0, 2^31) (bounds are checked before),
    so int32 arithmetic that wraps gives them exactly."""
    lv = np.asarray(level).astype(np.int32, copy=False)
    out = []
    for a in range(3):
        o = int(origin[a])
        o = np.int32(((o + 2**31) % 2**32) - 2**31)          # origin modulo 2^32, as int32
        c = pos[:, a]
        if c.dtype != np.int32:
            c = (c.astype(np.int64) - int(origin[a])).astype(np.int32)
        else:
            with np.errstate(over="ignore"):
                c = c - o
        out.append(np.right_shift(c, lv))
    return out


def packed_keys(q, level, lb: int) -> np.ndarray:
    """Packed int64 block keys (see `block_keys`) of level coordinates ``q``
    (three int32 columns) for blocks of ``2^lb`` cells per side."""
    key = np.asarray(level).astype(np.int64) << (3 * KEY_AXIS_BITS)
    key |= (q[2] >> lb).astype(np.int64) << (2 * KEY_AXIS_BITS)
    key |= (q[1] >> lb).astype(np.int64) << KEY_AXIS_BITS
    key |= q[0] >> lb
    return key

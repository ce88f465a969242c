"""Open-addressing hash tables of integer coordinates, one per level.

Point location keys the blocks of a `BlockVolume` by their level-L block
coordinate (`mi_amr.device.hash_sampler.BlockHash`): a lookup costs O(1)
expected probes regardless of the data size. The tables are built once on
the host (numpy) and probed in Dr.Jit with the same hash function.
"""

from __future__ import annotations

import numpy as np


#: Bits per axis in a packed ("narrow") 64-bit key. Levels whose coordinates
#: reach 2**KEY_BITS use "wide" keys: ``qx | qy << 32`` in 64 bits plus ``qz``
#: in a second 32-bit array, enough for any AMRCells (extents < 2**31).
KEY_BITS = 21
WIDE_KEY_BITS = 31
EMPTY_KEY = np.uint64(0xFFFFFFFFFFFFFFFF)
MAX_LEVELS = 32
#: Device bytes of one slot (`mi_amr.device.hash_sampler.DeviceReconstruction`):
#: the 64-bit key and the payload widened to 64 bits beside it, or (wide
#: keys) the key, its ``z`` and the payload.
SLOT_BYTES = 16


def hash_u32(qx, qy, qz):
    """32-bit spatial hash of integer coordinates (numpy or Dr.Jit UInt32).

    Wrapping uint32 arithmetic, written so that numpy and Dr.Jit give the
    same bits: a multiply-xor combine followed by a murmur-style finaliser.
    """
    h = (qx * 73856093) ^ (qy * 19349663) ^ (qz * 83492791)
    h = h ^ (h >> 16)
    h = h * 0x7FEB352D
    h = h ^ (h >> 15)
    h = h * 0x846CA68B
    h = h ^ (h >> 16)
    return h


def pack_key(qx, qy, qz, wide: bool = False):
    """64-bit key of unsigned level coordinates (numpy uint64 or Dr.Jit
    UInt64): exact with KEY_BITS bits per axis; with ``wide``, ``qx | qy << 32``
    (``qz`` is then compared separately)."""
    if wide:
        return qx | (qy << 32)
    return qx | (qy << KEY_BITS) | (qz << (2 * KEY_BITS))


class LevelHash:
    """Open-addressing hash tables, one per level, stored back to back,
    mapping integer level coordinates to a payload.

    Attributes (host, numpy)
    ------------------------
    keys : uint64 (S,), payload : (S,)
        Slots of all tables; empty slots hold ``EMPTY_KEY``.
    wide : bool
        Whether some level coordinate reaches ``2**KEY_BITS``; then ``keys``
        hold ``qx | qy << 32`` and ``keys_z`` (uint32 (S,)) the ``qz``.
    coord_limit : int
        Level coordinates must lie in ``[0, coord_limit)``.
    offset, mask : uint32 (MAX_LEVELS,)
        Start and capacity - 1 of the table of each level.
    level_bits : int
        Bit L set when level L has entries.
    max_probe : int
        Longest probe sequence any lookup (hit or miss) can take.
    """

    def __init__(self, entries: dict, payload_dtype, source: str, load_factor: float = 0.35):
        self.offset = np.zeros(MAX_LEVELS, dtype=np.uint32)
        self.mask = np.zeros(MAX_LEVELS, dtype=np.uint32)
        self.level_bits = 0
        entries = {L: (np.asarray(q, dtype=np.int64).reshape(-1, 3), data) for L, (q, data) in entries.items()}
        qmax = max((int(q.max()) for q, _ in entries.values() if q.size), default=0)
        self.wide = qmax >= (1 << KEY_BITS)
        self.coord_limit = 1 << (WIDE_KEY_BITS if self.wide else KEY_BITS)
        keys, keys_z, payload, max_probe, total = [], [], [], 1, 0
        for L, (q, data) in sorted(entries.items()):
            if q.size and (q.min() < 0 or q.max() >= self.coord_limit):
                raise ValueError(
                    f"{source}: level {L} spans {int(q.max()) + 1} cells per axis; "
                    f"at most {self.coord_limit} are supported")
            n = len(q)
            cap = 1 << max(4, int(np.ceil(np.log2(n / load_factor))))
            k, kz, v, probes = _build_table(q.astype(np.uint64), np.asarray(data, dtype=payload_dtype),
                                            cap, self.wide)
            keys.append(k)
            keys_z.append(kz)
            payload.append(v)
            max_probe = max(max_probe, probes)
            self.offset[L] = total
            self.mask[L] = cap - 1
            self.level_bits |= 1 << int(L)
            total += cap
        self.keys = np.concatenate(keys)
        self.keys_z = np.concatenate(keys_z) if self.wide else np.zeros(1, np.uint32)
        self.payload = np.concatenate(payload)
        self.max_probe = max_probe

    @property
    def nbytes(self) -> int:
        return self.keys.nbytes + self.payload.nbytes + (self.keys_z.nbytes if self.wide else 0)

    def lookup(self, level: int, q: np.ndarray):
        """Host lookup: ``(payload, found)`` for int (M, 3) level coordinates ``q``."""
        q = np.asarray(q, dtype=np.int64)
        ok = np.all((q >= 0) & (q < self.coord_limit), axis=1)
        qu = np.where(ok[:, None], q, 0).astype(np.uint64)
        key = pack_key(qu[:, 0], qu[:, 1], qu[:, 2], self.wide)
        h = hash_u32(*(qu[:, i].astype(np.uint32) for i in range(3)))
        found = np.zeros(len(q), dtype=bool)
        val = np.zeros(len(q), dtype=self.payload.dtype)
        if not (self.level_bits >> level) & 1:
            return val, found
        pending = np.nonzero(ok)[0]
        for p in range(self.max_probe):
            if not len(pending):
                break
            slot = self.offset[level] + ((h[pending] + np.uint32(p)) & self.mask[level])
            k = self.keys[slot]
            hit = k == key[pending]
            if self.wide:
                hit &= self.keys_z[slot] == qu[pending, 2].astype(np.uint32)
            found[pending[hit]] = True
            val[pending[hit]] = self.payload[slot[hit]]
            pending = pending[~hit & (k != EMPTY_KEY)]
        return val, found


def _build_table(q: np.ndarray, values: np.ndarray, cap: int, wide: bool):
    """Linear-probing insertion of all (distinct) keys, vectorised over
    rounds. Returns ``(keys, keys_z, values, max_probe)``."""
    keys = np.full(cap, EMPTY_KEY, dtype=np.uint64)
    keys_z = np.zeros(cap, dtype=np.uint32)
    vals = np.zeros(cap, dtype=values.dtype)
    key = pack_key(q[:, 0], q[:, 1], q[:, 2], wide)
    home = hash_u32(*(q[:, i].astype(np.uint32) for i in range(3))) & np.uint32(cap - 1)
    pending = np.arange(len(key))
    probe = np.zeros(len(key), dtype=np.int64)
    while len(pending):
        slot = (home[pending].astype(np.int64) + probe[pending]) & (cap - 1)
        free = keys[slot] == EMPTY_KEY
        cand = pending[free]
        cslot = slot[free]
        _, first = np.unique(cslot, return_index=True)   # one winner per free slot
        win = cand[first]
        keys[cslot[first]] = key[win]
        keys_z[cslot[first]] = q[win, 2]
        vals[cslot[first]] = values[win]
        placed = np.zeros(len(key), dtype=bool)
        placed[win] = True
        rest = pending[~placed[pending]]
        probe[rest] += 1
        pending = rest
    # A miss stops at the first empty slot: bound by the longest occupied run.
    occ = keys != EMPTY_KEY
    longest = _longest_cyclic_run(occ)
    return keys, keys_z, vals, int(max(probe.max() + 1, longest + 1))


def _longest_cyclic_run(occ: np.ndarray) -> int:
    if occ.all():
        raise ValueError("hash table is full")
    # rotate so that the array starts right after an empty slot
    start = int(np.argmin(occ))
    o = np.roll(occ, -start).astype(np.int8)
    edges = np.diff(np.concatenate([[0], o, [0]]))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    return int((ends - starts).max()) if len(starts) else 0

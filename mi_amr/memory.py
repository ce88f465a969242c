"""Memory budget: estimates of what a structure will need, checked before the
allocation, so that data too large for this machine give a clear error
instead of a crash in the middle of a build.

The limit is ``MI_AMR_MEMORY_LIMIT`` (bytes, or with a K/M/G/T suffix) when
set, else half of the physical memory. Estimates are peak host bytes per
item, measured with ``tracemalloc`` on 2e5-cell data sets (with margin).
"""

from __future__ import annotations

import os

ENV_VAR = "MI_AMR_MEMORY_LIMIT"

#: Peak build bytes per cell of each structure (measured, rounded up).
BYTES_PER_CELL = {
    "cells": 160,          # AMRCells validation (keys, sorting): 80 measured
}
#: Peak bytes of the region-tree build per (node, box) pair of a depth
#: (coordinates, face tests, the next depth's pairs), per leaf list entry
#: and per node (its box, the node arrays, the final tree): fitted to
#: tracemalloc peaks of ABRs and brick trees on cloud and blocks data.
BYTES_PER_TREE_PAIR = 150
BYTES_PER_TREE_ITEM = 16
BYTES_PER_TREE_NODE = 100
#: Bytes per macrocell: host ranges and level mask, device copies, majorants.
BYTES_PER_MACROCELL = 48
#: Cells read per chunk when streaming (`mi_amr.data.blocks`), and per chunk of
#: the builds that read blocks back: small enough that the chunks in flight on
#: every core stay a few bytes per cell at 10^7 cells.
CHUNK = 1 << 20


def load_bytes(n_cells: int, chunk: int = CHUNK) -> float:
    """Peak host bytes of streaming ``n_cells`` into a `BlockVolume`: the
    values (about 8 B per cell; block-structured data take 4) and one
    chunk's temporaries (measured 56-67 B per chunk cell with the dense
    tile index of `mi_amr.data.blocks.TileIndex`; 120-200 B when blocks
    are found by sorting)."""
    return 8.0 * n_cells + 80.0 * min(n_cells, chunk)


#: Peak bytes per macrocell of a macrocell grid build: its arrays, and the
#: dense coarse levels' minimum and maximum reduced at once (two threads):
#: fitted to tracemalloc peaks on cloud and blocks data (30-72 measured).
BYTES_PER_GRID_MACROCELL = 48


def grid_bytes(n_macrocells: int, n_values: int) -> float:
    """Peak host bytes of a macrocell grid build: its arrays, the dense
    levels' reductions and the chunks of block reductions in flight
    (``n_values``: the value slots of the blocks, or the cells)."""
    return BYTES_PER_GRID_MACROCELL * float(n_macrocells) + 12.0 * min(n_values, CHUNK)


def hash_bytes(n_blocks: int, method) -> float:
    """Peak host bytes of the block hash for the reconstruction ``method``
    (a `mi_amr.reconstruction.Reconstruction`; keys, payload and build
    rounds, and the ghost blocks and neighbour rows of a method that needs
    them), without the device copy of the values:
    ``method.hash_bytes_per_block`` per block."""
    return method.hash_bytes_per_block * n_blocks


class MemoryLimitError(MemoryError):
    """A structure would need more memory than the limit allows."""


def physical_memory() -> int:
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8 << 30


def parse_bytes(text: str) -> float:
    """``"512M"``, ``"2G"``, ``"1e9"`` -> bytes."""
    t = str(text).strip().upper().removesuffix("B").removesuffix("I")
    mult = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}
    if t and t[-1] in mult:
        return float(t[:-1]) * mult[t[-1]]
    return float(t)


def default_memory_limit() -> float:
    if os.environ.get(ENV_VAR):
        try:
            v = parse_bytes(os.environ[ENV_VAR])
        except ValueError:
            raise ValueError(f"{ENV_VAR}={os.environ[ENV_VAR]!r} is not a number of bytes "
                             "(e.g. 2G, 512M, 1e9)") from None
        if not v > 0:
            raise ValueError(f"{ENV_VAR} must be > 0, got {os.environ[ENV_VAR]!r}")
        return v
    return physical_memory() / 2


def format_bytes(n: float) -> str:
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"


def require(nbytes: float, what: str, limit: float | None = None, hint: str = ""):
    """Raise `MemoryLimitError` when ``what`` needs more than ``limit`` bytes."""
    limit = default_memory_limit() if limit is None else limit
    if nbytes > limit:
        raise MemoryLimitError(
            f"{what} needs about {format_bytes(nbytes)}, more than the memory limit of "
            f"{format_bytes(limit)} ({ENV_VAR} or the medium's memory_limit)"
            + (f"; {hint}" if hint else ""))


def bricks_bytes(n_cells: int, partial_block_cells: int) -> float:
    """Peak host bytes of cutting bricks from the blocks: full blocks are cut
    with no per-cell arrays (about 5 B per cell measured), cells of partial
    blocks are grouped one by one (about 80 B each)."""
    return 6.0 * n_cells + 80.0 * partial_block_cells


def structure_bytes(kind: str, n_cells: int) -> float:
    return BYTES_PER_CELL[kind] * float(n_cells)
